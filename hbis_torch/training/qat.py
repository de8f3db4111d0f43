"""Quantisation-aware fine-tuning: the network as onnxruntime runs its int8 file, in torch.

Calibrated int8 (:mod:`hbis_torch.training.quantize`) loses most where the classical image is
already clean: the network only adds a small correction, and rounding its features to 8 bits
changed its output by about 1e-3 rms (h = 4, a calibration-pool stack). :class:`QuantSim`
computes what the int8 file computes, with the same rounding at the same tensors, so that
training through it (``qat=True`` in training/train_sr.py) teaches the network to work with that
rounding; the ranges it trained with are then the int8 file's (:func:`ranges_metadata`, read by
:func:`hbis_torch.training.quantize.quantize_model`).

Which tensors are rounded, as onnxruntime's static QDQ quantisation of a plain network
(:class:`~hbis_torch.training.net.ResidualBlock`) leaves them, the first convolution and the
final sum kept in float32 (:func:`hbis_torch.training.quantize.float_nodes`)::

    head      the first convolution's output                          uint8, own range
    relu{i}   block i's ReLU (its first convolution fused with it)     uint8, [0, max]
    conv{i}   block i's second convolution's output                    uint8, own range
    add{i}    block i's output (input + second convolution)            uint8, own range
    body      head + the blocks' output                                uint8, own range
    tail      the last convolution's output, the correction            uint8, own range

Weights of every convolution but the first: int8, per output channel, symmetric. Ranges are
fixed at the start (:func:`observe_ranges`: the calibration pool's 0.001st and 99.999th
percentiles, as the calibration of :mod:`~hbis_torch.training.quantize`); rounding passes
gradients straight through inside its range (``torch.fake_quantize_per_tensor_affine``).
"""

from __future__ import annotations

import json
import re

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from hbis_torch.training.net import HbisSRNet, depth_to_space

PERCENTILE = 99.999  # as CALIBRATION_METHOD "percentile" of hbis_torch.training.quantize
METADATA_KEY = "quantization_ranges"  # the float file's metadata entry: JSON of tensor name -> [rmin, rmax]


def tensor_names(blocks: int) -> list[str]:
    """The rounded tensors of a network of ``blocks`` blocks, in the order it computes them."""
    names = ["head"]
    for i in range(blocks):
        names += [f"relu{i}", f"conv{i}", f"add{i}"]
    return names + ["body", "tail"]


def scale_and_zero_point(rmin: float, rmax: float) -> tuple[float, int]:
    """uint8 scale and zero point of a range, by onnxruntime's own arithmetic (the range widened
    to hold 0, 255 steps over it)."""
    from onnxruntime.quantization.quant_utils import compute_scale_zp

    zero, scale = compute_scale_zp(np.float32(rmin), np.float32(rmax), np.uint8(0), np.uint8(255))
    return float(scale), int(zero)


def fake_quant_weight(weight: Tensor) -> Tensor:
    """Per-output-channel symmetric int8 rounding of a convolution's weight (C_out, C_in, k, k)."""
    absmax = weight.detach().abs().amax(dim=(1, 2, 3)).clamp_min(1e-12)
    scale = (absmax / 127.0).float()
    zero = torch.zeros_like(scale, dtype=torch.int32)
    return torch.fake_quantize_per_channel_affine(weight, scale, zero, 0, -127, 127)


class QuantSim(nn.Module):
    """A plain :class:`~hbis_torch.training.net.HbisSRNet` with the int8 file's rounding.

    Parameters
    ----------
    net : HbisSRNet
        Its weights are trained through this module (they stay float32).
    ranges : dict of str to (float, float)
        (rmin, rmax) of every name of :func:`tensor_names` (:func:`observe_ranges`).

    Notes
    -----
    ``forward(base (B, h^2, H, W), noise (B, 1, H, W)) -> (B, 1, hH, hW)``, as the network's.
    """

    def __init__(self, net: HbisSRNet, ranges: dict):
        super().__init__()
        if net.architecture.kind != "plain":
            raise ValueError(f"quantisation-aware training takes plain networks, not {net.architecture.kind!r}")
        missing = set(tensor_names(net.blocks)) - set(ranges)
        if missing:
            raise ValueError(f"ranges lack {sorted(missing)}")
        self.net = net
        self.ranges = {name: (float(lo), float(hi)) for name, (lo, hi) in ranges.items()}
        # fixed with the ranges: computed once, not at every tensor of every training step
        self.scale_zero = {name: scale_and_zero_point(*bounds) for name, bounds in self.ranges.items()}

    def _round(self, name: str, x: Tensor) -> Tensor:
        scale, zero = self.scale_zero[name]
        return torch.fake_quantize_per_tensor_affine(x, scale, zero, 0, 255)

    def forward(self, base: Tensor, noise: Tensor) -> Tensor:
        return _plain_forward(self.net, base, noise, self._round, lambda conv: fake_quant_weight(conv.weight))


def _plain_forward(net: HbisSRNet, base: Tensor, noise: Tensor, at, weight) -> Tensor:
    """A plain network's forward pass, ``at(name, x)`` applied to each tensor of
    :func:`tensor_names` and ``weight(conv)`` giving every convolution's weight but the first's."""
    features = at("head", net.head(torch.cat((base - 0.5, noise), dim=1)))
    x = features
    for i, block in enumerate(net.body):
        inner = at(f"relu{i}", F.relu(F.conv2d(x, weight(block.conv1), block.conv1.bias, padding=1)))
        branch = at(f"conv{i}", F.conv2d(inner, weight(block.conv2), block.conv2.bias, padding=1))
        x = at(f"add{i}", x + branch)
    body = at("body", features + x)
    correction = at("tail", F.conv2d(body, weight(net.tail), net.tail.bias, padding=1))
    return depth_to_space(base + correction, net.h)


@torch.no_grad()
def observe_ranges(net: HbisSRNet, feeds: list[dict], percentile: float = PERCENTILE) -> dict:
    """(rmin, rmax) of every rounded tensor of ``net`` (float32, no rounding) over ``feeds``.

    Parameters
    ----------
    net : HbisSRNet
        A plain network.
    feeds : list of dict
        ``{"base": (1, h^2, S, S), "noise": (1, 1, S, S)}`` arrays
        (:func:`hbis_torch.training.quantize.calibration_inputs`).
    percentile : float
        Each range spans the values' (100 - percentile)th to percentile-th percentile, over all feeds.

    Returns
    -------
    dict of str to (float, float)
    """
    values: dict[str, list[Tensor]] = {name: [] for name in tensor_names(net.blocks)}

    def record(name: str, x: Tensor) -> Tensor:
        values[name].append(x.flatten())
        return x

    net = net.eval()
    for feed in feeds:
        base, noise = (torch.as_tensor(feed[k]) for k in ("base", "noise"))
        _plain_forward(net, base, noise, record, lambda conv: conv.weight)
    ranges = {}
    for name, parts in values.items():
        every = torch.cat(parts).numpy()
        lo, hi = np.percentile(every, [100.0 - percentile, percentile])
        ranges[name] = (float(lo), float(hi))
    return ranges


def ranges_metadata(ranges: dict) -> str:
    """The float file's :data:`METADATA_KEY` entry: JSON of name -> [rmin, rmax]."""
    return json.dumps({name: [float(lo), float(hi)] for name, (lo, hi) in ranges.items()})


def onnx_tensor_ranges(model, ranges: dict) -> dict[str, tuple[float, float]]:
    """The ranges keyed by the ONNX graph's tensor names, found from the weights each node reads.

    Parameters
    ----------
    model : onnx.ModelProto
        The float file of a plain network (exported by :mod:`hbis_torch.training.export`, whose
        convolutions read initializers named ``head.weight``, ``body.{i}.conv1.weight``, ...; a
        first convolution split in two is found by its sum, ``SPLIT_HEAD_ADD``).
    ranges : dict of str to (float, float)
        As :func:`observe_ranges`.

    Returns
    -------
    dict of str to (float, float)
        ONNX tensor name -> (rmin, rmax), for onnxruntime's ``TensorQuantOverrides``.

    Raises
    ------
    ValueError
        A rounded tensor not found in the graph.
    """
    from hbis_torch.training.onnx_rewrite import SPLIT_HEAD_ADD  # onnx, a second and a half to import: only here
    producer_of = {}  # our name -> ONNX tensor
    conv_out = {}  # ONNX tensor -> our name of the convolution
    for node in model.graph.node:
        if node.op_type == "Conv":
            weight = node.input[1]
            if weight == "head.weight":
                producer_of["head"] = node.output[0]
                conv_out[node.output[0]] = "head"
            elif weight == "tail.weight":
                producer_of["tail"] = node.output[0]
            elif weight.startswith("body.") and weight.endswith(".conv1.weight"):
                conv_out[node.output[0]] = f"conv1_{weight.split('.')[1]}"
            elif weight.startswith("body.") and weight.endswith(".conv2.weight"):
                i = weight.split(".")[1]
                producer_of[f"conv{i}"] = node.output[0]
                conv_out[node.output[0]] = f"conv{i}"
        elif node.op_type == "Add" and node.name == SPLIT_HEAD_ADD:  # the split first convolution's sum
            producer_of["head"] = node.output[0]
            conv_out[node.output[0]] = "head"
        elif node.op_type == "Relu" and conv_out.get(node.input[0], "").startswith("conv1_"):
            producer_of[f"relu{conv_out[node.input[0]].split('_')[1]}"] = node.output[0]
        elif node.op_type == "Add":
            names = {conv_out.get(t) for t in node.input}
            block = [n for n in names if n and re.fullmatch(r"conv\d+", n)]
            if block:
                producer_of[f"add{block[0][4:]}"] = node.output[0]
            elif "head" in names:
                producer_of["body"] = node.output[0]
    missing = [name for name in ranges if name not in producer_of]
    if missing:
        raise ValueError(f"tensors {missing} not found in the ONNX graph")
    return {producer_of[name]: tuple(ranges[name]) for name in ranges}
