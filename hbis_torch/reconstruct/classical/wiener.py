"""Wiener (MMSE linear) deblurring of the interpolated image, with aliasing and a fitted
power-law scene prior; the FFT's borders are kept quiet by the periodic + smooth split
(:mod:`.periodic`).
"""

from __future__ import annotations

import math
from functools import partial
from typing import NamedTuple

import torch
from torch import Tensor

from hbis_torch.reconstruct.classical.periodic import (
    BAND,
    BLOCK_ROWS,
    _row_blocks,
    add_shifted_smooth,
    mirror_borders,
    shift_image,
    smooth_spectrum,
)
from hbis_torch.reconstruct.classical import transfer
from hbis_torch.reconstruct.classical.transfer import box, diffraction_otf, gaussian_transfer, splat_transfer

# The deblurring never trusts the data more than this noise level (intensity units, [0, 1], for
# an image whose brightest value is 1; in proportion below that): below it the model's own errors
# (the periodic-border split, the prior, positions known to ~1e-3 px) dominate, and a sharper
# filter would amplify them near the aperture's zeros. Those errors are a share of the signal, so
# the floor follows the image's level: a 12-bit camera's values in a 16-bit file without their
# bit depth fill a sixteenth of [0, 1], and a fixed floor had blurred them (8-bit values read as
# 16-bit: hbis validate 10.6 dB below the single frame).
NOISE_FLOOR = 2e-3

# Half spectra of at least this many frequencies (a 2048 x 2560 image has 2.6 M, a full frame
# at h = 4 9.8 M, at h = 7 30 M) are inverted in place (:func:`_irfft2_in_place`): faster
# than irfft2 from there on, and less memory.
IN_PLACE_FFT_SIZE = 2 ** 20

# The aliases' terms (k != 0) are smooth in frequency: sinc's whose period is at least the LR
# side in frequencies of the spectrum, a power law away from its pole, the lens's OTF. They are
# evaluated on every n-th frequency along each axis, at least this many per period, and
# interpolated linearly in between (:class:`_AliasSums`): the filter moves by under 1e-4 of its
# largest value (tests/test_classical_fast.py), the full frame's image at h = 4 by 3e-7.
ALIAS_SAMPLES = 128

def wiener_deblur(
    image: Tensor, h: int, offset: tuple[float, float], kernel_sigma: float, noise: float,
    aperture: float = 1.0, cutoff: float | None = None, strength: float = 1.0, aliases: int = 1,
    dtype=torch.float32, overwrite: bool = False, lens_sigma: float = 0.0, fit_below: float | None = None,
    target_aperture: float | None = None,
) -> Tensor:
    """Wiener (MMSE linear) estimate of the p/h sensor's image from the interpolated one.

    Model, at frequency f in cycles per HR px (the splat's own transfer is divided out first):
    the image is the scene S seen through the kernel K and sampled on the HR lattice shifted
    by ``offset``; the wanted image is S seen through W and sampled on the output lattice::

        K(f) = optics(f) lens(f) box(h a, f) exp(2 pi i f . offset),   W(f) = optics(f) box(t, f)
        image(f) = sum_k S(f + k) K(f + k) + N(f),                  N white, std ``noise``

    (a = ``aperture``, t = ``target_aperture``), where k runs over the integer aliases (abs(k) <= ``aliases`` per axis).
    ``lens`` is a Gaussian blur beyond the diffraction of ``optics`` (a burst's lens, measured
    or given: ``lens_sigma``), in the kernel only, so the estimate undoes it; known to a spread
    (:func:`~.transfer.lens_transfer`): its mean where K has it, its square's mean in abs(K)^2.
    **Prior:** the scene's power spectrum is s^2 / abs(f)^2 (independent Gaussian gradients, the
    1/f^2 law of natural images). The MMSE filter is then, per frequency::

        sum_k P(f+k) W(f+k) conj(K(f+k)) / (sum_k P(f+k) abs(K(f+k))^2 + noise^2),

    which also treats the energy that aliases into f as noise rather than as signal to sharpen.
    s^2 is fitted to the image's own spectrum (less the noise) over the band the kernel passes.

    Parameters
    ----------
    image : Tensor, shape (rows, cols)
        Interpolated image on the grid shifted by ``offset`` (HR px) from the output grid.
    h : int
        Ratio of LR to HR pixel pitch.
    offset : (dx, dy)
        Where the interpolation grid's nodes sit relative to the output pixels, HR px.
    kernel_sigma : float
        Splat Gaussian (HR px).
    noise : float
        Standard deviation of the white noise per node, before the splat's smoothing.
    aperture : float
        Side of a pixel's square light-sensitive area over its pitch, sqrt(fill factor).
    cutoff : float or None
        Optical cutoff in cycles per LR px (None: optics ignored).
    strength : float
        Multiplies the noise power (1: the estimated noise).
    aliases : int
        Aliases summed per axis on each side.
    dtype : torch.dtype
        Of the FFTs and the filter (float32: within about 1e-6 of float64's, far below the noise
        floor; tests/test_fullframe.py checks it). The prior's fit is always float64.
    overwrite : bool
        ``image``'s memory may be reused (for the periodic part, then the result, which is then
        ``image`` itself if it is of ``dtype``); its content is lost.
    lens_sigma : float
        Standard deviation (LR px) of a Gaussian lens blur in the kernel (0: none).
    fit_below : float or None
        :func:`fit_spectrum`'s ``highest`` (cycles per HR px; a burst's: ``1 / h``).
    target_aperture : float or None
        The side of the output pixel that the wanted image averages the scene over, over its
        pitch (None: ``aperture``, a sensor h times finer; 0: the scene at the pixels' centres).

    Returns
    -------
    Tensor, shape (rows, cols), in ``image``'s dtype

    References
    ----------
    .. [1] N. Wiener, *Extrapolation, Interpolation, and Smoothing of Stationary Time Series*,
       MIT Press, 1949 (the minimum-mean-square-error linear filter).
    .. [2] L. Moisan, "Periodic plus smooth image decomposition", Journal of Mathematical Imaging
       and Vision 39(2), 2011, pp. 161-179 (:func:`periodic_smooth`).
    """
    # The FFT sees the image as periodic; its borders' jumps would ring through the whole image
    # at the frequencies the pixel aperture nearly erases. Deblur only the periodic part and
    # add the smooth rest back (Moisan 2011): the periodic part's spectrum is the image's less
    # the smooth part's, and the smooth part, shifted, is added to the filtered spectrum, so that
    # one rfft2 and one irfft2 do (images smaller than two BANDs: the smooth part on its own).
    work = image.to(dtype)
    own = overwrite or work.data_ptr() != image.data_ptr()  # work's memory may be reused
    shape = work.shape
    level = min(1.0, max(float(work.max()), 1e-3))  # of NOISE_FLOOR
    smooth = smooth_spectrum(work)
    spectrum = torch.fft.rfft2(work)
    work = work if own else None  # kept for the result, or freed
    fy = torch.fft.fftfreq(shape[0], dtype=torch.float64)[:, None]
    fx = torch.fft.rfftfreq(shape[1], dtype=torch.float64)[None, :]
    # the image's power |Z|^2 / n, from the real pairs (abs's square root squared: 2.5 times as long)
    measured = torch.empty(spectrum.shape, dtype=dtype) if h != 1 else None
    # One pass a block of rows at a time (while it is in the cache): the periodic part's spectrum
    # (the image's less the smooth part's), the splat's transfer divided out, the power.
    for block in _row_blocks(shape[0]):
        parts = torch.view_as_real(spectrum[block])  # real pairs: faster than complex ops
        parts.sub_(torch.view_as_real(smooth[block]))
        transfer = (splat_transfer(fx, kernel_sigma) * splat_transfer(fy[block], kernel_sigma)).to(dtype)
        parts.div_(transfer[..., None])
        if measured is not None:
            torch.mul(parts[..., 0], parts[..., 0], out=measured[block]).addcmul_(parts[..., 1], parts[..., 1])
            measured[block].div_(shape[0] * shape[1])
    del parts
    if min(shape) < 2 * BAND:
        smooth = torch.fft.irfft2(smooth, s=shape)

    if h == 1:  # nothing to deblur: only the splat's smoothing is undone
        return _add_smooth(spectrum, smooth, shape, offset, work).to(image.dtype)
    eps2 = (0.5 / max(shape)) ** 2  # keeps the prior finite at f = 0
    shifts = [(kx, ky) for ky in range(-aliases, aliases + 1) for kx in range(-aliases, aliases + 1)]
    noise2 = max(noise, NOISE_FLOOR * level) ** 2
    # the prior's fit evaluates the model on a subsample, in float64
    kernel = partial(_alias_kernel, fx, fy, h, aperture, cutoff, offset, eps2, lens_sigma=lens_sigma,
                     target=target_aperture)
    s2, beta = fit_spectrum(measured, fx, fy, kernel, shifts, noise2, highest=fit_below)
    model = _Model(fx[0].to(dtype), fy[:, 0].to(dtype), h, aperture, cutoff, offset, eps2, lens_sigma,
                   target_aperture)
    # the power averaged over 3 x 3 frequencies for the filter's prior (which needs each block's
    # neighbours as they were before filtering)
    _apply_filter(spectrum, _mean_3x3(measured), model, (shifts, s2, beta, noise2, strength))
    del measured  # a half spectrum's worth (120 MB at h = 7), not held through the inverse
    return _add_smooth(spectrum, smooth, shape, offset, work).to(image.dtype)


def _apply_filter(spectrum: Tensor, measured: Tensor, model: _Model, terms: tuple) -> None:
    """Multiply the half ``spectrum`` (rows, cols // 2 + 1) by the MMSE filter in place, a block
    of rows at a time: rows of opposite fy (i and rows - i) share their aliases' terms
    (:func:`_mmse_filter`), so a block of rows 0 < i < rows / 2 is filtered with its mirror
    block, rows 0 and rows / 2 alone. ``measured`` is the power averaged over 3 x 3
    frequencies, ``terms`` :func:`_mmse_filter`'s (shifts, s2, beta, noise2, strength)."""
    rows = spectrum.shape[0]
    aliases = _AliasSums(model, *terms[:3])
    for start in range(1, (rows + 1) // 2, BLOCK_ROWS):
        block = slice(start, min(start + BLOCK_ROWS, (rows + 1) // 2))
        # the mirror rows rows - i, ascending (a slice, not gathered): its filter flipped to them
        mirror = slice(rows - block.stop + 1, rows - block.start + 1)
        ahead, behind = _mmse_filter(measured[block], model._replace(fy=model.fy[block]), aliases.at(block),
                                     *terms[1:], mirrored=measured[mirror].flip(0))
        spectrum[block] *= ahead
        spectrum[mirror] *= behind.flip(0)
    spectrum[0] *= _mmse_filter(measured[:1], model._replace(fy=model.fy[:1]), aliases.at(slice(0, 1)),
                                *terms[1:])[0][0]
    if rows % 2 == 0 and rows > 1:  # fy = -1/2: alias (kx, ky) there is (kx, -ky) at +1/2, the mirrored side
        half = slice(rows // 2, rows // 2 + 1)
        spectrum[half] *= _mmse_filter(measured[half], model._replace(fy=model.fy[half]),
                                       aliases.at(half, mirrored=True), *terms[1:])[0]


class _AliasSums:
    """The aliases' (k != 0) sums of :func:`_mmse_filter` over the half spectrum's frequencies,
    from a coarse grid (:data:`ALIAS_SAMPLES`): for rows i of fy = +i / rows (0 <= i <= rows / 2;
    row rows - i, fy = -i / rows, has the same terms with ky's phase negated, the mirrored side).

    Attributes
    ----------
    power : Tensor, shape (coarse rows, coarse columns)
        sum_k P abs(K)^2.
    cross : list of two (re, im) pairs of such tensors
        sum_k P abs(K) W exp(-2 pi i k . offset) (the lattice phase's constant part), at +fy, then
        at -fy.
    """

    def __init__(self, model: _Model, shifts, s2: float, beta: float):
        rows, half = len(model.fy), len(model.fx)
        stride = max(1, min(rows, 2 * (half - 1)) // model.h // ALIAS_SAMPLES)
        self.row_nodes = _coarse(rows // 2 + 1, stride)
        col_nodes = _coarse(half, stride)
        fy = self.row_nodes.to(model.fx.dtype) / rows  # |fy|
        coarse = model._replace(fx=model.fx[col_nodes], fy=fy)
        shape = (len(fy), len(col_nodes))
        power = torch.zeros(shape, dtype=model.fx.dtype)
        cross = [(torch.zeros(shape, dtype=power.dtype), torch.zeros(shape, dtype=power.dtype)) for _ in (1, -1)]
        for kx, ky in shifts:
            if (kx, ky) == (0, 0):
                continue
            rows_k, cols_k = coarse.band(ky, coarse.fy), coarse.band(kx, coarse.fx)
            if len(rows_k) == 0 or len(cols_k) == 0:
                continue
            prior, k_mag, w, k2 = coarse.terms(kx, ky, rows_k, cols_k, s2, beta)
            _add_at(power, rows_k, cols_k, prior * k2)
            weighted = prior.mul_(k_mag)
            weighted *= w
            for (cross_re, cross_im), sign in zip(cross, (1, -1)):
                angle = 2 * math.pi * (kx * model.offset[0] + sign * ky * model.offset[1])
                _add_at(cross_re, rows_k, cols_k, weighted, math.cos(angle))
                _add_at(cross_im, rows_k, cols_k, weighted, -math.sin(angle))
        self.power, self.cross, self.along = power, cross, _interpolation(col_nodes, half)

    def at(self, block: slice, mirrored: bool = False) -> tuple[Tensor, list]:
        """(power, cross) at rows ``block`` of fy >= 0 (each (rows, cols // 2 + 1)): cross at
        +fy and -fy, or with ``mirrored`` the -fy side alone (the row fy = -1/2)."""
        down = _interpolation(self.row_nodes, block.stop, block.start)

        def fine(values: Tensor) -> Tensor:  # rows first: the coarse grid is the smaller
            return _lerp(_lerp(values, down, dim=0), self.along, dim=1)

        pairs = self.cross[1:] if mirrored else self.cross
        return fine(self.power), [tuple(fine(t) for t in pair) for pair in pairs]


def _coarse(n: int, stride: int) -> Tensor:
    """Every ``stride``-th of 0 .. n - 1, and n - 1."""
    nodes = torch.arange(0, n, stride)
    return nodes if int(nodes[-1]) == n - 1 else torch.cat((nodes, torch.tensor([n - 1])))


def _interpolation(nodes: Tensor, stop: int, start: int = 0) -> tuple[Tensor, Tensor]:
    """Linear interpolation from values at increasing ``nodes`` (from 0) to start .. stop - 1: the
    left node's position in ``nodes`` and the weight of the right one."""
    at = torch.arange(start, stop)
    if len(nodes) == 1:
        return torch.zeros(len(at), dtype=torch.long), torch.zeros(len(at))
    left = (torch.searchsorted(nodes, at, right=True) - 1).clamp_(0, len(nodes) - 2)
    t = (at - nodes[left]) / (nodes[left + 1] - nodes[left])
    return left, t


def _lerp(values: Tensor, where: tuple[Tensor, Tensor], dim: int) -> Tensor:
    """``values`` interpolated along ``dim`` (:func:`_interpolation`'s ``where``)."""
    left, t = where
    if len(left) and not bool(t.any()) and len(left) == values.shape[dim]:
        return values.clone()  # every node kept (stride 1)
    lo = values.index_select(dim, left)
    if values.shape[dim] == 1:
        return lo
    hi = values.index_select(dim, left + 1)
    shape = [1, 1]
    shape[dim] = -1
    return lo.lerp_(hi, t.to(values.dtype).view(shape))


def _add_smooth(spectrum: Tensor, smooth: Tensor, shape: tuple[int, int], offset: tuple[float, float],
                out: Tensor | None) -> Tensor:
    """The filtered periodic part's ``spectrum`` inverted (into ``out``, if given; ``spectrum``
    is overwritten) plus the smooth part shifted by ``offset`` (:func:`shift_image`): given as
    its spectrum (added before the inverse, the borders mended after), or as an image (shape
    ``shape``: added after the inverse)."""
    if smooth.is_complex():
        add_shifted_smooth(spectrum, smooth, shape, offset)
        out = _irfft2_in_place(spectrum, shape, out=out)
        return out if offset == (0.0, 0.0) else mirror_borders(out, smooth, offset)
    return shift_image(smooth, offset, add_to=_irfft2_in_place(spectrum, shape, out=out))


def _mean_3x3(power: Tensor) -> Tensor:
    """``avg_pool2d(power, 3, 1, 1, count_include_pad=False)`` of (rows, cols) as two separable
    sums divided by the neighbours counted (a tenth of avg_pool2d's time); ``power`` is
    overwritten with the result."""
    rows, cols = power.shape
    across = power.clone()
    across[:, 1:] += power[:, :-1]
    across[:, :-1] += power[:, 1:]
    power.copy_(across)
    power[1:] += across[:-1]
    power[:-1] += across[1:]
    del across

    def counted(n: int) -> Tensor:  # neighbours along one axis: 3, 2 at either end
        count = torch.full((n,), 3.0, dtype=power.dtype)
        count[0] -= 1
        count[-1] -= 1
        return count if n > 1 else torch.ones(1, dtype=power.dtype)

    return power.div_(counted(rows)[:, None]).div_(counted(cols)[None, :])


def _irfft2_in_place(spectrum: Tensor, shape: tuple[int, int], out: Tensor | None = None) -> Tensor:
    """``torch.fft.irfft2(spectrum, s=shape, out=out)`` without its spectrum-sized temporary.

    The inverse along the columns is done a block of columns at a time, written back into
    ``spectrum`` (which is overwritten), then the rows' inverse a block of rows at a time into
    ``out``: 240 MB less at the peak for a full frame at h = 7, and half irfft2's time on large
    images (torch 2.13, idle cores, 2 threads: 0.12 s against 0.25 s at 3840 x 5120, 0.39 s
    against 0.74 s at 6720 x 8960; 0.9 times at 2048 x 2560, the same at 1024 x 1280), which is
    why spectra under :data:`IN_PLACE_FFT_SIZE` go to irfft2 itself. The values are the same.
    """
    if spectrum.numel() < IN_PLACE_FFT_SIZE:
        return torch.fft.irfft2(spectrum, s=shape, out=out)
    rows, cols = shape
    if out is None:
        out = torch.empty(shape, dtype=spectrum.real.dtype)
    for block in _row_blocks(spectrum.shape[1]):
        spectrum[:, block] = torch.fft.ifft(spectrum[:, block], dim=0)
    for block in _row_blocks(rows):
        out[block] = torch.fft.irfft(spectrum[block], n=cols, dim=1)
    return out


def _alias_kernel(fx: Tensor, fy: Tensor, h: int, aperture: float, cutoff: float | None,
                  offset: tuple[float, float], eps2: float, kx: int, ky: int,
                  pick: tuple[Tensor, Tensor] | None = None, lens_sigma: float = 0.0, target: float | None = None):
    """abs(K), W, the lattice phase and abs(f + k)^2 of alias (kx, ky): on the whole spectrum's
    grid, or at the (row, column) pairs ``pick`` (then without the phase). The separable
    factors are computed along each axis once.

    ``fx`` (1, cols) and ``fy`` (rows, 1) are the half spectrum's frequencies in cycles per HR
    px; ``h``, ``aperture``, ``cutoff`` and ``offset`` are :func:`wiener_deblur`'s, and ``eps2``
    (cycles^2 per HR px^2) keeps abs(f + k)^2 above 0. :func:`wiener_deblur` binds all but
    (kx, ky, pick) with :func:`functools.partial`.
    """
    gx, gy = fx + kx, fy + ky  # (1, cols), (rows, 1)
    box_x, box_y = box(gx, h * aperture), box(gy, h * aperture)
    target = aperture if target is None else target
    pix_x, pix_y = box(gx, target), box(gy, target)
    if pick is not None:
        rows, cols = pick
        gx, box_x, pix_x = (t[0].index_select(0, cols) for t in (gx, box_x, pix_x))
        gy, box_y, pix_y = (t[:, 0].index_select(0, rows) for t in (gy, box_y, pix_y))
    r2 = gx * gx + gy * gy + eps2
    optics = torch.ones_like(r2) if cutoff is None else diffraction_otf(torch.sqrt(r2) * h / cutoff)
    k_mag, w = optics * box_x * box_y, optics * pix_x * pix_y
    if lens_sigma > 0:
        k_mag = k_mag * gaussian_transfer(r2, lens_sigma * h)
    if pick is not None:
        return k_mag, w, None, r2
    # The lattice's phase factor is separable too: two 1-D exponentials, one product.
    phase = torch.exp(-2j * math.pi * gx * offset[0]) * torch.exp(-2j * math.pi * gy * offset[1])
    return k_mag, w, phase, r2


class _Model(NamedTuple):
    """The image model of :func:`wiener_deblur` on the half spectrum's frequencies: ``fx``
    (cols,) and ``fy`` (rows,) in cycles per HR px (the dtype of the filter), and the other
    arguments as there."""

    fx: Tensor
    fy: Tensor
    h: int
    aperture: float
    cutoff: float | None
    offset: tuple[float, float]
    eps2: float
    lens_sigma: float = 0.0
    target: float | None = None  # wiener_deblur's target_aperture (None: aperture)

    def band(self, k: int, f: Tensor) -> Tensor:
        """Indices along one axis where alias k can pass the optics (abs(f + k) below the cutoff,
        in cycles per HR px): elsewhere its every term is 0."""
        if self.cutoff is None:
            return torch.arange(len(f))
        return torch.nonzero((f + k).abs() < self.cutoff / self.h)[:, 0]

    def terms(self, kx: int, ky: int, rows: Tensor, cols: Tensor, s2: float, beta: float):
        """The prior P = s2 abs(f + k)^-beta, abs(K), W and abs(K)^2 of alias (kx, ky) at rows x cols:
        the lens's transfer in abs(K) is its mean over :data:`~.transfer.LENS_SPREAD`, in abs(K)^2 its
        square's (:func:`~.transfer.lens_transfer`)."""
        gx, gy = self.fx[cols][None, :] + kx, self.fy[rows][:, None] + ky
        r2 = (gx * gx + self.eps2) + gy * gy
        optics = (torch.ones_like(r2) if self.cutoff is None
                  else diffraction_otf(torch.sqrt(r2).mul_(self.h / self.cutoff)))
        lens = (transfer.lens_transfer(r2, self.lens_sigma * self.h, transfer.LENS_SPREAD)
                if self.lens_sigma > 0 else None)
        prior = r2.log_().mul_(-0.5 * beta).exp_().mul_(s2)  # pow's a quarter of the time
        k_mag = optics * (box(gx, self.h * self.aperture) * box(gy, self.h * self.aperture))
        k2 = k_mag * k_mag
        if lens is not None:
            k_mag *= lens[0]
            k2 *= lens[1]
        target = self.aperture if self.target is None else self.target
        optics *= box(gx, target) * box(gy, target)
        return prior, k_mag, optics, k2

    def phase(self) -> tuple[Tensor, Tensor]:
        """The lattice's phase factor of the unaliased term, exp(-2 pi i f . offset), as its
        factors along x (cols,) and y (rows,)."""
        px = torch.exp(-2j * math.pi * self.fx.double() * self.offset[0]).to(self.fx.dtype.to_complex())
        py = torch.exp(-2j * math.pi * self.fy.double() * self.offset[1]).to(self.fx.dtype.to_complex())
        return px, py


def _mmse_filter(measured: Tensor, model: _Model, aliased: tuple[Tensor, list], s2: float, beta: float,
                 noise2: float, strength: float, mirrored: Tensor | None = None) -> list[Tensor]:
    """The MMSE filter of :func:`wiener_deblur` at the frequencies of (rows of) the half spectrum.

    Parameters
    ----------
    measured : Tensor, shape (rows, cols // 2 + 1), real
        The image's power at those frequencies: abs(Z)^2 / (number of pixels) of the periodic
        part's rfft2 Z (the splat's transfer divided out), averaged over 3 x 3 frequencies.
    model : _Model
        The image model on those frequencies, ``fy`` (rows,), ``fx`` (cols // 2 + 1,) (its
        dtype is the filter's).
    aliased : (Tensor, list of (Tensor, Tensor))
        The aliases' sums at those rows (:meth:`_AliasSums.at`): sum_k P abs(K)^2, then
        sum_k P abs(K) W exp(-2 pi i k . offset) as (real, imaginary), at the rows and (with
        ``mirrored``) at the mirrored rows. They are overwritten.
    s2, beta : float
        The scene prior s^2 / abs(f)^beta (:func:`fit_spectrum`).
    noise2 : float
        Noise power per node (intensity^2).
    strength : float
        Multiplies the noise power.
    mirrored : Tensor, shape of ``measured``, optional
        The power at the rows of frequencies -fy (same order): their filter too.

    Returns
    -------
    list of Tensor, shape of ``measured``, complex
        The filter at the rows, then (with ``mirrored``) at the mirrored rows.
    """
    # Alias k's lattice phase is the unaliased one times the constant exp(-2 pi i k . offset),
    # so the numerator is phase(f) sum_k c_k P W |K|: two real sums, the aliases' in ``aliased``
    # (:class:`_AliasSums`). The unaliased term comes last, since its prior depends on the
    # others' sum.
    sides = [measured] if mirrored is None else [measured, mirrored]
    power, cross = aliased
    # Where the image holds more power than the power law explains (a grating, a texture), the
    # prior of the unaliased frequency is raised to what is measured (power smoothed over 3 x 3
    # frequencies, less the noise and the aliases' share), as long as the aperture passes it.
    every_row, every_col = torch.arange(measured.shape[0]), torch.arange(measured.shape[1])
    prior0, k0, w0, seen = model.terms(0, 0, every_row, every_col, s2, beta)
    passed = seen > 0.05
    px, py = model.phase()
    filters = []
    for side, (cross_re, cross_im), py_side in zip(sides, cross, (py, py.conj())):
        empirical = side.sub(noise2).sub_(power).clamp_min_(0).div_(seen.clamp_min(1e-12))
        prior = torch.where(passed, torch.maximum(prior0, empirical), prior0)
        del empirical
        total = power + prior * seen
        prior *= k0
        cross_re += prior.mul_(w0)
        del prior
        total += strength * noise2
        cross_re /= total
        cross_im /= total
        del total
        filt = torch.complex(cross_re, cross_im)
        del cross_re, cross_im
        filt *= py_side[:, None]
        filt *= px[None, :]
        filters.append(filt)
    return filters


def _add_at(sums: Tensor, rows: Tensor, cols: Tensor, values: Tensor, alpha: float = 1.0) -> None:
    """``sums[rows][:, cols] += alpha * values`` in place, for increasing ``rows`` and ``cols``
    (the columns contiguous, as fx increases): as a slice's add_ where the rows are contiguous
    too (a block's fy are monotone), which runs on every thread where index_add_ runs on one."""
    c0, c1 = int(cols[0]), int(cols[-1]) + 1
    r0, r1 = int(rows[0]), int(rows[-1]) + 1
    if r1 - r0 == len(rows):
        sums[r0:r1, c0:c1].add_(values, alpha=alpha)
    else:
        sums[:, c0:c1].index_add_(0, rows, values, alpha=alpha)


def _ring_of(fx: Tensor, fy: Tensor, edges: Tensor) -> Tensor:
    """The ring of frequencies (fx, fy) (broadcast), in cycles per px: i where abs(f) lies in
    (edges[i], edges[i + 1]]; -1 and len(edges) - 1 outside."""
    return torch.bucketize(torch.sqrt(fx * fx + fy * fy), edges) - 1


def _ring_sums(power: Tensor, fx: Tensor, fy: Tensor, edges: Tensor) -> tuple[Tensor, Tensor]:
    """Frequencies counted (int64) and their ``power`` summed (float64) in each ring of
    :func:`_ring_of` (``len(edges) - 1`` of them), a block of rows at a time (float64
    temporaries of a few MB). ``power`` (rows, cols // 2 + 1) is on the half spectrum's
    frequencies ``fx`` (1, cols // 2 + 1) and ``fy`` (rows, 1) (``fftfreq``'s order): rows i and
    rows - i (fy and -fy) lie in the same rings, so the rings are found for rows 0 .. rows // 2
    only, the mirrored rows' power added to theirs.

    Along a row, abs(f) grows with fx, so each ring is a run of columns: the row's columns with
    abs(f) <= edges[j] are the first ``searchsorted(fx^2, edges[j]^2 - fy^2)``, and a ring's sum
    is the difference of the row's running sums at its two ends (no ring index per frequency: a
    full frame at h = 4 in 0.026 s against bincount's 0.083 s, at h = 7 0.062 s against 0.23 s)."""
    rows = power.shape[0]
    fx2, edges2 = fx[0] * fx[0], edges * edges  # fx: rfftfreq's, ascending
    count = torch.zeros(len(edges) - 1, dtype=torch.int64)
    total = torch.zeros(len(edges) - 1, dtype=torch.float64)
    for block in _row_blocks(rows // 2 + 1):
        row = torch.arange(block.start, block.stop)
        mirrored = (row > 0) & (2 * row != rows)  # rows with a mirror of their own
        weight = power[block].to(torch.float64, copy=True)  # power itself stays as it is
        weight[mirrored] += power[rows - row[mirrored]].double()
        running = torch.zeros((len(row), weight.shape[1] + 1), dtype=torch.float64)
        torch.cumsum(weight, dim=1, out=running[:, 1:])
        ends = torch.searchsorted(fx2, edges2 - fy[block] * fy[block], right=True)  # (rows, len(edges))
        total += running.gather(1, ends).diff(dim=1).sum(0)
        count += (ends.diff(dim=1) * (1 + mirrored.long())[:, None]).sum(0)
    return count, total


def fit_spectrum(power: Tensor, fx: Tensor, fy: Tensor, kernel, shifts, noise2: float,
                 highest: float | None = None) -> tuple[float, float]:
    """Fit the scene prior s^2 / abs(f)^beta to an image's power spectrum, the noise being known.

    ``power`` (rows, cols // 2 + 1) is abs(Z(f))^2 / n of the (splat-corrected) image's rfft2 Z
    over its n pixels. The model of its expectation is s^2 S_beta(f) + sigma^2
    with S_beta(f) = sum_k abs(K(f+k))^2 / abs(f+k)^beta over the aliases k in ``shifts`` ((kx, ky)
    pairs); ``kernel(kx, ky, (rows, cols))`` gives (abs(K), W, phase, abs(f+k)^2) of alias k at
    those entries of the spectrum.
    In log-spaced frequency rings where the image stands clear of the noise (twice its power)
    and the kernel passes the scene (abs(K)^2 above 1e-4 of its largest ring value),
    log(power - sigma^2) - log S_beta is fitted by a constant (log s^2); the beta of a grid over
    [1.5, 4] (steps of 0.25) with the smallest scatter is kept. With ``highest`` (cycles per
    px), only the rings that end at or below it are fitted.

    A burst's lattice is fitted below one cycle per LR px (``highest = 1 / h``,
    :func:`~hbis_torch.reconstruct.classical.sr.classical_sr`): there the pixel's box (its first
    zero) lets the scene through only faintly, and the lattice holds besides it what the
    interpolation of its empty nodes leaves: where the samples leave whole sub-pixel phases
    empty (a burst of pure shifts that cluster, a region the robustness leaves to the reference
    alone), the filled nodes' errors repeat with the LR lattice's period, at 1 / h and its
    multiples. Fitted, that power flattened the slope, and the filter then sharpened the errors
    as scene detail over the whole image. On the training simulator's 640 x 480 bursts the cut
    raised those with a moving object at S = 2 and left those of shifts and turns (S = 2 to 4),
    which fitted no ring above 1 / h, unchanged (docs/real-bursts.md).

    Returns
    -------
    s2, beta : float
    """
    rows, half = power.shape
    cols = 2 * (half - 1) if half > 1 else 1
    edges = torch.logspace(math.log10(1.5 / max(rows, cols)), math.log10(0.71), 25, dtype=fx.dtype)

    count, total = _ring_sums(power, fx, fy, edges)
    m = total / count.clamp_min(1)
    # The model's shape is smooth in frequency: evaluate it on a subsample (about 16k points).
    stride = max(1, rows * half // 16384)
    pick = torch.arange(0, rows * half, stride)
    ring = _ring_of(fx[0, pick % half], fy[pick // half, 0], edges)  # -1 and 24: outside the rings
    inside = (ring >= 0) & (ring < 24)
    pick, sub_ring = pick[inside], ring[inside]
    sub_count = torch.bincount(sub_ring, minlength=24)
    at = [kernel(kx, ky, (pick // half, pick % half)) for kx, ky in shifts]
    k2 = torch.stack([t[0] * t[0] for t in at])  # (aliases, n)
    log_r2 = torch.stack([torch.log(t[3]) for t in at])
    # Rings the kernel all but closes (beyond the lens's cutoff: only noise and rounding there)
    # say nothing of the scene: fitted, their near-zero model would blow the level up.
    passed = torch.bincount(sub_ring, k2.sum(0), minlength=24) / sub_count.clamp_min(1)
    clear = (count >= 8) & (sub_count >= 1) & (m > 2 * noise2) & (passed > 1e-4 * float(passed.max()))
    if highest is not None:
        clear &= edges[1:] <= highest
    betas = torch.arange(1.5, 4.01, 0.25).tolist()
    if int(clear.sum()) < 3:
        # Too few frequencies stand above the noise to fit a slope: a 1/f^2 law through those
        # that do, or, with none, a scene far below the noise at every frequency.
        betas = [2.0]
        if not bool(clear.any()):
            shape = (k2 * torch.exp(-log_r2)).sum(0)
            return 1e-3 * noise2 / max(float(shape.max()), 1e-300), 2.0
    target = (m[clear] - noise2).log()
    # S_beta on the subsample for every beta of the evenly spaced grid: |f+k|^-beta by repeated
    # multiplication with |f+k|^-step (one exp for all the betas, not one per beta).
    power = torch.exp(-0.5 * betas[0] * log_r2)
    step = torch.exp(-0.5 * (betas[1] - betas[0]) * log_r2) if len(betas) > 1 else None
    best = None
    for j, beta in enumerate(betas):
        if j:
            power = power * step
        shape = (k2 * power).sum(0)
        S = (torch.bincount(sub_ring, shape, minlength=24) / sub_count.clamp_min(1))[clear]
        gap = target - S.clamp_min(1e-300).log()
        level, scatter = float(gap.mean()), float(((gap - gap.mean()) ** 2).mean())
        if best is None or scatter < best[0]:
            best = (scatter, math.exp(level), beta)
    return best[1], best[2]
