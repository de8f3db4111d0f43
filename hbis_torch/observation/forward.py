"""The forward model of an observation (cross-validation's and the burst adaptation's): what a frame
should record, given a super-resolved estimate and where the frame's samples lie on the estimate's grid.

Sample (u, v) of a frame sees the scene at position q(u, v) of the reference frame (LR pixels,
:func:`hbis_torch.reconstruct.positions.stack_sample_positions`), integrated over the pixel's
area and blurred a little by the lens. The estimate lies on the output grid (docs/design.md
section 1: HR pixel (U, V) centred at LR ((U + 0.5) / h - 0.5, (V + 0.5) / h - 0.5)). So the
prediction is the estimate filtered by the pixel's box (side sqrt(fill factor) LR pixels)
and a Gaussian of ``blur_px`` LR pixels, both integrated over the HR pixels, then read at q
with bicubic interpolation.

The box is centred where an LR pixel's centre falls on the HR grid: on an HR pixel's centre
for odd h, half-way between two for even h (:func:`centre_offset`). A box centred on an HR pixel
and then read half a pixel on by the interpolation (as this model did until 2026-12-05) blurs
the prediction by about an HR pixel's width more: it rewarded estimates sharper than the scene
at h = 2 and 4 (tests/test_validate.py checks that a frame of the HR pixels' own means is
predicted exactly). The bicubic read still softens the frames that moved a fraction of an HR
pixel a little, at every h. A cubic B-spline read would not (a prefilter and four bilinear reads,
differentiable for the adaptation, which must predict as validation does); on the adaptation's
development bursts it changed the adapted network's gain by a few hundredths of a dB for half
as much adaptation time again, so the bicubic read stays.
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


def centre_offset(h: int) -> float:
    """Where an LR pixel's centre lies beyond the centre of the HR pixel before it, HR px: 0 for
    odd h, 1/2 for even h (LR position u is HR position h (u + 1/2) - 1/2)."""
    return ((h - 1) / 2) % 1.0


def pixel_kernel(h: int, fill_factor: float = 1.0, blur_px: float = DEFAULT_BLUR_PX) -> np.ndarray:
    """The 1-D kernel (on the HR grid) of one LR pixel's box and the Gaussian blur, separable,
    centred on the LR pixel's centre: :func:`centre_offset` beyond the middle tap.

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
        Weights summing to 1: weight R + n is the exact integral over HR pixel n (from n - 1/2 to
        n + 1/2) of the box centred at :func:`centre_offset` (and of the Gaussian, convolved on
        the HR grid). Convolved with an image, it gives at HR pixel i what an LR pixel centred
        at HR position i + centre_offset(h) records: symmetric for odd h; at h = 2 without blur
        (1/2, 1/2) on pixels 0 and 1, not the box centred on an HR pixel, (1/4, 1/2, 1/4).
    """
    if not (0 < fill_factor <= 1) or not (math.isfinite(blur_px) and blur_px >= 0):
        raise HbisInputError(f"fill factor must lie in (0, 1] and blur >= 0, got {fill_factor}, {blur_px}")
    half = 0.5 * math.sqrt(fill_factor) * h
    centre = centre_offset(h)
    reach = int(math.ceil(half + centre + 0.5))
    n = np.arange(-reach, reach + 1, dtype=np.float64)
    box = np.clip(np.minimum(n + 0.5, centre + half) - np.maximum(n - 0.5, centre - half), 0.0, None)
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
    grid = sample_grid(q, h, rows, cols)
    out = F.grid_sample(blurred[None], grid[None].float(), mode="bicubic", padding_mode="border",
                        align_corners=False)[0]
    out = out.double().numpy()
    return out[0] if estimate.ndim == 2 else np.moveaxis(out, 0, -1)


def sample_grid(q: torch.Tensor, h: int, rows: int, cols: int) -> torch.Tensor:
    """grid_sample's coordinates (align_corners=False; (..., 2), q's dtype) of LR positions ``q``
    (..., 2) (u, v) in an image of a ``rows`` x ``cols`` LR frame's h-times grid blurred by
    :func:`pixel_kernel`, whose HR pixel i holds the LR pixel centred at HR position
    i + :func:`centre_offset`: LR u is HR h (u + 1/2) - 1/2, the pixel index that less the
    offset, at (2 index + 1) / (h cols) - 1."""
    shift = 2 * centre_offset(h) / h
    return torch.stack(((2 * q[..., 0] + 1 - shift) / cols - 1, (2 * q[..., 1] + 1 - shift) / rows - 1), dim=-1)
