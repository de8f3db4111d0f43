"""Scattered samples onto a grid: Gaussian splatting (normalized convolution, O(N)), moving
samples onto their lattice nodes, and filling the grid's holes.

Grid coordinates: node (i, j) is at x = j, y = i (HR px).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from hbis_torch.errors import HbisInputError


def common_offset(coords: Tensor) -> float:
    """Circular mean of the fractional parts of HR coordinates, in [-0.5, 0.5)."""
    angle = 2 * math.pi * coords
    z = torch.complex(torch.cos(angle).mean(), torch.sin(angle).mean())
    if float(z.abs()) < 0.2:  # no common offset (irregular samples): use the output grid
        return 0.0
    return float(torch.angle(z)) / (2 * math.pi)


def splat(values: Tensor, x: Tensor, y: Tensor, shape: tuple[int, int], sigma: float,
          weights: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """Splat scattered samples onto a grid with a Gaussian; O(N).

    Parameters
    ----------
    values, x, y : Tensor, shape (N,)
        Sample values and their grid coordinates (node (i, j) is at x = j, y = i).
    shape : (rows, cols)
    sigma : float
        Gaussian standard deviation in grid px; the footprint is the 3 x 3 nodes around the
        nearest one (enough for sigma <= 0.6).
    weights : Tensor, shape (N,), optional
        Per-sample weights (0 leaves a sample out).

    Returns
    -------
    numerator, denominator : Tensor, shape (rows, cols)
        sum of w g v and sum of w g over the samples near each node.
    """
    rows, cols = shape
    xi, yi = torch.round(x), torch.round(y)
    on_nodes = bool(((xi - x).abs().max() < 1e-9) & ((yi - y).abs().max() < 1e-9))
    w0 = torch.ones_like(values) if weights is None else weights
    if on_nodes:
        return _splat_on_nodes(values, xi, yi, shape, sigma, w0)
    num = torch.zeros(rows * cols, dtype=values.dtype)
    den = torch.zeros(rows * cols, dtype=values.dtype)
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            nx, ny = xi + dx, yi + dy
            inside = (nx >= 0) & (nx < cols) & (ny >= 0) & (ny < rows)
            g = torch.exp(-((nx - x) ** 2 + (ny - y) ** 2) / (2 * sigma * sigma)) * w0 * inside
            idx = (ny.clamp(0, rows - 1) * cols + nx.clamp(0, cols - 1)).long()
            num.index_add_(0, idx, g * values)
            den.index_add_(0, idx, g)
    return num.reshape(rows, cols), den.reshape(rows, cols)


def _splat_on_nodes(values: Tensor, xi: Tensor, yi: Tensor, shape: tuple[int, int], sigma: float,
                    weights: Tensor) -> tuple[Tensor, Tensor]:
    """:func:`splat` for samples that sit on nodes: the Gaussian's 3 x 3 weights are then the
    same for every sample, so the samples are summed per node once and the sums spread with the
    separable kernel [a, 1, a] x [a, 1, a], a = exp(-1 / (2 sigma^2))."""
    nodes = _OnNodes(xi, yi, shape, sigma, weights)
    return nodes.spread(nodes.w * values), nodes.spread(nodes.w)


class _OnNodes:
    """Samples sitting on nodes (integer ``xi``, ``yi``, shape (N,)): their node indices and
    weights, computed once for any number of value sets (:func:`_splat_on_nodes`)."""

    def __init__(self, xi: Tensor, yi: Tensor, shape: tuple[int, int], sigma: float, weights: Tensor):
        rows, cols = shape
        # A one-node frame around the grid keeps what samples just outside give to the border nodes.
        near = (xi >= -1) & (xi <= cols) & (yi >= -1) & (yi <= rows)
        self.idx = ((yi + 1) * (cols + 2) + xi + 1).clamp(0, (rows + 2) * (cols + 2) - 1).long()
        self.w = weights * near
        self.shape, self.a = shape, math.exp(-1 / (2 * sigma * sigma))

    def spread(self, weighted: Tensor) -> Tensor:
        """(rows, cols): the per-node sums of ``weighted`` (N,), spread with the 3 x 3 kernel."""
        rows, cols = self.shape
        sums = torch.zeros((rows + 2) * (cols + 2), dtype=weighted.dtype)
        sums.index_add_(0, self.idx, weighted)
        sums = sums.view(rows + 2, cols + 2)
        a = self.a
        sums = a * (sums[:, :-2] + sums[:, 2:]) + sums[:, 1:-1]
        return a * (sums[:-2] + sums[2:]) + sums[1:-1]


def splat_on_lattice(values: Tensor, x: Tensor, y: Tensor, shape: tuple[int, int], sigma: float,
                     weights: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """:func:`snap_to_lattice` followed by :func:`splat`, the same sums with one pass fewer: the
    snapped samples' nodes and weights (hence the denominator) serve both the pilot and the result.

    Parameters
    ----------
    values, x, y, shape, sigma, weights
        As :func:`snap_to_lattice`'s.

    Returns
    -------
    numerator, denominator : Tensor, shape (rows, cols)
        As :func:`splat`'s of :func:`snap_to_lattice`'s samples.
    """
    xn, yn = torch.round(x), torch.round(y)
    dx, dy = xn - x, yn - y
    nodes = _OnNodes(xn, yn, shape, sigma, torch.ones_like(values) if weights is None else weights)
    den = nodes.spread(nodes.w)
    num = nodes.spread(nodes.w * values)
    if float(torch.maximum(dx.abs(), dy.abs()).max()) < 1e-3:
        return num, den
    sx, sy = _slopes(fill_holes(num, den), x, y)
    return nodes.spread(nodes.w * (values + sx * dx + sy * dy)), den


def _slopes(pilot: Tensor, x: Tensor, y: Tensor) -> tuple[Tensor, Tensor]:
    """The gradient (d/dx, d/dy) of an image (rows, cols) at points (x, y), bilinear."""
    gy, gx = torch.gradient(pilot)
    rows, cols = pilot.shape
    grid = torch.stack((2 * x / max(cols - 1, 1) - 1, 2 * y / max(rows - 1, 1) - 1), -1)[None, None]
    slopes = torch.nn.functional.grid_sample(torch.stack((gx, gy))[None], grid.to(pilot.dtype),
                                             mode="bilinear", padding_mode="border", align_corners=True)
    return slopes[0, 0, 0], slopes[0, 1, 0]


def snap_to_lattice(values: Tensor, x: Tensor, y: Tensor, shape: tuple[int, int], sigma: float,
                    weights: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor]:
    """Move every sample to its nearest lattice node, correcting its value to first order.

    The deblurring models one sample per node. Samples a fraction of a node off it (motor
    errors, the optics' distortion) are moved there with value v + grad(Z) . (node - x), the
    gradient taken from a first interpolation Z of all samples (smooth: it carries the pixel's
    blur, built here from the snapped samples), so that the lattice model holds without the
    bias of snapping.

    Parameters
    ----------
    values, x, y : Tensor, shape (N,)
        Samples and their lattice coordinates.
    shape : (rows, cols)
    sigma : float
        Splat Gaussian of the first interpolation.
    weights : Tensor, shape (N,), optional

    Returns
    -------
    values, x, y : Tensor, shape (N,)
        Corrected values at integer coordinates.
    """
    xn, yn = torch.round(x), torch.round(y)
    dx, dy = xn - x, yn - y
    if float(torch.maximum(dx.abs(), dy.abs()).max()) < 1e-3:
        return values, xn, yn
    # The pilot's only job is the local slope; built from the snapped samples it costs no
    # Gaussian per sample, and the slope it gives is off by second-order terms only.
    sx, sy = _slopes(fill_holes(*splat(values, xn, yn, shape, sigma, weights)), x, y)
    return values + sx * dx + sy * dy, xn, yn


def _gaussian_blur(img: Tensor, sigma: float) -> Tensor:
    """Gaussian blur (rows, cols) with mirrored borders, via the FFT."""
    pad = min(int(math.ceil(4 * sigma)), img.shape[0] - 1, img.shape[1] - 1)
    p = torch.nn.functional.pad(img[None, None], (pad, pad, pad, pad), mode="reflect")[0, 0]
    fy = torch.fft.fftfreq(p.shape[0], dtype=img.dtype)[:, None]
    fx = torch.fft.rfftfreq(p.shape[1], dtype=img.dtype)[None, :]
    g = torch.exp(-2 * math.pi ** 2 * sigma ** 2 * (fx * fx + fy * fy))
    out = torch.fft.irfft2(torch.fft.rfft2(p) * g, s=p.shape)
    return out[pad:pad + img.shape[0], pad:pad + img.shape[1]]


def _blur_at(img: Tensor, sigma: float, rows: Tensor, cols: Tensor) -> Tensor:
    """:func:`_gaussian_blur` of ``img`` at the nodes (rows[i], cols[i]) only, (K,): sampled
    Gaussian taps out to 4 sigma, mirrored borders."""
    H, W = img.shape
    pad = min(int(math.ceil(4 * sigma)), H - 1, W - 1)
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


def fill_holes(num: Tensor, den: Tensor) -> Tensor:
    """num / den, with nodes of little weight taken from the sums blurred wider and wider.

    Only the holes' blurred values are used: where there are few of them (a frame's border)
    they are computed at the holes alone (:func:`_blur_at`), else by blurring the whole image.
    """
    typical = float(den[den > 0].median()) if bool((den > 0).any()) else 0.0
    if typical == 0.0:
        raise HbisInputError("no sample falls on the output grid")
    image = num / den.clamp_min(1e-12)
    rows, cols = torch.nonzero(den < 0.25 * typical).unbind(1)
    sigma = 1.0
    while len(rows) and sigma <= 64:
        taps = 2 * int(math.ceil(4 * sigma)) + 1
        if len(rows) * taps * taps <= num.numel() // 4:
            n2, d2 = _blur_at(num, sigma, rows, cols), _blur_at(den, sigma, rows, cols)
        else:
            n2, d2 = _gaussian_blur(num, sigma)[rows, cols], _gaussian_blur(den, sigma)[rows, cols]
        ok = d2 >= 0.05 * typical
        image[rows[ok], cols[ok]] = n2[ok] / d2[ok].clamp_min(1e-12)
        rows, cols = rows[~ok], cols[~ok]
        sigma *= 2
    if len(rows):
        image[rows, cols] = num.sum() / den.sum()
    return image
