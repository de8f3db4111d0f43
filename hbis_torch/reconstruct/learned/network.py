"""A small network that refines the classical reconstruction, conditioned on the noise level.

Design (why it looks like this)
-------------------------------
The network does not see the frames: it sees what the classical method made of them. The
classical data step (:func:`hbis_torch.reconstruct.classical.classical_sr`: normalized convolution
of every sample at its exact position, then a Wiener filter built from the stack's optics,
fill factor and measured noise) already uses what the network cannot infer well from a patch:
where each sample sits (any reference frame, any scan, any place on the sensor), the lens's
cutoff and the noise power. The network is the learned prior on top (the split of USRNet, Zhang,
Van Gool and Timofte, CVPR 2020, with one unfolded step): it removes the Wiener filter's noise
and ringing and restores what a linear filter cannot, told how noisy the frames are by a
per-pixel noise map (as in FFDNet).

It works on the low-resolution grid, where it is h^2 times cheaper than on the output grid::

    base  (B, h^2, H, W) -- the classical image, space-to-depth by h, minus 0.5
    noise (B, 1, H, W)   -- per LR pixel, the frames' noise standard deviation (frames in
                            [0, 1]) times ``NOISE_SCALE`` (10, see
                            :func:`~hbis_torch.reconstruct.learned.network_inputs`)
      -> 3x3 conv -> residual blocks -> 3x3 conv to h^2 channels
      -> added to the base, depth-to-space: the image (B, 1, h H, h W)

The last convolution starts at zero, so an untrained network returns the classical image
exactly, and training only learns a correction: a stack unlike any in training degrades towards
the classical method rather than away from it.

One model per h: the channel counts (h^2 + 1 in, h^2 out) and the depth-to-space factor are h
itself. Only plain operators are used (Conv, Relu, Add, Sub, Reshape, Transpose), so the model
exports to ONNX with dynamic height and width. Depth-to-space and space-to-depth are written as
reshape/permute because the dynamo ONNX exporter mistranslates ``pixel_unshuffle``.

All tensors are float32: the classical image it refines is rounded to float32 too, and the
correction is small next to it.

Its size and the kind of its residual blocks are one
:class:`~hbis_torch.reconstruct.learned.architecture.Architecture`; :func:`build_net` is the one
way the build side (training, export, the variants' A/B) and the bursts' test-time adaptation
(:mod:`hbis_torch.reconstruct.learned.adapt`, which fine-tunes it in PyTorch) make the network from
it. Running a shipped model needs none of this: onnxruntime runs the exported file.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from hbis_torch.reconstruct.learned.architecture import IR_EXPAND, Architecture


def space_to_depth(x: Tensor, block: int) -> Tensor:
    """Rearrange ``block x block`` tiles into channels, like ``F.pixel_unshuffle``.

    Parameters
    ----------
    x : Tensor, shape (B, C, H * block, W * block)
    block : int

    Returns
    -------
    Tensor, shape (B, C * block^2, H, W)
        Channel ``c * block^2 + dy * block + dx`` holds ``x[:, c, y * block + dy, x * block + dx]``.
    """
    b, c, hh, ww = x.shape
    h, w = hh // block, ww // block
    x = x.reshape(b, c, h, block, w, block)
    x = x.permute(0, 1, 3, 5, 2, 4)
    return x.reshape(b, c * block * block, h, w)


def depth_to_space(x: Tensor, block: int) -> Tensor:
    """Inverse of :func:`space_to_depth`, like ``F.pixel_shuffle``.

    Parameters
    ----------
    x : Tensor, shape (B, C * block^2, H, W)
    block : int

    Returns
    -------
    Tensor, shape (B, C, H * block, W * block)
    """
    b, cc, h, w = x.shape
    c = cc // (block * block)
    x = x.reshape(b, c, block, block, h, w)
    x = x.permute(0, 1, 4, 2, 5, 3)
    return x.reshape(b, c, h * block, w * block)


class ResidualBlock(nn.Module):
    """conv3x3 -> ReLU -> conv3x3, added to the input. (B, C, H, W) -> (B, C, H, W)."""

    def __init__(self, width: int) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(width, width, 3, padding=1)
        self.conv2 = nn.Conv2d(width, width, 3, padding=1)

    def forward(self, x: Tensor) -> Tensor:
        return x + self.conv2(F.relu(self.conv1(x)))


class InvertedResidual(nn.Module):
    """conv 1x1 to ``expand`` x width -> ReLU -> depthwise 3x3 -> ReLU -> conv 1x1 back, added to the
    input (MobileNetV2's block without its batch norms). (B, C, H, W) -> (B, C, H, W)."""

    def __init__(self, width: int, expand: int = IR_EXPAND) -> None:
        super().__init__()
        inner = expand * width
        self.body = nn.Sequential(
            nn.Conv2d(width, inner, 1), nn.ReLU(),
            nn.Conv2d(inner, inner, 3, padding=1, groups=inner), nn.ReLU(),
            nn.Conv2d(inner, width, 1))

    def forward(self, x: Tensor) -> Tensor:
        return x + self.body(x)


BLOCKS = {"plain": ResidualBlock, "ir": InvertedResidual}  # by Architecture.kind


class HbisSRNet(nn.Module):
    """Refiner of the classical image for one resolution improvement factor ``h``.

    Parameters
    ----------
    h : int
        Resolution improvement factor (>= 2).
    width : int
        Feature channels of the residual body.
    blocks : int
        Number of residual blocks.
    kind : {"plain", "ir"}
        The residual blocks: :class:`ResidualBlock` or :class:`InvertedResidual`.

    Attributes
    ----------
    architecture : Architecture
        The four arguments, checked (:func:`build_net` builds the network from one).

    Notes
    -----
    ``forward(base, noise)`` takes the classical image space-to-depth (B, h^2, H, W) in [0, 1]
    and the noise map (B, 1, H, W) (:func:`~hbis_torch.reconstruct.learned.network_inputs`), and
    returns the image (B, 1, h H, h W), not clipped (callers clip to [0, 1]).
    """

    def __init__(self, h: int, width: int = 32, blocks: int = 4, kind: str = "plain") -> None:
        super().__init__()
        self.architecture = Architecture(h, width, blocks, kind)
        self.h, self.width, self.blocks = self.architecture.h, self.architecture.width, self.architecture.blocks
        cells = self.h * self.h
        self.head = nn.Conv2d(cells + 1, self.width, 3, padding=1)
        self.body = nn.Sequential(*[BLOCKS[kind](self.width) for _ in range(self.blocks)])
        self.tail = nn.Conv2d(self.width, cells, 3, padding=1)
        # Start as the classical image itself: the correction begins at 0.
        nn.init.zeros_(self.tail.weight)
        nn.init.zeros_(self.tail.bias)

    def config(self) -> dict:
        """The constructor arguments (:meth:`Architecture.as_dict`), to rebuild the model from a checkpoint."""
        return self.architecture.as_dict()

    def features(self, base: Tensor, noise: Tensor) -> Tensor:
        """What the last convolution sees: (B, width, H, W) from ``forward``'s inputs. A burst's
        test-time adaptation fine-tunes only that convolution on these, computed once
        (:mod:`hbis_torch.reconstruct.learned.adapt`)."""
        features = self.head(torch.cat((base - 0.5, noise), dim=1))
        return features + self.body(features)

    def forward(self, base: Tensor, noise: Tensor) -> Tensor:
        return depth_to_space(base + self.tail(self.features(base, noise)), self.h)


def build_net(config: Architecture | dict) -> HbisSRNet:
    """The network of an :class:`Architecture` (or of its :meth:`~Architecture.as_dict`, e.g. a
    checkpoint's ``model_config``), freshly initialised from torch's global generator.

    Parameters
    ----------
    config : Architecture or dict

    Returns
    -------
    HbisSRNet
        In training mode, float32; its last convolution is zero, so it returns the classical image.
    """
    arch = config if isinstance(config, Architecture) else Architecture.from_dict(config)
    return HbisSRNet(arch.h, arch.width, arch.blocks, arch.kind)
