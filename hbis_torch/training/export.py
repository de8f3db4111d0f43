"""ONNX export of the SR network, and the parity check of torch against onnxruntime.

:func:`export_model` writes a trained :class:`~hbis_torch.training.net.HbisSRNet` to ONNX
(opset :data:`OPSET`, dynamic batch, height and width; self-contained: weights inside, no .data
file), with the exporter's depth-to-space replaced by one ``DepthToSpace`` node
(:func:`hbis_torch.training.onnx_rewrite.fuse_depth_to_space`), the first convolution split in
two from h = 4 (:func:`~hbis_torch.training.onnx_rewrite.split_head_conv`) and ``metadata_props``
carrying what a user of the model needs: ``format``, ``h``, ``frames`` (= h^2),
``normalisation``, ``training_commit`` (git HEAD when the checkpoint was trained),
``export_commit``, ``opset``, ``parameters``, ``model_config`` (the network's
:class:`~hbis_torch.reconstruct.learned.architecture.Architecture` as JSON: h, width, blocks,
kind; the runtime sizes its tiles' halo from it), ``val_psnr_db`` and
``val_classical_psnr_db`` (the network's and the classical image's PSNR on the validation set: a
model that gains less than 0.1 dB is not used,
:func:`~hbis_torch.reconstruct.learned.domain.unhelpful_model`),
``training_steps``, ``training_config`` (JSON), ``training_domain`` (JSON: the optics and noise the
training spanned, :mod:`hbis_torch.reconstruct.learned.domain`) and ``graph_rewrites``; a
network fine-tuned for its int8 file also ``quantization_ranges`` (JSON, the activation ranges it
trained with, :mod:`hbis_torch.training.qat`), which the int8 file then takes.

:func:`check_parity` compares the raw network outputs of torch and onnxruntime on random inputs
at a size other than the export size (:data:`CHECK_SIZE`); :data:`TOLERANCE` is the largest
absolute difference accepted. The scripts export/export_onnx.py and export/check_onnx.py are
the command lines over these functions.
"""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import numpy as np
import torch

from hbis_torch.io_utils import atomic_path
from hbis_torch.reconstruct.learned import MODEL_FORMAT, NORMALISATION, LearnedSR, available_providers
from hbis_torch.training import qat
from hbis_torch.training.data import training_domain
from hbis_torch.training.net import HbisSRNet, build_net, count_parameters
from hbis_torch.training.onnx_rewrite import fuse_depth_to_space, split_head_conv

OPSET = 18
EXPORT_SIZE = (32, 40)  # (H, W) of the example inputs traced at export; any size runs after
TOLERANCE = 1e-4  # largest accepted |torch - onnxruntime| of the network outputs (images in [0, 1])
CHECK_SIZE = (45, 67)  # deliberately not EXPORT_SIZE, and odd


def git_head() -> str:
    """``git rev-parse HEAD`` of the repository holding this file, or "unknown"."""
    try:
        return subprocess.run(
            ["git", "rev-parse", "HEAD"], cwd=Path(__file__).resolve().parent,
            capture_output=True, text=True, check=True,
        ).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def load_weights(path) -> dict:
    """A checkpoint dict read with ``torch.load(weights_only=True)``: no pickle code runs.

    A file that needs more than tensors, numbers, strings, lists and dicts (an object that only
    pickle can rebuild) is refused in one :class:`~hbis_torch.errors.HbisInputError` line.
    """
    import pickle

    from hbis_torch.errors import HbisInputError

    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except FileNotFoundError:
        raise HbisInputError(f"{path}: no such file") from None
    except pickle.UnpicklingError as exc:
        text = str(exc)
        if "GLOBAL" not in text and "global" not in text:  # not a class to rebuild: a damaged file
            raise HbisInputError(f"{path}: not a readable checkpoint (the file is damaged or of another kind)") from None
        detail = next((line.strip() for line in text.splitlines() if "GLOBAL" in line or "global" in line), "")[:160]
        raise HbisInputError(f"{path}: refused: the file needs pickle to load, which could run code; a checkpoint "
                             f"holds only tensors, numbers, strings, lists and dicts ({detail})") from None
    except (RuntimeError, OSError, EOFError, ValueError) as exc:
        raise HbisInputError(f"{path}: not a readable checkpoint ({type(exc).__name__}: "
                             f"{(str(exc).strip().splitlines() or [''])[0][:160]})") from None
    if not isinstance(ckpt, dict) or "model" not in ckpt or "model_config" not in ckpt:
        raise HbisInputError(f"{path}: not a checkpoint (a dict with 'model' and 'model_config')")
    return ckpt


def load_checkpoint(path) -> tuple[HbisSRNet, dict]:
    """The model (eval mode, float32) and the raw checkpoint dict.

    Parameters
    ----------
    path : str or Path
        A ``model.pt`` / ``ckpt.pt`` written by training/train_sr.py, or a weights file written
        by ``export/export_onnx.py --weights``: a dict with ``model`` (state dict) and
        ``model_config`` (the network's :class:`~hbis_torch.reconstruct.learned.architecture.Architecture`
        as a dict; one without ``kind`` is the plain kind).

    Returns
    -------
    model : HbisSRNet
    checkpoint : dict

    Raises
    ------
    HbisInputError
        For a file that is missing, corrupt, or needs pickle to load: it is read with
        ``weights_only=True`` (tensors, numbers, strings, lists and dicts only), so a shared
        checkpoint cannot run code.
    """
    ckpt = load_weights(path)
    model = build_net(ckpt["model_config"])
    model.load_state_dict(ckpt["model"])
    return model.eval(), ckpt


def example_inputs(h: int, rows: int, cols: int, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """A random classical image (1, h^2, rows, cols) in [0, 1] and noise map (1, 1, rows, cols) in [0, 1].

    Parameters
    ----------
    h : int
        Resolution improvement factor of the network.
    rows, cols : int
        LR size of the inputs, pixels.
    seed : int
        Seed of the torch generator: the same seed gives the same inputs.

    Returns
    -------
    base : Tensor, shape (1, h^2, rows, cols), float32
    noise : Tensor, shape (1, 1, rows, cols), float32
    """
    g = torch.Generator().manual_seed(seed)
    base = torch.rand(1, h * h, rows, cols, generator=g)
    noise = torch.rand(1, 1, rows, cols, generator=g)
    return base, noise


def export_model(model: HbisSRNet, out_path, info: dict | None = None, opset: int = OPSET,
                 rewrite: bool = True) -> dict:
    """Export ``model`` to ``out_path`` (written atomically); returns the metadata written.

    ``info`` is the training checkpoint (or any dict) with ``git_commit``, ``val_psnr``,
    ``history`` or ``val_classical_psnr`` (:func:`classical_val_psnr`), ``step``, ``config`` and
    ``training_domain``; missing entries are recorded as unknown (the
    domain as the current pipeline's, :func:`~hbis_torch.training.data.training_domain`).
    ``rewrite``: replace the exporter's reshape/transpose depth-to-space with ONNX DepthToSpace
    (:func:`hbis_torch.training.onnx_rewrite.fuse_depth_to_space`) and, from h = 4, split the
    first convolution (:func:`~hbis_torch.training.onnx_rewrite.split_head_conv`); same outputs,
    faster in onnxruntime.

    Parameters
    ----------
    model : HbisSRNet
        Inputs ``base`` (B, h^2, H, W) and ``noise`` (B, 1, H, W), output ``image``
        (B, 1, hH, hW); B, H and W stay dynamic in the file.
    out_path : str or Path
        The .onnx file to write.
    info : dict, optional
    opset : int
    rewrite : bool

    Returns
    -------
    dict of str to str
        The ``metadata_props`` written (see the module docstring).
    """
    import onnx

    info = info or {}
    model = model.eval()
    base, noise = example_inputs(model.h, *EXPORT_SIZE)
    batch, rows, cols = (torch.export.Dim(n, min=1, max=8192) for n in ("batch", "height", "width"))
    dims = {0: batch, 2: rows, 3: cols}
    program = torch.onnx.export(
        model, (base, noise), input_names=["base", "noise"], output_names=["image"],
        dynamic_shapes={"base": dims, "noise": dims}, opset_version=opset, dynamo=True,
        external_data=False, verbose=False,
    )
    proto = program.model_proto
    fused = fuse_depth_to_space(proto, model.h) if rewrite else 0
    split = split_head_conv(proto) if rewrite else 0
    metadata = {
        "format": MODEL_FORMAT,
        "h": str(model.h),
        "frames": str(model.h * model.h),
        "normalisation": NORMALISATION,
        "training_commit": str(info.get("git_commit", "unknown")),
        "export_commit": git_head(),
        "opset": str(opset),
        "parameters": str(count_parameters(model)),
        **model.architecture.to_metadata(),
        "val_psnr_db": f"{float(info.get('val_psnr', float('nan'))):.3f}",
        "val_classical_psnr_db": f"{classical_val_psnr(info):.3f}",
        "training_steps": str(info.get("step", "unknown")),
        "training_config": json.dumps(info.get("config", {})),
        "training_domain": json.dumps(info.get("training_domain") or training_domain()),
        "graph_rewrites": f"DepthToSpace x{fused}" + (", split head" if split else ""),
    }
    if info.get("qat_ranges"):  # trained for its int8 file's rounding: the ranges it trained with
        metadata[qat.METADATA_KEY] = qat.ranges_metadata(info["qat_ranges"])
    del proto.metadata_props[:]
    for key, value in metadata.items():
        proto.metadata_props.add(key=key, value=value)
    proto.doc_string = f"hbis-torch SR refiner of the classical image, h = {model.h}; see hbis_torch/models/README.md"
    onnx.checker.check_model(proto)
    with atomic_path(out_path) as tmp:
        onnx.save(proto, str(tmp))
        tmp.chmod(0o644)
    return metadata


def classical_val_psnr(info: dict) -> float:
    """The classical image's PSNR on the validation set (dB): ``val_classical_psnr``, else the
    ``base_psnr`` of the training history (the same at every step); NaN if neither is there."""
    if "val_classical_psnr" in info:
        return float(info["val_classical_psnr"])
    history = info.get("history") or []
    return float(history[-1]["base_psnr"]) if history else float("nan")


def training_info(ckpt: dict) -> dict:
    """What :func:`export_model` records about training, from a training checkpoint or from a
    weights file written by ``--weights`` (hbis_torch/models/hbis_sr_h*.pt), whose ``metadata`` is that of
    the first export: a re-export keeps the training commit, validation PSNR, steps and config.

    Returns
    -------
    dict
        ``git_commit``, ``val_psnr`` and ``val_classical_psnr`` (dB), ``step``, ``config`` and
        ``training_domain`` where known (a training checkpoint is returned as it is).
    """
    if "metadata" not in ckpt:
        return ckpt
    meta = ckpt["metadata"]
    return {"git_commit": meta.get("training_commit", "unknown"),
            "val_psnr": float(meta.get("val_psnr_db", "nan")),
            "val_classical_psnr": float(meta.get("val_classical_psnr_db", "nan")),
            "step": meta.get("training_steps", "unknown"),
            "config": json.loads(meta.get("training_config", "{}")),
            "training_domain": json.loads(meta.get("training_domain", "null")),
            **({"qat_ranges": json.loads(meta[qat.METADATA_KEY])} if qat.METADATA_KEY in meta else {})}


def export(checkpoint, out_path, opset: int = OPSET) -> dict:
    """Export a checkpoint written by training/train_sr.py, or a weights file written by
    ``--weights``; returns the metadata written (:func:`export_model`)."""
    model, ckpt = load_checkpoint(checkpoint)
    return export_model(model, out_path, training_info(ckpt), opset)


def check_parity(onnx_path, checkpoint, size=CHECK_SIZE, seed: int = 1, provider: str = "auto") -> float:
    """Max abs(torch - onnxruntime) of the raw network outputs on random inputs of ``size``.

    ``checkpoint`` is a model.pt path or the HbisSRNet itself; ``provider`` the onnxruntime
    execution provider (:func:`hbis_torch.reconstruct.learned.execution_providers`).

    Parameters
    ----------
    onnx_path : str or Path
        The exported model.
    checkpoint : str, Path or HbisSRNet
    size : (int, int)
        (H, W) of the random inputs (:func:`example_inputs`), LR pixels; not :data:`EXPORT_SIZE`.
    seed : int
        Seed of the inputs.
    provider : str
        ``"auto"``, ``"cpu"`` or ``"openvino"``.

    Returns
    -------
    float
        The largest absolute difference of the two (1, 1, hH, hW) outputs (images in [0, 1]).

    Raises
    ------
    ValueError
        ``size`` is the export size (the check would not test the dynamic axes).
    AssertionError
        The two outputs differ in shape.
    """
    if tuple(size) == tuple(EXPORT_SIZE):
        raise ValueError("check at a size other than the export size")
    model = checkpoint if isinstance(checkpoint, torch.nn.Module) else load_checkpoint(checkpoint)[0]
    model = model.eval()
    base, noise = example_inputs(model.h, *size, seed=seed)
    with torch.no_grad():
        expected = model(base, noise).numpy()
    runner = LearnedSR(onnx_path, provider=provider)
    got = runner.infer(base.numpy(), noise.numpy())
    if got.shape != expected.shape:
        raise AssertionError(f"onnxruntime output {got.shape} != torch output {expected.shape}")
    return float(np.abs(got - expected).max())


def check_parity_all(onnx_path, checkpoint, size=CHECK_SIZE) -> dict[str, float]:
    """:func:`check_parity` for every execution provider this onnxruntime has, by name."""
    return {provider: check_parity(onnx_path, checkpoint, size, provider=provider)
            for provider in available_providers()}
