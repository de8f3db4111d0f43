"""The periodic + smooth split of an image (Moisan 2011) that keeps the FFT's borders quiet in
the Wiener step, and the smooth part's sub-pixel shift: bicubic with mirrored borders
(:func:`shift_image`), or, with the same result, in the Fourier domain on the periodic
spectrum (:func:`add_shifted_smooth`) plus the few border rows and columns where mirrored and
periodic taps differ (:func:`mirror_borders`), so that the smooth part is never inverted on
its own.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

# Rows of a spectrum or image handled at a time where temporaries per row are needed: they then
# stay a few MB whatever the image's size.
BLOCK_ROWS = 256

# Rows (and columns) at each border that the bicubic's taps of the two rows next to it reach,
# mirrored or wrapped around: :func:`mirror_borders` needs an image of at least twice this.
BAND = 4


def _row_blocks(rows: int) -> list[slice]:
    return [slice(r, min(r + BLOCK_ROWS, rows)) for r in range(0, rows, BLOCK_ROWS)]


def smooth_spectrum(image: Tensor) -> Tensor:
    """The rfft2 of the smooth part s of :func:`periodic_smooth`, (rows, cols // 2 + 1) complex,
    in ``image``'s precision: the image's own rfft2 less this is the periodic part's.

    References
    ----------
    .. [1] L. Moisan, "Periodic plus smooth image decomposition", Journal of Mathematical Imaging
       and Vision 39(2), 2011, pp. 161-179.
    """
    M, N = image.shape
    # The boundary image v (the jumps across opposite borders: rows 0 and M - 1 hold
    # +-(image[-1] - image[0]), columns 0 and N - 1 likewise) is zero inside, so its rfft2 is
    # two outer products of 1-D transforms: A(r) (1 - e^(2 pi i q / M)) + B(q) (1 - e^(2 pi i r / N)).
    complex_dtype = image.dtype.to_complex()
    rows = torch.fft.rfft(image[-1, :] - image[0, :])  # A, (N // 2 + 1,)
    cols = torch.fft.fft(image[:, -1] - image[:, 0])  # B, (M,)
    turn_q = 1 - torch.exp(2j * math.pi * torch.arange(M, dtype=torch.float64) / M).to(complex_dtype)
    turn_r = 1 - torch.exp(2j * math.pi * torch.arange(N // 2 + 1, dtype=torch.float64) / N).to(complex_dtype)
    # the denominator 2 cos(2 pi q / M) + 2 cos(2 pi r / N) - 4 from its two 1-D parts
    cos_q = 2 * torch.cos(2 * math.pi * torch.arange(M, dtype=image.dtype) / M)
    cos_r = 2 * torch.cos(2 * math.pi * torch.arange(N // 2 + 1, dtype=image.dtype) / N)
    S = torch.empty((M, N // 2 + 1), dtype=complex_dtype)
    # a block of rows at a time, while its temporaries are in the cache
    for block in _row_blocks(M):
        part = torch.mul(turn_q[block, None], rows[None, :], out=S[block])
        part.add_(cols[block, None] * turn_r[None, :])
        den = (cos_q[block, None] + cos_r[None, :]).sub_(4)
        if block.start == 0:
            den[0, 0] = 1.0
        torch.view_as_real(part).div_(den[..., None])  # as real pairs: a third of a complex division's time
    S[0, 0] = 0
    return S


def periodic_smooth(image: Tensor, in_place: bool = False) -> tuple[Tensor, Tensor]:
    """Periodic plus smooth decomposition (Moisan, J. Math. Imaging Vis. 39, 2011).

    image = p + s with p periodic (no jump between opposite borders) and s smooth (its
    Laplacian vanishes inside; it carries the border jumps). Shapes (rows, cols); ``in_place``
    writes p over ``image``.

    References
    ----------
    .. [1] L. Moisan, "Periodic plus smooth image decomposition", Journal of Mathematical Imaging
       and Vision 39(2), 2011, pp. 161-179.
    """
    s = torch.fft.irfft2(smooth_spectrum(image), s=image.shape)
    return (image.sub_(s) if in_place else image - s), s


def shift_image(image: Tensor, offset: tuple[float, float], add_to: Tensor | None = None) -> Tensor:
    """A smooth image whose node j sits at coordinate j + offset, resampled at the integer
    coordinates (that is, at nodes j - offset): bicubic, borders mirrored. Used for the smooth
    part of the periodic + smooth split, which varies slowly, so a cubic needs no prefilter.

    The interpolation is ``grid_sample``'s (bicubic, A = -0.75, reflection about the border
    nodes, align_corners=True); the offset being the same for every node, it is applied as two
    4-tap filters, one per axis, a block of rows at a time (no (rows, cols, 2) grid: a full
    frame's 0.5 GB). Shapes (rows, cols); with ``add_to`` the result is added to it in place
    (and returned).
    """
    if offset == (0.0, 0.0):
        return image if add_to is None else add_to.add_(image)
    rows, cols = image.shape
    out = torch.zeros_like(image) if add_to is None else add_to
    wx, ix = _cubic_taps(float(offset[0]), cols)
    wy, iy = _cubic_taps(float(offset[1]), rows)
    for block in _row_blocks(rows):
        n = block.stop - block.start
        part = image.index_select(0, iy[block.start:block.stop + 3]).index_select(1, ix)  # (n + 3, cols + 3)
        across = sum(w * part[:, k:k + cols] for k, w in enumerate(wx))
        out[block] += sum(w * across[k:k + n] for k, w in enumerate(wy))
    return out


def _cubic_taps(shift: float, n: int) -> tuple[list[float], Tensor]:
    """The bicubic (Keys, A = -0.75, as ``grid_sample``'s) that resamples n nodes at j - ``shift``:
    its 4 weights, and the indices (n + 3,) whose entries j .. j + 3 are node j's taps, reflected
    about the first and last nodes."""
    start = math.floor(-shift)
    t, A = -shift - start, -0.75
    weights = [(((A * (t + 1) - 5 * A) * (t + 1) + 8 * A) * (t + 1) - 4 * A),
               ((A + 2) * t - (A + 3)) * t * t + 1,
               ((A + 2) * (1 - t) - (A + 3)) * (1 - t) * (1 - t) + 1,
               ((A * (2 - t) - 5 * A) * (2 - t) + 8 * A) * (2 - t) - 4 * A]
    index = torch.arange(n + 3) + (start - 1)
    if n == 1:
        return weights, torch.zeros_like(index)
    index = index.remainder(2 * (n - 1))  # reflect about 0 and n - 1 (period 2 (n - 1))
    return weights, torch.where(index > n - 1, 2 * (n - 1) - index, index)


def _periodic_taps(shift: float, n: int) -> Tensor:
    """:func:`_cubic_taps`'s indices (n + 3,) with the n nodes taken as periodic, not mirrored."""
    return (torch.arange(n + 3) + (math.floor(-shift) - 1)).remainder(n)


def _shift_factor(shift: float, n: int, count: int, dtype) -> Tensor:
    """:func:`_cubic_taps`'s 4-tap filter along an axis of n nodes, applied periodically, as a
    DFT multiplier at frequencies k = 0 .. count - 1: sum_b w_b exp(2 pi i k (b + start - 1) / n)."""
    weights, _ = _cubic_taps(shift, n)
    start = math.floor(-shift)
    k = torch.arange(count, dtype=torch.float64)
    factor = sum(w * torch.exp(2j * math.pi * k * ((b + start - 1) / n)) for b, w in enumerate(weights))
    return factor.to(dtype)


def add_shifted_smooth(spectrum: Tensor, smooth: Tensor, shape: tuple[int, int], offset: tuple[float, float]) -> Tensor:
    """Add to an rfft2 ``spectrum`` (in place) that of :func:`shift_image` of the smooth part,
    taken periodically; :func:`mirror_borders` then makes its borders mirrored.

    Parameters
    ----------
    spectrum, smooth : Tensor, shape (rows, cols // 2 + 1), complex
        A half spectrum, and that of the smooth part (:func:`smooth_spectrum`).
    shape : (rows, cols)
        The image's.
    offset : (dx, dy)
        :func:`shift_image`'s, HR px.

    Returns
    -------
    Tensor: ``spectrum``
    """
    rows, cols = shape
    along_x = _shift_factor(float(offset[0]), cols, smooth.shape[1], smooth.dtype)
    along_y = _shift_factor(float(offset[1]), rows, rows, smooth.dtype)
    for block in _row_blocks(rows):
        spectrum[block] += smooth[block].mul(along_y[block, None]).mul_(along_x[None, :])
    return spectrum


def _smooth_band(smooth: Tensor, rows: Tensor, cols: Tensor, shape: tuple[int, int]) -> tuple[Tensor, Tensor]:
    """Rows ``rows`` (K,) and columns ``cols`` (L,) of irfft2(``smooth``, shape): (K, cols) and
    (rows, L), without the whole inverse.

    Rows: the inverse along the rows' axis at those rows alone (a (K, rows) matrix), then irfft
    along each. Columns: irfft2 is the real part of (1/N) sum_r c_r Y(m, r) e^(2 pi i r n / N),
    Y the inverse along the rows' axis, c_r = 2 but at r = 0 and r = N / 2 (where it is 1): the
    sum over r first, at the L columns, then the inverse along the rows' axis of those alone.
    Both products in float64, one pass over ``smooth`` a block of rows at a time: BLAS's sums may
    split with the threads, and the image must not depend on their number (at float32's
    rounding a float64 sum's order never shows).
    """
    M, N = shape
    half = smooth.shape[1]
    inverse = torch.exp(2j * math.pi * torch.outer(rows.double(), torch.arange(M, dtype=torch.float64)) / M) / M
    count = torch.full((half,), 2.0, dtype=torch.float64)
    count[0] = 1.0
    if N % 2 == 0:
        count[-1] = 1.0
    freq = torch.arange(half, dtype=torch.float64)
    forward = count[:, None] * torch.exp(2j * math.pi * torch.outer(freq, cols.double()) / N) / N
    at_rows = torch.zeros((len(rows), half), dtype=torch.complex128)
    at_cols = []
    for block in _row_blocks(M):
        part = smooth[block].to(torch.complex128)
        at_rows += inverse[:, block] @ part
        at_cols.append(part @ forward)
    real = smooth.real.dtype
    return (torch.fft.irfft(at_rows, n=N, dim=1).to(real),
            torch.fft.ifft(torch.cat(at_cols), dim=0).real.to(real))


def mirror_borders(out: Tensor, smooth: Tensor, offset: tuple[float, float]) -> Tensor:
    """Where :func:`add_shifted_smooth`'s periodic shift of the smooth part differs from
    :func:`shift_image`'s mirrored one (the two rows and columns next to each border, whose
    taps reach past it), add the difference to ``out`` (rows, cols) in place: the smooth part
    at the :data:`BAND` rows and columns next to each border, from its spectrum ``smooth``,
    shifted both ways. ``out`` needs at least 2 :data:`BAND` rows and columns."""
    M, N = out.shape
    rows_at = torch.cat((torch.arange(BAND), torch.arange(M - BAND, M)))
    cols_at = torch.cat((torch.arange(BAND), torch.arange(N - BAND, N)))
    at_row = torch.full((M,), -1, dtype=torch.long)
    at_row[rows_at] = torch.arange(2 * BAND)
    at_col = torch.full((N,), -1, dtype=torch.long)
    at_col[cols_at] = torch.arange(2 * BAND)
    wx, mirror_x = _cubic_taps(float(offset[0]), N)
    wy, mirror_y = _cubic_taps(float(offset[1]), M)
    wrap_x, wrap_y = _periodic_taps(float(offset[0]), N), _periodic_taps(float(offset[1]), M)
    # the rows next to the top and bottom, every column (corners included): shifted along x
    # both ways, then along y
    band, band_cols = _smooth_band(smooth, rows_at, cols_at, (M, N))  # (2 BAND, N), (M, 2 BAND)
    mirrored = sum(w * band[:, mirror_x[b:b + N]] for b, w in enumerate(wx))
    wrapped = sum(w * band[:, wrap_x[b:b + N]] for b, w in enumerate(wx))
    for i in (0, 1, M - 2, M - 1):
        out[i] += sum(w * (mirrored[at_row[mirror_y[i + a]]] - wrapped[at_row[wrap_y[i + a]]])
                      for a, w in enumerate(wy))
    # the columns next to the left and right, the other rows (whose taps along y stay inside)
    down = sum(w * band_cols[wrap_y[a:a + M]] for a, w in enumerate(wy))[2:M - 2]
    for j in (0, 1, N - 2, N - 1):
        out[2:M - 2, j] += sum(w * (down[:, at_col[mirror_x[j + b]]] - down[:, at_col[wrap_x[j + b]]])
                               for b, w in enumerate(wx))
    return out
