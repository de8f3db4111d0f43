"""The network in torch for training: it is defined with the learned method
(:mod:`hbis_torch.reconstruct.learned.network`, where the bursts' test-time adaptation builds it
too); this module adds what only training does with it (:func:`count_parameters`,
:func:`grow_net`) and keeps the names training, export and the tests import from here."""

from __future__ import annotations

import torch
from torch import nn

from hbis_torch.reconstruct.learned.architecture import Architecture
from hbis_torch.reconstruct.learned.network import (BLOCKS, HbisSRNet, InvertedResidual, ResidualBlock, build_net,
                                                    depth_to_space, space_to_depth)

__all__ = ["BLOCKS", "HbisSRNet", "InvertedResidual", "ResidualBlock", "build_net", "count_parameters",
           "depth_to_space", "grow_net", "space_to_depth"]


def count_parameters(model: nn.Module) -> int:
    """Number of trainable parameters."""
    return sum(p.numel() for p in model.parameters() if p.requires_grad)


def grow_net(small: HbisSRNet, architecture: Architecture) -> HbisSRNet:
    """A wider and/or deeper plain network that computes exactly what ``small`` computes.

    The function-preserving growth of Net2Net (Chen, Goodfellow and Shlens, ICLR 2016), in its
    simplest form: ``small``'s weights fill the first ``small.width`` channels of the larger
    network's first ``small.blocks`` blocks; the new channels are read by nothing the old ones
    feed (their weights into old channels and into the tail are zero), and the new blocks' last
    convolution starts at zero, so they are identities. The new weights that are not zero keep
    :func:`build_net`'s random initialisation, so training moves them at once. A larger network
    then starts at the smaller one's held-out quality instead of at the classical image's.

    Parameters
    ----------
    small : HbisSRNet
        The trained network, plain kind.
    architecture : Architecture
        Of the grown network: the same h and kind, width and blocks at least ``small``'s.

    Returns
    -------
    HbisSRNet
        Training mode, float32; the random part drawn from torch's global generator.

    Raises
    ------
    HbisInputError
        Another h or kind, or a width or depth smaller than ``small``'s.
    """
    from hbis_torch.errors import HbisInputError

    old = small.architecture
    if (architecture.h, architecture.kind, old.kind) != (old.h, "plain", "plain") or \
            architecture.width < old.width or architecture.blocks < old.blocks:
        raise HbisInputError(f"cannot grow {old} into {architecture}: the same h, plain blocks, "
                             "and a width and depth at least the smaller network's")
    big, w = build_net(architecture), old.width
    with torch.no_grad():
        big.head.weight[:w].copy_(small.head.weight)
        big.head.bias[:w].copy_(small.head.bias)
        for block, source in zip(big.body, small.body):
            for conv, src in ((block.conv1, source.conv1), (block.conv2, source.conv2)):
                conv.weight[:w, :w].copy_(src.weight)
                conv.weight[:w, w:].zero_()  # old channels read no new one
                conv.bias[:w].copy_(src.bias)
        for block in list(big.body)[old.blocks:]:
            block.conv2.weight.zero_()
            block.conv2.bias.zero_()
        big.tail.weight.zero_()
        big.tail.weight[:, :w].copy_(small.tail.weight)
        big.tail.bias.copy_(small.tail.bias)
    return big
