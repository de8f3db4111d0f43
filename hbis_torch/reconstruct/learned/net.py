"""A small multi-frame super-resolution network for Risley-prism sub-pixel scans.

Design (why it looks like this)
-------------------------------
An h x h scan shifts the scene by about 1/h pixel between frames, so the h^2 frames, put in
*registered order* (channel ``py * h + px`` holds the frame whose samples sit at sub-pixel phase
(px, py) / h, see :func:`hbis_torch.reconstruct.learned.prepare_inputs`), are very nearly the h^2 polyphase
components of the high-resolution image. The network therefore works entirely on the
low-resolution grid, where it is h^2 times cheaper than on the output grid:

    frames  (B, h^2, H, W)    -- in [0, 1], registered order
    offsets (B, 2 h^2, H, W)  -- per pixel, how far each sample sits from its nominal phase,
                                  in output (HR) pixels, (x, y) per frame
      -> 3x3 conv -> residual blocks -> 3x3 conv to h^2 channels -> depth-to-space (B, 1, hH, hW)
      -> plus a linear base: a k x k conv of all h^2 frames to h^2 channels, depth-to-space
         (``skip = k``; it starts as bilinear upsampling of the reference frame, channel 0),
         or, with ``skip = 0`` (the first models), the bilinearly upsampled reference frame

Why the linear base: with only the bilinear base, every bit of detail and all the deblurring has
to pass through the nonlinear body, which stops near 48 dB on smooth content where a linear
Wiener-like deconvolution of the h^2 frames (the classical method's prior) does better. The
k x k conv *is* such a linear multi-frame deconvolution, learned directly (on the LR grid it
reaches k * h output pixels), and the body only learns what is left.

The shifts are not exactly on the 1/h grid (the pattern is scaled and offset by up to a quarter
of an output pixel at the sensor's corners at h = 4), so the per-pixel residual offsets are
inputs: the network learns how to use them from training stacks taken all over the sensor. A
splat onto the output grid followed by a CNN refiner would use the offsets explicitly, but every
convolution would then run on h^2 times more pixels.

One model per h (not one model conditioned on h): the input channel count (3 h^2) and the
depth-to-space factor are h itself, so a conditioned model would have to pad to the largest h
and pay for it at every h; separate models are small (< 2 MB) and each ONNX file states its h.

Only plain operators are used (Conv, Relu, Add, Pad, Reshape, Transpose, Resize), so the model exports
to ONNX with dynamic height and width. Depth-to-space and space-to-depth are written as
reshape/permute because the dynamo ONNX exporter mistranslates ``pixel_unshuffle``.

All tensors are float32 (the trained weights are float32); tests compare against float64
classical references.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from hbis_torch.checks import check_h
from hbis_torch.errors import HbisInputError


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


def bilinear_kernel(h: int, size: int) -> Tensor:
    """Conv weights (h^2, size, size) that, followed by depth-to-space, upsample one LR channel
    bilinearly by h (``F.interpolate(..., mode="bilinear", align_corners=False)``).

    Found by upsampling a unit impulse: output channel ``dy * h + dx`` at LR pixel (y, x) takes
    the impulse's response at output pixel (h y + dy, h x + dx); a convolution reads its input
    mirrored, hence the flip.
    """
    impulse = torch.zeros(1, 1, size, size)
    impulse[..., size // 2, size // 2] = 1.0
    response = F.interpolate(impulse, scale_factor=h, mode="bilinear", align_corners=False)
    return space_to_depth(response, h)[0].flip(-1, -2)


class ResidualBlock(nn.Module):
    """conv3x3 -> ReLU -> conv3x3, added to the input. (B, C, H, W) -> (B, C, H, W)."""

    def __init__(self, width: int) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(width, width, 3, padding=1)
        self.conv2 = nn.Conv2d(width, width, 3, padding=1)

    def forward(self, x: Tensor) -> Tensor:
        return x + self.conv2(F.relu(self.conv1(x)))


class HbisSRNet(nn.Module):
    """Multi-frame SR network for one resolution improvement factor ``h``.

    Parameters
    ----------
    h : int
        Resolution improvement factor (>= 2); the model takes h^2 frames.
    width : int
        Feature channels of the residual body.
    blocks : int
        Number of residual blocks.
    skip : int
        Kernel size (odd) of the linear multi-frame base; 0 for the bilinear base of the first
        models (their checkpoints have no ``skip`` entry and rebuild with 0).

    Notes
    -----
    ``forward(frames, offsets)`` takes frames (B, h^2, H, W) in [0, 1] in registered order and
    offsets (B, 2 h^2, H, W) in output pixels, and returns the image (B, 1, h H, h W), not
    clipped (callers clip to [0, 1]).
    """

    def __init__(self, h: int, width: int = 48, blocks: int = 5, skip: int = 0) -> None:
        super().__init__()
        check_h(h, minimum=2)
        if int(skip) != skip or skip < 0 or (skip and skip % 2 == 0):
            raise HbisInputError(f"skip must be 0 or an odd kernel size, got {skip!r}")
        self.h, self.width, self.blocks, self.skip = int(h), int(width), int(blocks), int(skip)
        frames = self.h * self.h
        self.head = nn.Conv2d(3 * frames, width, 3, padding=1)
        self.body = nn.Sequential(*[ResidualBlock(width) for _ in range(blocks)])
        self.tail = nn.Conv2d(width, frames, 3, padding=1)
        # Start as "bilinear upsampling of the reference frame": the residual branch begins at 0.
        nn.init.zeros_(self.tail.weight)
        nn.init.zeros_(self.tail.bias)
        self.linear = None
        if self.skip:
            # Replicate padding makes the initial base equal to bilinear upsampling (which clamps
            # at the border), edges included.
            self.linear = nn.Conv2d(frames, frames, self.skip, padding=self.skip // 2, padding_mode="replicate")
            with torch.no_grad():
                self.linear.weight.zero_()
                self.linear.weight[:, 0] = bilinear_kernel(self.h, self.skip)
                self.linear.bias.fill_(0.5)  # the frames come in centred on 0.5

    @property
    def frame_count(self) -> int:
        return self.h * self.h

    def config(self) -> dict:
        """The constructor arguments, to rebuild the model from a checkpoint."""
        return {"h": self.h, "width": self.width, "blocks": self.blocks, "skip": self.skip}

    def forward(self, frames: Tensor, offsets: Tensor) -> Tensor:
        centred = frames - 0.5
        features = self.head(torch.cat((centred, offsets), dim=1))
        features = features + self.body(features)
        out = self.tail(features)
        if self.linear is not None:
            return depth_to_space(out + self.linear(centred), self.h)
        base = F.interpolate(frames[:, :1], scale_factor=self.h, mode="bilinear", align_corners=False)
        return base + depth_to_space(out, self.h)


def count_parameters(model: nn.Module) -> int:
    """Number of trainable parameters."""
    return sum(p.numel() for p in model.parameters() if p.requires_grad)
