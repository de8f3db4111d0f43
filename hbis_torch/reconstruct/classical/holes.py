"""The holes a splat leaves on its grid, filled from the sums blurred wider and wider
(:func:`fill_holes`), and the Gaussian blurs it takes: at the holes alone (:func:`_blur_at`), or
of the whole image by a separable convolution (:func:`_separable_blur`, a band of rows at a time
on large images) or the FFT (:func:`_gaussian_blur`).

Shapes (rows, cols) in HR px, or (..., rows, cols) for the whole-image blurs.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

from hbis_torch.errors import HbisInputError


def _gaussian_blur(img: Tensor, sigma: float) -> Tensor:
    """Gaussian blur of ``img`` (..., rows, cols) with mirrored borders, via the FFT (in
    ``img``'s dtype; the padded image is freed before the inverse transform)."""
    rows, cols = img.shape[-2:]
    pad = min(math.ceil(4 * sigma), rows - 1, cols - 1)
    p = torch.nn.functional.pad(img.reshape(1, -1, rows, cols), (pad, pad, pad, pad), mode="reflect")[0]
    fy = torch.fft.fftfreq(p.shape[1], dtype=img.dtype)[:, None]
    fx = torch.fft.rfftfreq(p.shape[2], dtype=img.dtype)[None, :]
    g = torch.exp(-2 * math.pi ** 2 * sigma ** 2 * (fx * fx + fy * fy))
    spectrum, shape = torch.fft.rfft2(p), p.shape[1:]
    del p
    out = torch.fft.irfft2(spectrum.mul_(g), s=shape)
    return out[:, pad:pad + rows, pad:pad + cols].reshape(img.shape)


# A larger image's separable blur goes a band of at least this many rows at a time.
BLUR_BAND_ROWS = 1024


def _separable_blur(img: Tensor, sigma: float) -> Tensor:
    """:func:`_blur_at` at every node of ``img`` (..., rows, cols): the same sampled Gaussian
    taps out to 4 sigma and mirrored borders, by kornia's separable convolution.

    For the few taps of a small sigma (9 at sigma = 1) cheaper than the FFT blur
    (:func:`_gaussian_blur`), and the same values as the blur at the holes alone (to float
    rounding), where the FFT's Gaussian, continuous in frequency, differs from the sampled one by
    up to 0.2 % of the image's range at sigma = 1."""
    from kornia.filters import gaussian_blur2d

    rows, cols = img.shape[-2:]
    radius = min(math.ceil(4 * sigma), rows - 1, cols - 1)
    flat = img.reshape(-1, 1, rows, cols)

    def blur(part: Tensor) -> Tensor:
        return gaussian_blur2d(part, (2 * radius + 1,) * 2, (sigma, sigma), border_type="reflect", separable=True)

    bands = rows // BLUR_BAND_ROWS
    if bands < 2 or cols < 256:
        return blur(flat).reshape(img.shape)
    # Bands of rows with the taps' halo: kornia's padded copies and sums of a band, not of the whole
    # image (an 8000 x 6000 lattice's pair took 1.5 GB more). Each tap is summed in the same order,
    # so the values are the whole image's to the bit; every band is BLUR_BAND_ROWS rows or more,
    # so kornia takes the same path for each.
    out = torch.empty_like(flat)
    edges = [round(k * rows / bands) for k in range(bands + 1)]
    for top, bottom in zip(edges[:-1], edges[1:]):
        lo, hi = max(top - radius, 0), min(bottom + radius, rows)
        out[:, :, top:bottom] = blur(flat[:, :, lo:hi].contiguous())[:, :, top - lo:bottom - lo]
    return out.reshape(img.shape)


def _blur_at(img: Tensor, sigma: float, rows: Tensor, cols: Tensor) -> Tensor:
    """:func:`_gaussian_blur` of ``img`` at the nodes (rows[i], cols[i]) only, (K,): sampled
    Gaussian taps out to 4 sigma, mirrored borders."""
    H, W = img.shape
    pad = min(math.ceil(4 * sigma), H - 1, W - 1)
    d = torch.arange(-pad, pad + 1)
    g = torch.exp(-(d * d).to(img.dtype) / (2 * sigma * sigma))
    g = g / g.sum()

    def mirror(i: Tensor, n: int) -> Tensor:  # as torch's "reflect" padding: -1 -> 1, n -> n - 2
        i = i.abs()
        return torch.where(i > n - 1, 2 * (n - 1) - i, i)

    rr = mirror(rows[:, None] + d, H)  # (K, taps)
    cc = mirror(cols[:, None] + d, W)
    window = img[rr[:, :, None], cc[:, None, :]]  # (K, taps, taps)
    return torch.einsum("ktu,t,u->k", window, g, g)


# Images of more nodes than this take their medians on every MEDIAN_STRIDE-th node (the median of a
# million values costs 6 ms).
MEDIAN_NODES = 1 << 18
# A prime above the largest scale (16), so that the nodes taken fall in every one of the lattice's
# S x S classes alike. Every other row and column (before 2026-12-07) took one class of the four at
# S = 2: where a burst's shifts cluster, the classes get different numbers of samples, and one
# class's noise and typical weight are not the lattice's (a held-out burst's noise in a dim light
# read 0.9 or 1.4 times the lattice's as a local field of a hundredth of a pixel moved which nodes
# passed the weight test).
MEDIAN_STRIDE = 17
# fill_holes blurs whole images up to this sigma by a separable convolution (:func:`_separable_blur`,
# 17 taps), wider ones by the FFT (:func:`_gaussian_blur`).
SEPARABLE_MAX_SIGMA = 2.0


def median_subset(image: Tensor) -> Tensor:
    """``image`` (rows, cols), or, if it has more than :data:`MEDIAN_NODES` entries, every
    :data:`MEDIAN_STRIDE`-th of its entries in reading order, (N,): where the robust statistics
    take their medians. Images of one shape give the same entries (a mask beside its values)."""
    return image.reshape(-1)[::MEDIAN_STRIDE] if image.numel() > MEDIAN_NODES else image


def typical_weight(den: Tensor) -> float:
    """The median of the splat weights' sums ``den`` (rows, cols) over the nodes that have any
    (0 if none has); on :func:`median_subset` of a large lattice."""
    den = median_subset(den)
    positive = den > 0
    return lower_median(den, positive) if bool(positive.any()) else 0.0


def lower_median(values: Tensor, where: Tensor) -> float:
    """``float(values[where].median())`` (the lower of the two middle values for an even count)
    of a CPU tensor and a boolean mask of its shape, in NumPy: torch's boolean indexing would
    first list the selected entries' indices (16 bytes a 2-D entry, 1 GB at h = 7 full frame),
    and its median would copy them again."""
    picked = values.numpy()[where.numpy()]  # a copy, partitioned in place
    if not picked.size:
        raise ValueError("the median of no values")
    middle = (picked.size - 1) // 2
    picked.partition(middle)
    return float(picked[middle])


def _holes(den: Tensor, below: float) -> tuple[Tensor, Tensor]:
    """The rows and columns (int64, row-major order) of the nodes of ``den`` (rows, cols) below
    ``below``, found in NumPy: its vectorised comparison and flat nonzero take a full frame at
    h = 4 in 8 ms, torch's ``nonzero(den < below)`` in 26 ms."""
    rows, cols = np.divmod(np.flatnonzero(den.numpy() < below), den.shape[1])
    return torch.from_numpy(rows), torch.from_numpy(cols)


def fill_holes(num: Tensor, den: Tensor, typical: float | None = None, *, in_place: bool = False,
               blur=None) -> Tensor:
    """num / den, with nodes of little weight taken from the sums blurred wider and wider.

    Only the holes' blurred values are used: where there are few of them (a frame's border)
    they are computed at the holes alone (:func:`_blur_at`), else by blurring the whole image.
    Shapes (rows, cols); ``typical`` is :func:`typical_weight` of ``den``, if the caller has it;
    ``in_place`` writes the image over ``num`` (no image-sized temporaries); ``blur``, (num, den,
    sigma) -> the two blurred whole (2, rows, cols), replaces the whole image's blur (the raw
    planes blur both sums in one float32 batch).
    """
    if typical is None:
        typical = typical_weight(den)
    if typical == 0.0:
        raise HbisInputError("no sample falls on the output grid")
    rows, cols = _holes(den, 0.25 * typical)
    fills = []  # (rows, cols, values) of the holes, from the sums before num is divided
    sigma = 1.0
    while len(rows) and sigma <= 64:
        taps = 2 * math.ceil(4 * sigma) + 1
        if len(rows) * taps * taps <= num.numel() // 4:
            n2, d2 = _blur_at(num, sigma, rows, cols), _blur_at(den, sigma, rows, cols)
        elif blur is None:  # the whole image blurred: a convolution for a few taps, else the FFT
            whole = _separable_blur if sigma <= SEPARABLE_MAX_SIGMA else _gaussian_blur
            n2, d2 = whole(num, sigma)[rows, cols], whole(den, sigma)[rows, cols]
        else:
            blurred = blur(num, den, sigma)
            n2, d2 = blurred[0][rows, cols].to(num.dtype), blurred[1][rows, cols].to(den.dtype)
            del blurred
        ok = d2 >= 0.05 * typical
        fills.append((rows[ok], cols[ok], n2[ok] / d2[ok].clamp_min(1e-12)))
        rows, cols = rows[~ok], cols[~ok]
        sigma *= 2
    if len(rows):
        fills.append((rows, cols, num.sum() / den.sum()))
    if in_place and 0.25 * typical >= 1e-12:
        image = num.div_(den)  # every node below 1e-12 (0/0 among them) is a hole, overwritten below
    else:
        image = num / den.clamp_min(1e-12)
    for rows, cols, values in fills:
        image[rows, cols] = values
    return image
