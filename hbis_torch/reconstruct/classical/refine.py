"""A burst's image made consistent with its samples: iterative back-projection on the burst's own
forward model, from the image's lower frequencies.

The classical image puts the samples on the nodes of the S-times lattice and deblurs it. Where the
frames' sub-pixel phases cluster (shifts that leave rows or columns of the lattice without samples
of their own), those nodes are filled from their neighbours, and the fill's errors repeat with the
LR lattice, at one cycle per LR px and above, where the pixel's box passes the scene only faintly:
the data hardly constrain them, and no estimate of the motion wins them back
(``training/swap_shifts.py``). Here the image is first low-passed below that frequency (a Gaussian
of :data:`LOW_PASS_LR_PX`), and the forward model (the lens's Gaussian and the pixel's box, then
each frame's sample positions, bilinear) is then inverted by Landweber steps, each normalised by
the samples' local weight (iterative back-projection [1]_), every sample counted with its
robustness weight (a moving object's samples stay out). Stopping early is what regularises
Landweber's steps [2]_: they stop once a step lowers the weighted residual by less than
:data:`STALL` of it (on the training simulator's bursts, within the few steps where the PSNR
peaks), or after :data:`MAX_ITERATIONS`.

Coordinates: a sample at reference position (u, v) LR px lies at x = S (u + 0.5) - 0.5 on the
output grid (docs/design.md, section 1). float32 throughout: the residuals are of the order of the
noise (1e-2), far above float32's rounding of values in [0, 1] (6e-8); tests/test_refine.py holds
it to a float64 run.

References
----------
.. [1] M. Irani and S. Peleg, "Improving resolution by image registration", CVGIP: Graphical
   Models and Image Processing 53(3), 1991.
.. [2] H. W. Engl, M. Hanke and A. Neubauer, "Regularization of Inverse Problems", Kluwer, 1996
   (Landweber's iteration, stopped early).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

# The start's low-pass: a Gaussian of this sigma in LR px passes 0.29 of the frames' Nyquist
# frequency (half a cycle per LR px) and 0.007 of one cycle per LR px, where the filled nodes'
# errors begin.
LOW_PASS_LR_PX = 0.5
# Stop once a step lowers the weighted residual's RMS by less than this share of it, or after
# MAX_ITERATIONS steps.
STALL = 0.01
MAX_ITERATIONS = 16
# Each step's size, times the samples' local weight's inverse.
STEP = 1.0
# Bursts of up to this many samples keep every frame's taps between steps (28 bytes a sample: 16
# frames of 640 x 480, 138 MB); larger ones compute a frame's again at each step.
KEEP_TAPS_SAMPLES = 1 << 24
# Output px of reflected border around the image, so that the blur's wrap-around and samples just
# outside the reference's frame land on the border, not on the far side.
PAD_PX = 16


@dataclass
class Refined:
    """What :func:`refine_on_samples` returns.

    Attributes
    ----------
    image : Tensor, shape (S H, S W)
        In [0, 1]; float32 (float64 where the image given was a float64 tensor).
    steps : int
        Landweber steps taken.
    residual : float
        The weighted residual's RMS (values in [0, 1]) before the last step.
    stopped_by : str
        ``"stall"`` or ``"iterations"``.
    """

    image: Tensor
    steps: int
    residual: float
    stopped_by: str


def _otf(shape: tuple[int, int], scale: int, lens_sigma: float, box: float) -> Tensor:
    """The forward model's transfer on the padded output grid, (rows, cols // 2 + 1) float64: the
    pixel's box (``box`` output px wide) times the lens's Gaussian (``lens_sigma`` LR px)."""
    fy = torch.fft.fftfreq(shape[0], dtype=torch.float64)[:, None]
    fx = torch.fft.rfftfreq(shape[1], dtype=torch.float64)[None]
    s = lens_sigma * scale
    return torch.sinc(box * fy) * torch.sinc(box * fx) * torch.exp(-2 * math.pi**2 * s * s * (fx**2 + fy**2))


def _filter(image: Tensor, transfer: Tensor) -> Tensor:
    return torch.fft.irfft2(torch.fft.rfft2(image) * transfer, s=image.shape)


class _Taps:
    """One frame's samples on the padded grid: where each one lies (grid_sample's coordinates), its
    top-left node (flat index) and bilinear weights to the four nodes around it, and its
    robustness weight (0 where it falls off the grid)."""

    def __init__(self, positions: Tensor, weights: Tensor, scale: int, shape: tuple[int, int], dtype):
        rows, cols = shape
        # float32: a few thousand output px, to 1e-4 px (a sample's bilinear weights to 1e-4)
        x = positions[..., 0].to(dtype).add_(0.5).mul_(scale).add_(PAD_PX - 0.5)
        y = positions[..., 1].to(dtype).add_(0.5).mul_(scale).add_(PAD_PX - 0.5)
        # grid_sample's coordinates (align_corners=False): -1 and 1 are the grid's outer edges
        self.grid = torch.stack(((2 * x + 1) / cols - 1, (2 * y + 1) / rows - 1), dim=-1)[None]
        x, y = x.reshape(-1), y.reshape(-1)
        x0, y0 = torch.floor(x), torch.floor(y)
        inside = (x0 >= 0) & (x0 <= cols - 2) & (y0 >= 0) & (y0 <= rows - 2)
        fx, fy = x - x0, y - y0
        self.index = (y0.clamp_(0, rows - 2) * cols + x0.clamp_(0, cols - 2)).long()
        self.cols = cols
        self.taps = ((1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy)
        self.weights = weights.reshape(-1).to(dtype) * inside

    def sample(self, grid_image: Tensor) -> Tensor:
        """The image's bilinear values at the samples, (N,) (grid_sample: a fifth of four gathers' time)."""
        return torch.nn.functional.grid_sample(grid_image[None, None], self.grid, mode="bilinear",
                                               align_corners=False).reshape(-1)

    def spread(self, values: Tensor, into: Tensor) -> None:
        """Adds ``values`` (N,) onto the grid (flat) by the transposed bilinear weights."""
        i, c = self.index, self.cols
        for nodes, tap in zip((i, i + 1, i + c, i + c + 1), self.taps):
            into.index_add_(0, nodes, values * tap)


def refine_on_samples(image, frames: Tensor, positions, weights: Tensor, scale: int, lens_sigma: float,
                      fill_factor: float = 1.0, max_iterations: int = MAX_ITERATIONS, step: float = STEP,
                      low_pass_lr_px: float = LOW_PASS_LR_PX) -> Refined:
    """Iterative back-projection of a burst's samples from ``image``'s lower frequencies (module
    docstring).

    Parameters
    ----------
    image : array-like, shape (S H, S W)
        The burst's image on the output grid, values in [0, 1]. A float64 tensor runs the whole
        refinement in float64 (the tests' reference); anything else in float32.
    frames : Tensor, shape (F, H, W), float32
        The brightness-corrected frames.
    positions : Tensor, shape (F, H, W, 2), or BurstPositions
        Each sample's place on the reference grid, LR px.
    weights : Tensor, shape (F, H, W)
        Robustness weights in [0, 1] (0: the sample is left out).
    scale : int
        S.
    lens_sigma : float
        The lens's Gaussian sigma, LR px (0: none).
    fill_factor : float
        The pixel's light-sensitive share of its area: the box is sqrt(fill_factor) LR px wide.
    max_iterations : int
    step : float
        Each step's size (:data:`STEP`).
    low_pass_lr_px : float
        The start's low-pass Gaussian, LR px (0: the image as it is).

    Returns
    -------
    Refined
    """
    given = torch.as_tensor(image)
    dtype = torch.float64 if given.dtype == torch.float64 else torch.float32
    start = given.to(dtype)
    if start.ndim != 2 or start.shape != (scale * frames.shape[1], scale * frames.shape[2]):
        raise ValueError(f"the image must be (S H, S W) = ({scale * frames.shape[1]}, {scale * frames.shape[2]}), "
                         f"got {tuple(start.shape)}")
    padded = torch.nn.functional.pad(start[None, None], (PAD_PX,) * 4, mode="reflect")[0, 0]
    shape = tuple(padded.shape)
    low = low_pass_lr_px * scale
    fy = torch.fft.fftfreq(shape[0], dtype=torch.float64)[:, None]
    fx = torch.fft.rfftfreq(shape[1], dtype=torch.float64)[None]
    x = _filter(padded, torch.exp(-2 * math.pi**2 * low * low * (fx**2 + fy**2)).to(dtype))
    transfer = _otf(shape, scale, lens_sigma, scale * math.sqrt(fill_factor)).to(dtype)
    # the local weight of the samples, smoothed as the step is: the step's normaliser
    spread_sigma = math.sqrt(scale**2 * fill_factor / 12 + (lens_sigma * scale) ** 2)
    smooth = torch.exp(-2 * math.pi**2 * spread_sigma**2 * (fx**2 + fy**2)).to(dtype)
    kept = [] if frames.numel() <= KEEP_TAPS_SAMPLES else None

    def taps_of(k: int) -> _Taps:
        if kept is not None and k < len(kept):
            return kept[k]
        t = _Taps(positions[k], weights[k], scale, shape, dtype)
        if kept is not None:
            kept.append(t)
        return t

    density, total = torch.zeros(shape[0] * shape[1], dtype=dtype), 0.0
    for k in range(len(frames)):
        t = taps_of(k)
        t.spread(t.weights, density)
        total += float(t.weights.sum(dtype=torch.float64))
    if total == 0:  # no sample to be consistent with
        return Refined(start.clamp(0, 1), 0, math.nan, "iterations")
    density = _filter(density.reshape(shape), smooth).clamp_min_(1e-3)
    previous, residual, stopped_by, steps = math.inf, math.nan, "iterations", 0
    for steps in range(max_iterations):
        seen = _filter(x, transfer)
        back = torch.zeros(shape[0] * shape[1], dtype=dtype)
        squares = 0.0
        for k in range(len(frames)):
            t = taps_of(k)
            difference = frames[k].reshape(-1).to(dtype) - t.sample(seen)
            weighted = difference * t.weights
            squares += float(torch.dot(weighted, difference))
            t.spread(weighted, back)
        residual = math.sqrt(squares / max(total, 1e-12))
        if residual > previous * (1 - STALL):
            stopped_by = "stall"
            break
        previous = residual
        x += _filter(back.reshape(shape), transfer).div_(density).mul_(step)
    else:
        steps = max_iterations
    inner = x[PAD_PX:PAD_PX + start.shape[0], PAD_PX:PAD_PX + start.shape[1]]
    return Refined(inner.clamp(0, 1).contiguous(), steps, residual, stopped_by)
