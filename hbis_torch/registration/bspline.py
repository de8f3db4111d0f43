"""Cubic B-spline resampling: Fourier prefiltering, blur kernels and spline evaluation.

Images are (F, H, W) (or (C, H, W) shared by every frame), in any float dtype; points are
(u, v) pixel coordinates, (F, N, 2), with pixel (u, v) the centre of column u and row v. Blur
widths are in px. Filtering is done on mirror-padded images in the Fourier domain (rfft2 grids
of shape (Hp, Wp // 2 + 1)); evaluation is four bilinear ``grid_sample`` fetches per point.
"""

from __future__ import annotations

import functools
import math

import torch
from torch import Tensor

from hbis_torch.registration.threaded_sample import grid_sample_threaded


def _fast_fft_size(n: int) -> int:
    """The smallest integer >= n whose only prime factors are 2, 3 and 5."""
    while True:
        m = n
        for p in (2, 3, 5):
            while m % p == 0:
                m //= p
        if m == 1:
            return n
        n += 1


@functools.lru_cache(maxsize=32)
def _frequency_filters(Hp: int, Wp: int, blur: tuple, dtype) -> tuple[Tensor, ...]:
    """Responses on the (Hp, Wp // 2 + 1) rfft2 grid, cached per size and blur: the blur (the
    Gaussian exp(-sigma^2 w^2 / 2) for ``blur = ("gaussian", sigma)``, or a symmetric sampled
    kernel's exact response for ``blur = ("kernel", k_0, ..., k_r)``), the cubic B-spline's
    sampled kernel [1, 4, 1] / 6 ((4 + 2 cos w) / 6 per axis, never below 1/3), and the
    derivatives d/du, d/dv (i w per axis). Callers must not modify them."""
    wy = 2 * math.pi * torch.fft.fftfreq(Hp, dtype=dtype)[:, None]
    wx = 2 * math.pi * torch.fft.rfftfreq(Wp, dtype=dtype)[None, :]
    if blur[0] == "gaussian":
        response = torch.exp(-0.5 * blur[1] ** 2 * (wx * wx + wy * wy))
    else:
        taps = torch.tensor(blur[1:], dtype=dtype)  # k_0, k_1, ..., k_r
        j = torch.arange(1, len(taps), dtype=dtype)
        response = ((taps[0] + 2 * (taps[1:] * torch.cos(wx[..., None] * j)).sum(-1))
                    * (taps[0] + 2 * (taps[1:] * torch.cos(wy[..., None] * j)).sum(-1)))
    spline = (4 + 2 * torch.cos(wx)) * (4 + 2 * torch.cos(wy)) / 36
    return response, spline, 1j * wx * torch.ones_like(wy), 1j * wy * torch.ones_like(wx)


def _padded_spectrum(images: Tensor, blur_sigma: float, kernel: Tensor | None):
    """rfft2 of the mirror-padded images times the blur's response, (F, Hp, Wp // 2 + 1), with
    the filters of :func:`_frequency_filters`, the padded size and the crop back to (H, W).

    The pad is wide enough that filtering equals mirrored-border convolution to about 3e-5 (the
    B-spline inverse decays as 0.268^n, 1e-5 after 8 px; the Gaussian within 3 sigma), and a
    little wider at the far sides to reach a size the FFT is fast at (factors 2, 3, 5).
    """
    F, H, W = images.shape
    radius = int(math.ceil(3 * blur_sigma)) if kernel is None else (len(kernel) - 1) // 2
    pad = min(8 + radius, H - 1, W - 1)
    extra_h = min(_fast_fft_size(H + 2 * pad) - H - 2 * pad, H - 1 - pad)
    extra_w = min(_fast_fft_size(W + 2 * pad) - W - 2 * pad, W - 1 - pad)
    padded = torch.nn.functional.pad(images[:, None], (pad, pad + extra_w, pad, pad + extra_h), mode="reflect")[:, 0]
    Hp, Wp = padded.shape[-2:]
    blur = ("gaussian", float(blur_sigma)) if kernel is None else ("kernel", *kernel[radius:].tolist())
    filters = _frequency_filters(Hp, Wp, blur, images.dtype)
    spectrum = torch.fft.rfft2(padded) * filters[0]
    crop = (slice(None), slice(pad, pad + H), slice(pad, pad + W))
    return spectrum, filters, (Hp, Wp), crop


def prefilter(images: Tensor, blur_sigma: float = 0.0, kernel: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """Gaussian-blurred images and their cubic B-spline coefficients, both (F, H, W).

    Both filters are applied at once in the Fourier domain on mirror-padded images: the
    Gaussian exp(-sigma^2 w^2 / 2), and the inverse of the B-spline's sampled kernel
    [1, 4, 1] / 6, whose response (4 + 2 cos w) / 6 never falls below 1/3.

    Parameters
    ----------
    images : Tensor, shape (F, H, W)
    blur_sigma : float
        Standard deviation of the Gaussian in px (0: no blur).
    kernel : Tensor, shape (2 r + 1,), optional
        A symmetric sampled kernel to blur with instead of the Gaussian (applied separably,
        through its exact frequency response: the same as convolution with mirrored borders).

    Returns
    -------
    blurred : Tensor, shape (F, H, W)
    coefficients : Tensor, shape (F, H, W)
        ``bspline_sample(coefficients, p)`` interpolates the blurred frames at points p.
    """
    spectrum, (_, spline, *_), size, crop = _padded_spectrum(images, blur_sigma, kernel)
    blurred = torch.fft.irfft2(spectrum, s=size)[crop]
    coefficients = torch.fft.irfft2(spectrum / spline, s=size)[crop].contiguous()
    return blurred, coefficients


def _reference_splines(reference: Tensor, kernel: Tensor) -> tuple[Tensor, Tensor]:
    """What the fit needs of the reference (H, W), blurred by ``kernel``, from one FFT.

    Returns
    -------
    coefficients : Tensor, shape (3, H, W)
        Cubic B-spline coefficients of the blurred reference and of its exact derivatives d/du
        and d/dv (so that one fetch interpolates value and gradient at any point).
    strength : Tensor, shape (H, W)
        Squared gradient of the coefficients at the pixels: where to compare. (The coefficients
        are the blurred reference sharpened by the spline's prefilter; on bench_registration's
        stacks choosing points by their gradient was as accurate as by the blurred image's
        central differences, and it needs no extra transform.)
    """
    spectrum, (_, spline, d_u, d_v), size, crop = _padded_spectrum(reference[None], 0.0, kernel)
    coef = spectrum / spline
    parts = torch.fft.irfft2(torch.cat((coef, coef * d_u, coef * d_v)), s=size)[crop].contiguous()
    return parts, parts[1] ** 2 + parts[2] ** 2


def bspline_sample(coefficients: Tensor, points: Tensor) -> Tensor:
    """Evaluate cubic B-spline images at fractional pixel points.

    Cubic B-spline interpolation, unlike torch's bicubic (Keys, a = -0.75), has no first-order
    error, so a sub-pixel warp does not bias the registration (about 1e-4 px instead of 0.04 px
    on content at a tenth of the sampling rate). Each 4 x 4 B-spline sum is computed as four
    bilinear fetches (Sigg & Hadwiger, GPU Gems 2, ch. 20), all by ``grid_sample``.

    Parameters
    ----------
    coefficients : Tensor, shape (F, H, W)
        From :func:`prefilter`.
    points : Tensor, shape (F, N, 2)
        (u, v) pixel coordinates; the image is mirrored about its border pixels.

    Returns
    -------
    Tensor, shape (F, N), in the coefficients' dtype.
    """
    F = coefficients.shape[0]
    n = points.shape[1]
    got, (gu0, gu1, gv0, gv1) = _bilinear_fetches(coefficients[:, None], points)
    got = got.view(F, 4, n)
    return gv0 * (gu0 * got[:, 0] + gu1 * got[:, 1]) + gv1 * (gu0 * got[:, 2] + gu1 * got[:, 3])


def _bilinear_fetches(images: Tensor, points: Tensor) -> tuple[Tensor, tuple[Tensor, ...]]:
    """The four bilinear fetches behind a cubic B-spline evaluation, and their weights.

    A 4 x 4 B-spline sum is four bilinear fetches at shifted positions (Sigg & Hadwiger,
    GPU Gems 2, ch. 20). ``images`` (B, C, H, W) and ``points`` (B, n, 2) (u, v) px give the
    fetches (B, C, 4 n), fetch j of point i at index j n + i, and their weights
    ``(gu0, gu1, gv0, gv1)``, each (B, n), in the images' dtype.
    """
    B, C, H, W = images.shape
    n = points.shape[1]
    dtype = images.dtype
    # Both axes at once, (B, n, 2): the weights of the two fetches along each axis and their
    # positions already in grid_sample's [-1, 1] coordinates (align_corners=True).
    i = torch.floor(points)
    f = (points - i).to(dtype)  # the sub-pixel part, exact even when the coordinate is large
    i = i.to(dtype)
    f2 = f * f
    f3 = f2 * f
    w1 = (4 - 6 * f2 + 3 * f3) / 6
    g0 = (1 - f) ** 3 / 6 + w1
    g1 = 1 - g0
    scale = torch.tensor([2.0 / (W - 1), 2.0 / (H - 1)], dtype=dtype)
    p0 = (i - 1 + w1 / g0) * scale - 1
    p1 = (i + 1 + f3 / (6 * g1)) * scale - 1
    # The four fetches: (u0, v0), (u1, v0), (u0, v1), (u1, v1).
    u = torch.stack((p0[..., 0], p1[..., 0]), 1).repeat(1, 2, 1)
    v = torch.stack((p0[..., 1], p1[..., 1]), 1).repeat_interleave(2, 1)
    grid = torch.stack((u, v), -1)  # (B, 4, n, 2)
    got = torch.nn.functional.grid_sample(
        images, grid.view(B, 1, 4 * n, 2), mode="bilinear", padding_mode="reflection", align_corners=True,
    )
    gu0, gu1, gv0, gv1 = g0[..., 0], g1[..., 0], g0[..., 1], g1[..., 1]
    return got.view(B, C, 4 * n), (gu0, gu1, gv0, gv1)


@functools.lru_cache(maxsize=8)
def gaussian_kernel(sigma: float, dtype=torch.float64) -> Tensor:
    """Sampled, normalised 1-D Gaussian of standard deviation ``sigma`` px, radius ceil(2 sigma),
    shape (2 r + 1,); ``[1]`` for sigma = 0.

    The frames are blurred at the compared points by direct (2 r + 1)^2 sums, so the radius is
    what a registration costs per point; the reference is blurred by the same truncated kernel,
    so the two stay matched. On bench_registration's stacks radius 2 (sigma = 1) was as accurate
    as radius 3 (mean error 0.0031 / 0.0024 / 0.0043 px at 128^2 / 256^2 / 512^2, against
    0.0032 / 0.0036 / 0.0051). Cached: callers must not modify the result."""
    radius = int(math.ceil(2 * sigma))
    if radius == 0:
        return torch.ones(1, dtype=dtype)
    x = torch.arange(-radius, radius + 1, dtype=torch.float64)
    k = torch.exp(-0.5 * (x / sigma) ** 2)
    return (k / k.sum()).to(dtype)


def _spline_fetch(coefficients: Tensor, points: Tensor) -> Tensor:
    """Evaluate C cubic B-spline images (C, H, W) at every frame's points (F, N, 2) -> (C, F, N).

    The same four-bilinear-fetch evaluation as :func:`bspline_sample`, for C images shared by
    every frame and with fewer operations: the fit calls it with value and gradient channels at
    once, and its cost at small frames is mostly per operation. ``points`` are float64 (u, v) px, so that the
    sub-pixel part stays exact at any frame size; the rest is in the coefficients' dtype.
    Coefficients outside the image read as 0 (the cheapest padding): the values are exact at
    points at least 2 px inside the image, and the fit compares no others.
    """
    C, H, W = coefficients.shape
    F, N = points.shape[:2]
    dtype = coefficients.dtype
    i = torch.floor(points)
    f = (points - i).to(dtype)
    f2 = f * f
    w1 = (0.5 * f - 1).mul_(f2).add_(2 / 3)  # (4 - 6 f^2 + 3 f^3) / 6
    g0 = (1 - f) ** 3 / 6 + w1  # weight of the lower fetch
    g1 = 1 - g0
    # Fetch positions in grid_sample's [-1, 1] (align_corners=True), (2, F, N, 2): lower, upper.
    scale = _grid_scale(W, H, dtype)
    at = (torch.stack((w1 / g0 - 1, 1 + f2 * f / (6 * g1))) + i.to(dtype)) * scale - 1
    # The four fetches (u0, v0), (u1, v0), (u0, v1), (u1, v1): index [v fetch, u fetch].
    grid = torch.stack((at[None, :, ..., 0].expand(2, 2, F, N), at[:, None, ..., 1].expand(2, 2, F, N)), -1)
    got = grid_sample_threaded(coefficients[None], grid.view(1, 1, 4 * F * N, 2), mode="bilinear",
                               padding_mode="zeros", align_corners=True).view(C, 4, F, N)
    weights = torch.stack((g0, g1))  # (2, F, N, 2): [fetch, ..., axis]
    # The four fetches' weights (v weight times u weight), in the fetches' order: (4, F, N).
    weights = (weights[:, None, ..., 1] * weights[None, ..., 0]).view(4, F, N)
    return (got * weights).sum(1)


@functools.lru_cache(maxsize=16)
def _grid_scale(W: int, H: int, dtype) -> Tensor:
    """(2,) factors from px to grid_sample's align_corners=True coordinates, cached (callers
    must not modify them)."""
    return torch.tensor([2.0 / (W - 1), 2.0 / (H - 1)], dtype=dtype)
