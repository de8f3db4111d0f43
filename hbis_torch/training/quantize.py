"""int8 versions of the shipped SR models: static QDQ quantisation calibrated on the training pool.

:func:`quantize_model` turns any model file of the ``hbis-sr-onnx/2`` format (the shipped
``hbis_sr_h{h}.onnx``, or any other a training run exported) into its int8 file
(:func:`~hbis_torch.reconstruct.learned.runtime.int8_path`: ``NAME.int8.onnx`` beside it), which the learned method runs by default
where it is faster (``hbis reconstruct --precision``, :mod:`hbis_torch.reconstruct.learned.runtime`).

How it is quantised, and why
----------------------------
* **Static, QDQ format** (``onnxruntime.quantization.quantize_static``): every convolution's
  input and output pass through QuantizeLinear/DequantizeLinear pairs, which onnxruntime fuses
  into integer convolutions; the activations' scales are fixed by calibration, not measured per
  run, so nothing is computed at run time beyond the integer convolutions.
* **Per-channel int8 weights, uint8 activations** (onnxruntime's fast path on x86: u8 x s8).
* **Calibrated on the training pool** (:func:`calibration_inputs`: whole examples of
  :func:`hbis_torch.training.data.build_pool` at the model's h, from a seed stream of their own,
  so neither the training's nor the held-out photographs' stacks), each activation's range to
  its 99.999th percentile (:data:`CALIBRATION_METHOD`).
* **Ranges from quantisation-aware training** where the float file has them (its
  ``quantization_ranges`` entry, :mod:`hbis_torch.training.qat`): the network was fine-tuned
  through the int8 file's rounding with those ranges, so they replace the calibrated ones
  (onnxruntime's ``TensorQuantOverrides``).
* **The image path stays float32** (:func:`float_nodes`): the network only adds a small
  correction to its input (:mod:`hbis_torch.training.net`), so the final ``Add`` of the input
  and the correction, and the ``DepthToSpace`` after it, are left out of the quantisation, and so
  is the first convolution, which reads the image. An image rounded to 8 bits would lose about a
  quarter of a dB at the 47 dB the models reach. The features rounded to 8 bits of their own
  ranges cost more than that in the cleanest stacks unless the network was fine-tuned for the
  rounding (:mod:`hbis_torch.training.qat`).

The int8 file keeps the model's ``metadata_props`` and adds ``precision`` (``int8``),
``quantized_from`` (the float file's name and SHA-256) and ``calibration`` (JSON: the pool's
seed, count, size and method). export/quantize_int8.py is the command line;
export/check_int8.py checks a model against its int8 file on the held-out matrix, cell by cell;
:func:`float_activations` writes an int8 file's twin without the activations' rounding, which
splits its loss between the rounding at run time and its weights (``check_int8.py
--float-activations``).
"""

from __future__ import annotations

import hashlib
import json
import tempfile
from pathlib import Path

import numpy as np

from hbis_torch.errors import HbisInputError
from hbis_torch.io_utils import atomic_path
from hbis_torch.reconstruct.learned.runtime import check_model, int8_path
from hbis_torch.training import qat

CALIBRATION_SEED = 31_000  # a pool seed of its own: neither training's (0, 1) nor the tests'
CALIBRATION_COUNT = 48  # pool examples
CALIBRATION_METHOD = "percentile"  # ranges to the 99.999th percentile: on the held-out matrix at h = 4, 9 cells
# beyond 0.05 dB against 12 for min/max over 16 examples and 22 for min/max over 48 (export/check_int8.py)
CALIBRATION_SIDE = 192  # output pixels on a side of each example (LR side: this / h, at least 24)


def calibration_inputs(h: int, count: int = CALIBRATION_COUNT, seed: int = CALIBRATION_SEED,
                       size: int | None = None) -> list[dict]:
    """The network's inputs for ``count`` training-pool examples at factor ``h``.

    Each example gives two feeds, one with the noise of its sensor model and one with the noise
    measured on its lattice (the runtime sees either, :func:`hbis_torch.training.data.whole_example`).

    Returns
    -------
    list of dict
        ``{"base": (1, h^2, S, S), "noise": (1, 1, S, S)}``, float32; S = ``size`` (default: a
        the LR side of :data:`CALIBRATION_SIDE` output pixels, at least 24).
    """
    from hbis_torch.training.data import build_pool, whole_example

    size = size or max(24, CALIBRATION_SIDE // h)
    feeds = []
    for example in build_pool(h, count, size, seed):
        for measured in (False, True):
            base, noise, _ = whole_example(example, h, measured_noise=measured)
            feeds.append({"base": base, "noise": noise})
    return feeds


def float_nodes(model) -> list[str]:
    """Names of the nodes kept in float32.

    * The first convolution (both halves and their sum where it is split,
      :func:`~hbis_torch.training.onnx_rewrite.split_head_conv`) and everything before it: its
      input holds the classical image and the noise map in one tensor, and one 8-bit scale over
      both would round the image to steps of several hundredths (activations have one scale per
      tensor). It is the cheapest convolution (h^2 + 1 input channels), so keeping it float costs
      little.
    * The ``Add`` that takes the graph input ``base`` directly (the residual sum of the input and
      the correction) and every node after it.
    """
    from hbis_torch.training.onnx_rewrite import SPLIT_HEAD_ADD  # onnx, a second and a half to import: only here

    graph = model.graph
    keep, after = [], set()
    head_seen = False
    split = any(node.name == SPLIT_HEAD_ADD for node in graph.node)  # the head is two convolutions and their sum
    for node in graph.node:  # the graph is topologically sorted
        if not head_seen:
            keep.append(node.name)
            head_seen = node.name == SPLIT_HEAD_ADD if split else node.op_type == "Conv"
        elif (node.op_type == "Add" and "base" in node.input) or any(name in after for name in node.input):
            keep.append(node.name)
            after.update(node.output)
    return keep


class _Reader:
    """onnxruntime's CalibrationDataReader over a list of feeds."""

    def __init__(self, feeds: list[dict]):
        self.feeds = iter(feeds)

    def get_next(self):
        return next(self.feeds, None)


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def quantize_model(model, out=None, *, count: int = CALIBRATION_COUNT, seed: int = CALIBRATION_SEED,
                   method: str = CALIBRATION_METHOD, overwrite: bool = False) -> Path:
    """Write the int8 file of an ``hbis-sr-onnx/2`` model (static QDQ, per-channel weights).

    Parameters
    ----------
    model : path
        The float32 model file.
    out : path, optional
        Where to write it (default ``NAME.int8.onnx`` beside it).
    count : int
        Training-pool examples to calibrate on (:func:`calibration_inputs`).
    seed : int
        The calibration pool's seed.
    method : {"minmax", "percentile", "entropy"}
        How the activations' ranges are calibrated.
    overwrite : bool
        Replace an existing ``out``; else an existing file is refused.

    Returns
    -------
    Path
        ``out``.

    Raises
    ------
    HbisInputError
        Not an hbis SR model, already int8, or ``out`` exists without ``overwrite``.
    """
    import onnx
    from onnxruntime.quantization import CalibrationMethod, QuantFormat, QuantType, quantize_static
    from onnxruntime.quantization.shape_inference import quant_pre_process

    path, metadata = check_model(model)
    if metadata.get("precision", "fp32") != "fp32":
        raise HbisInputError(f"{path} is {metadata['precision']} already; quantise its float32 file")
    out = Path(out) if out is not None else int8_path(path)
    if out.exists() and not overwrite:
        raise HbisInputError(f"{out} exists; pass overwrite (--overwrite) to replace it")
    methods = {"minmax": CalibrationMethod.MinMax, "percentile": CalibrationMethod.Percentile,
               "entropy": CalibrationMethod.Entropy}
    if method not in methods:
        raise HbisInputError(f"unknown calibration method {method!r} (choose from {', '.join(methods)})")
    h = int(metadata["h"])
    feeds = calibration_inputs(h, count, seed)
    float_model = onnx.load(str(path))
    options = {"ActivationSymmetric": False, "WeightSymmetric": True}
    trained_ranges = metadata.get(qat.METADATA_KEY)
    if trained_ranges:  # the ranges the network was fine-tuned with, not the calibration's
        ranges = qat.onnx_tensor_ranges(float_model, json.loads(trained_ranges))
        options["TensorQuantOverrides"] = {name: [{"rmin": np.float32(lo), "rmax": np.float32(hi)}]
                                           for name, (lo, hi) in ranges.items()}
    with tempfile.TemporaryDirectory() as tmp:
        prepared, quantized = Path(tmp) / "prepared.onnx", Path(tmp) / "int8.onnx"
        quant_pre_process(str(path), str(prepared), skip_symbolic_shape=True)
        quantize_static(str(prepared), str(quantized), _Reader(feeds), quant_format=QuantFormat.QDQ,
                        per_channel=True, activation_type=QuantType.QUInt8, weight_type=QuantType.QInt8,
                        calibrate_method=methods[method], nodes_to_exclude=float_nodes(float_model),
                        extra_options=options)
        result = onnx.load(str(quantized))
    del result.metadata_props[:]
    calibration = {"pool_seed": seed, "count": count, "size": int(feeds[0]["base"].shape[-1]), "method": method,
                   "feeds": "each example with its sensor model's and its measured noise",
                   "activation_ranges": "quantisation-aware training's" if trained_ranges else "calibrated"}
    for key, value in {**metadata, "precision": "int8", "quantized_from": f"{path.name} sha256 {_sha256(path)}",
                       "calibration": json.dumps(calibration)}.items():
        result.metadata_props.add(key=key, value=str(value))
    with atomic_path(out) as tmp:
        onnx.save(result, str(tmp))
    return out


def float_activations(model, out) -> Path:
    """Write the twin of an int8 QDQ file whose activations are not rounded: each activation's
    QuantizeLinear/DequantizeLinear pair becomes a Clip to the range the pair represents,
    ``[(q_min - zero point) scale, (q_max - zero point) scale]`` (0 and 255 for uint8).

    The twin computes what the int8 file does but in float32 between the clips: its weights
    (int8, per channel), the clipping of its activations (the pairs also stand for the ReLUs,
    which the quantiser folds into them), not the 8-bit steps. Its loss against the float
    model is the weights' part of the int8 file's; the rest is the rounding's.

    Parameters
    ----------
    model : path
        An int8 file (:func:`quantize_model`'s).
    out : path
        Where to write the twin (an existing file is refused).

    Returns
    -------
    Path
        ``out``.
    """
    import onnx
    from onnx import helper, numpy_helper

    path, metadata = check_model(model)
    if metadata.get("precision") != "int8":
        raise HbisInputError(f"{path} is not an int8 file")
    out = Path(out)
    if out.exists():
        raise HbisInputError(f"{out} exists; choose another path")
    int8 = onnx.load(str(path))
    graph = int8.graph
    constants = {t.name: numpy_helper.to_array(t) for t in graph.initializer}
    dequantize = {n.input[0]: n for n in graph.node if n.op_type == "DequantizeLinear"}
    nodes, paired = [], set()
    for node in graph.node:
        if node.op_type == "QuantizeLinear":  # activations only: the weights are stored quantised
            pair = dequantize[node.output[0]]
            paired.add(pair.name)
            scale, zero = float(constants[node.input[1]]), constants[node.input[2]]
            steps = np.iinfo(zero.dtype)
            limits = [f"{node.name}_min", f"{node.name}_max"]
            for name, value in zip(limits, ((steps.min - int(zero)) * scale, (steps.max - int(zero)) * scale)):
                graph.initializer.append(numpy_helper.from_array(np.array(value, np.float32), name))
            nodes.append(helper.make_node("Clip", [node.input[0], *limits], [pair.output[0]],
                                          name=f"{node.name}_clip"))
        else:
            nodes.append(node)
    nodes = [node for node in nodes if node.name not in paired]  # the pairs' DequantizeLinear
    used = {name for node in nodes for name in node.input}
    kept = [t for t in graph.initializer if t.name in used]  # not the pairs' scales and zero points
    del graph.node[:], graph.initializer[:]
    graph.node.extend(nodes)
    graph.initializer.extend(kept)
    onnx.checker.check_model(int8)
    with atomic_path(out) as tmp:
        onnx.save(int8, str(tmp))
    return out
