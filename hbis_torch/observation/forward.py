"""The forward model of an observation (cross-validation's and the burst adaptation's): what a frame
should record, given a super-resolved estimate and where the frame's samples lie on the estimate's grid.

Sample (u, v) of a frame sees the scene at position q(u, v) of the reference frame (LR pixels,
:func:`hbis_torch.reconstruct.positions.stack_sample_positions`), integrated over the pixel's
area and blurred a little by the lens. The estimate lies on the output grid (docs/design.md
section 1: HR pixel (U, V) centred at LR ((U + 0.5) / h - 0.5, (V + 0.5) / h - 0.5)). So the
prediction is the estimate filtered by the pixel's box (side sqrt(fill factor) LR pixels)
and a Gaussian of ``blur_px`` LR pixels, both integrated over the HR pixels, then read at q
with bicubic interpolation.
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F

from hbis_torch.errors import HbisInputError

#: Standard deviation of the Gaussian blur the prediction adds to the pixel's box, in LR pixels:
#: a lens a little softer than the pixel, the same for every method (it only lowers the weight of
#: the highest frequencies, where the frames carry aliasing rather than signal).
DEFAULT_BLUR_PX = 0.2


def pixel_kernel(h: int, fill_factor: float = 1.0, blur_px: float = DEFAULT_BLUR_PX) -> np.ndarray:
    """The 1-D kernel (on the HR grid) of one LR pixel's box and the Gaussian blur, separable.

    Parameters
    ----------
    h : int
        HR pixels per LR pixel.
    fill_factor : float
        The pixel's light-sensitive area, in (0, 1]: a box of side sqrt(fill_factor) LR pixels.
    blur_px : float
        Gaussian standard deviation, LR pixels (0: the box alone).

    Returns
    -------
    np.ndarray, shape (2 R + 1,), float64
        Weights summing to 1, centred: each weight is the exact integral of the box (and of the
        Gaussian, convolved on the HR grid) over one HR pixel.
    """
    if not (0 < fill_factor <= 1) or not (math.isfinite(blur_px) and blur_px >= 0):
        raise HbisInputError(f"fill factor must lie in (0, 1] and blur >= 0, got {fill_factor}, {blur_px}")
    half = 0.5 * math.sqrt(fill_factor) * h
    reach = int(math.ceil(half + 0.5))
    n = np.arange(-reach, reach + 1, dtype=np.float64)
    box = np.clip(np.minimum(n + 0.5, half) - np.maximum(n - 0.5, -half), 0.0, None)
    sigma = blur_px * h
    if sigma > 0:
        g_reach = int(math.ceil(4 * sigma + 0.5))
        m = np.arange(-g_reach, g_reach + 1, dtype=np.float64)
        cdf = np.vectorize(lambda t: 0.5 * (1 + math.erf(t / (sigma * math.sqrt(2)))))
        box = np.convolve(box, cdf(m + 0.5) - cdf(m - 0.5))
    return box / box.sum()


def blur_estimate(estimate, h: int, fill_factor: float = 1.0, blur_px: float = DEFAULT_BLUR_PX) -> torch.Tensor:
    """The estimate as an LR pixel would see it at every HR position: box and blur, separably.

    Parameters
    ----------
    estimate : array or Tensor, shape (h H, h W) or (h H, h W, C)
    h, fill_factor, blur_px
        As :func:`pixel_kernel`.

    Returns
    -------
    Tensor, shape (C, h H, h W), float32 (C = 1 for a grey estimate); edges replicated.
    """
    x = torch.as_tensor(np.asarray(estimate, dtype=np.float32))
    x = x[None] if x.ndim == 2 else x.permute(2, 0, 1)
    kernel = torch.from_numpy(pixel_kernel(h, fill_factor, blur_px).astype(np.float32))
    r = len(kernel) // 2
    x = x[:, None]
    x = F.conv2d(F.pad(x, (r, r, 0, 0), mode="replicate"), kernel.view(1, 1, 1, -1))
    x = F.conv2d(F.pad(x, (0, 0, r, r), mode="replicate"), kernel.view(1, 1, -1, 1))
    return x[:, 0]


def predict_frame(estimate, positions, h: int, fill_factor: float = 1.0,
                  blur_px: float = DEFAULT_BLUR_PX) -> np.ndarray:
    """What a frame whose samples lie at ``positions`` records of the scene ``estimate``.

    Parameters
    ----------
    estimate : array, shape (h H, h W) or (h H, h W, C)
        On the output grid of an H x W reference frame, in [0, 1].
    positions : array, shape (H', W', 2)
        (u, v) of each of the frame's samples on the reference frame, LR pixels (the frame may
        be of another size than the reference); positions off the estimate read its edge.
    h : int
        The estimate's refinement factor.
    fill_factor, blur_px
        As :func:`pixel_kernel`.

    Returns
    -------
    np.ndarray, shape (H', W') or (H', W', C), float64
        The predicted frame, before any gain and offset.
    """
    estimate = np.asarray(estimate)
    rows, cols = estimate.shape[0] // h, estimate.shape[1] // h
    if estimate.shape[0] != rows * h or estimate.shape[1] != cols * h or rows < 1 or cols < 1:
        raise HbisInputError(f"an estimate at h = {h} must have a multiple of {h} rows and columns, "
                             f"got {estimate.shape}")
    q = torch.as_tensor(np.asarray(positions, dtype=np.float64))
    if q.ndim != 3 or q.shape[-1] != 2:
        raise HbisInputError(f"positions must have shape (H, W, 2), got {tuple(q.shape)}")
    blurred = blur_estimate(estimate, h, fill_factor, blur_px)
    # grid_sample's coordinates with align_corners=False: HR pixel U at (2 U + 1) / (h W) - 1,
    # which is (2 u + 1) / W - 1 for U = h (u + 0.5) - 0.5
    grid = torch.stack(((2 * q[..., 0] + 1) / cols - 1, (2 * q[..., 1] + 1) / rows - 1), dim=-1)
    out = F.grid_sample(blurred[None], grid[None].float(), mode="bicubic", padding_mode="border",
                        align_corners=False)[0]
    out = out.double().numpy()
    return out[0] if estimate.ndim == 2 else np.moveaxis(out, 0, -1)
