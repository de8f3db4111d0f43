"""Network variants of the research A/B (training/variants_ab.py) and of its cost benchmark
(benchmarks/bench_variant_cost.py): how a variant is written and built.

A variant is ``name:width:blocks:blur[:body]`` (:data:`VARIANT_FORMAT`): the residual body's
width and depth, whether the network is told the lens's blur width lambda F / p (1 / cutoff, LR
pixels) as a second conditioning channel beside the noise map (1) or not (0), and the body's
blocks, an :class:`~hbis_torch.reconstruct.learned.architecture.Architecture` kind (``plain``, the
shipped design and the default, or ``ir``, inverted residuals). :func:`make_variant` builds it
through :func:`~hbis_torch.training.net.build_net`, so every variant starts from the same seed.
"""

from __future__ import annotations

import torch

from hbis_torch.reconstruct.learned.architecture import KINDS, Architecture
from hbis_torch.training.net import HbisSRNet, build_net

PATCH = 32  # LR side of a training crop, as train_sr.py
VARIANT_FORMAT = "name:width:blocks:blur[:" + "|".join(KINDS) + "]"  # one variant of --variants


def parse_variants(text: str) -> list[tuple[str, int, int, bool, str]] | None:
    """``name:width:blocks:blur[:body],...`` as (name, width, blocks, blur, body) tuples; None if malformed."""
    variants = []
    for spec in text.split(","):
        fields = spec.split(":")
        if len(fields) == 4:
            fields.append("plain")
        if len(fields) != 5 or fields[3] not in ("0", "1") or fields[4] not in KINDS:
            return None
        name, width, blocks, blur, body = fields
        if not (width.isdigit() and blocks.isdigit()):
            return None
        variants.append((name, int(width), int(blocks), blur == "1", body))
    return variants


def macs_per_pixel(model: torch.nn.Module) -> int:
    """Multiply-adds per LR pixel of the network's convolutions (each weight is used once per pixel)."""
    return sum(m.weight.numel() for m in model.modules() if isinstance(m, torch.nn.Conv2d))


def make_variant(h: int, width: int, blocks: int, blur: bool, body: str = "plain") -> HbisSRNet:
    """The network of a variant, from seed 0.

    Parameters
    ----------
    h : int
        Resolution improvement factor.
    width, blocks : int
    blur : bool
        Its head takes one more input channel, the blur width map (B, 1, H, W) after the noise
        map; that channel's weights start at zero, so the variant starts as the one without it.
    body : {"plain", "ir"}
        The :class:`~hbis_torch.reconstruct.learned.architecture.Architecture` kind.

    Returns
    -------
    HbisSRNet
    """
    torch.manual_seed(0)
    model = build_net(Architecture(h, width=width, blocks=blocks, kind=body))
    if blur:
        head = torch.nn.Conv2d(h * h + 2, width, 3, padding=1)
        with torch.no_grad():
            head.weight.zero_()
            head.weight[:, :h * h + 1] = model.head.weight
            head.bias.copy_(model.head.bias)
        model.head = head
    return model
