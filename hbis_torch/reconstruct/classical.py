"""Classical multi-frame super-resolution: scattered samples -> h-times grid -> deblur.

Every sample of every frame is placed at its true position on the reference frame's grid (from
the optics, from the registration, or both), then:

1. **Interpolation (normalized convolution, O(N)).** Each sample is splatted with a small
   Gaussian (sigma ``kernel_sigma`` HR px, 3 x 3 footprint) onto an h-times grid; the image is
   the weighted sum over the sum of weights (Knutsson & Westin 1993). The splat grid is shifted
   by the samples' common sub-pixel offset (half an HR pixel for even h, where the scan puts
   the samples between the output pixels' centres), so that interpolation does not average
   neighbours; the deblurring removes that shift exactly, in the Fourier domain. Holes
   (missing frames, the border) are filled from the same sums blurred wider.
2. **Deblurring (Wiener filter with aliasing).** The interpolated image is the scene seen
   through the optics (diffraction-limited OTF of the f-number), the LR pixel's aperture (a box
   of h HR pixels, times sqrt(fill factor)), sampled on the HR lattice. What is wanted is what an
   ideal sensor of pitch p/h sees (the project's ground truth): the same optics and an aperture
   of one HR pixel. The output is the minimum-mean-square-error linear estimate of that image
   (:func:`wiener_deblur`), which also accounts for the scene energy that aliases onto the
   lattice. **Prior:** the scene is Gaussian with a power-law spectrum s^2 / |f|^beta (natural
   images: beta about 2, i.e. independent Gaussian gradients), s^2 and beta fitted to the data
   within the sensor's own band; the noise is white, its level measured on the HR lattice
   (:func:`lattice_noise`). The FFT's periodic borders are handled by Moisan's periodic + smooth
   decomposition.

Coordinates: LR pixel (u, v) is the centre of column u, row v of the reference frame's ROI;
HR pixel (U, V) is centred at LR ((U + 0.5)/h - 0.5, (V + 0.5)/h - 0.5) (DESIGN contract).
Computation is in float64; the result is rounded to float32.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

from hbis_torch.checks import as_float64_tensor, check_h
from hbis_torch.errors import HbisInputError

# The deblurring never trusts the data more than this noise level (intensity units, [0, 1]):
# below it the model's own errors (the periodic-border split, the prior, positions known to
# ~1e-3 px) dominate, and a sharper filter would amplify them near the aperture's zeros.
NOISE_FLOOR = 2e-3

__all__ = [
    "classical_sr",
    "optical_sample_positions",
    "reconstruct",
    "METHODS",
    "REGISTRATIONS",
    "diffraction_otf",
    "optics_cutoff",
]


# --------------------------------------------------------------------------- optics


def optics_cutoff(system) -> float:
    """Incoherent diffraction cutoff of the lens, in cycles per LR (sensor) pixel: p / (lambda F)."""
    cam = system.camera
    return cam.pixel_pitch_um / (cam.wavelength_nm * 1e-3 * cam.f_number)


def diffraction_otf(rho: Tensor) -> Tensor:
    """OTF of an aberration-free circular pupil at normalised frequency rho = f / f_cutoff.

    (2/pi) (acos(rho) - rho sqrt(1 - rho^2)) for rho < 1, else 0.
    """
    r = rho.clamp(0, 1)
    return (2 / math.pi) * (torch.acos(r) - r * torch.sqrt(1 - r * r))


def _box(f: Tensor, width: float) -> Tensor:
    """Transfer function of a box of ``width`` px at frequency f (cycles/px): sinc(width f)."""
    return torch.sinc(width * f)


# --------------------------------------------------------------------------- checks


# --------------------------------------------------------------------------- interpolation


def _common_offset(coords: Tensor) -> float:
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
    rows, cols = shape
    # A one-node frame around the grid keeps what samples just outside give to the border nodes.
    near = (xi >= -1) & (xi <= cols) & (yi >= -1) & (yi <= rows)
    idx = ((yi + 1) * (cols + 2) + xi + 1).clamp(0, (rows + 2) * (cols + 2) - 1).long()
    w = weights * near
    sums = torch.zeros(2, (rows + 2) * (cols + 2), dtype=values.dtype)
    sums[0].index_add_(0, idx, w * values)
    sums[1].index_add_(0, idx, w)
    sums = sums.view(2, rows + 2, cols + 2)
    a = math.exp(-1 / (2 * sigma * sigma))
    sums = a * (sums[:, :, :-2] + sums[:, :, 2:]) + sums[:, :, 1:-1]
    sums = a * (sums[:, :-2] + sums[:, 2:]) + sums[:, 1:-1]
    return sums[0], sums[1]


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
    pilot = _fill_holes(*splat(values, xn, yn, shape, sigma, weights))
    gy, gx = torch.gradient(pilot)
    rows, cols = shape
    grid = torch.stack((2 * x / max(cols - 1, 1) - 1, 2 * y / max(rows - 1, 1) - 1), -1)[None, None]
    slopes = torch.nn.functional.grid_sample(torch.stack((gx, gy))[None], grid.to(pilot.dtype),
                                             mode="bilinear", padding_mode="border", align_corners=True)
    sx, sy = slopes[0, 0, 0], slopes[0, 1, 0]
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


def _fill_holes(num: Tensor, den: Tensor) -> Tensor:
    """num / den, with nodes of little weight taken from the sums blurred wider and wider."""
    typical = float(den[den > 0].median()) if bool((den > 0).any()) else 0.0
    if typical == 0.0:
        raise HbisInputError("no sample falls on the output grid")
    image = num / den.clamp_min(1e-12)
    need = den < 0.25 * typical
    sigma = 1.0
    while bool(need.any()) and sigma <= 64:
        n2, d2 = _gaussian_blur(num, sigma), _gaussian_blur(den, sigma)
        ok = need & (d2 >= 0.05 * typical)
        image = torch.where(ok, n2 / d2.clamp_min(1e-12), image)
        need = need & ~ok
        sigma *= 2
    if bool(need.any()):
        image = torch.where(need, num.sum() / den.sum(), image)
    return image


# --------------------------------------------------------------------------- deblurring


def splat_transfer(f: Tensor, sigma: float) -> Tensor:
    """Transfer function, along one axis, of normalized convolution with the 3-tap Gaussian
    splat on a lattice with one sample per node: (1 + 2a cos 2 pi f) / (1 + 2a), a = e^(-1/2s^2).
    """
    a = math.exp(-1 / (2 * sigma * sigma))
    return (1 + 2 * a * torch.cos(2 * math.pi * f)) / (1 + 2 * a)


def wiener_deblur(
    image: Tensor,
    h: int,
    offset: tuple[float, float],
    kernel_sigma: float,
    noise: float,
    aperture: float = 1.0,
    cutoff: float | None = None,
    strength: float = 1.0,
    aliases: int = 1,
) -> Tensor:
    """Wiener (MMSE linear) estimate of the p/h sensor's image from the interpolated one.

    Model, at frequency f in cycles per HR px (the splat's own transfer is divided out first):
    the image is the scene S seen through the kernel K and sampled on the HR lattice shifted
    by ``offset``; the wanted image is S seen through W and sampled on the output lattice::

        K(f) = optics(f) box(h a, f) exp(2 pi i f . offset),   W(f) = optics(f) box(a, f)
        image(f) = sum_k S(f + k) K(f + k) + N(f),                  N white, std ``noise``

    (a = ``aperture``), where k runs over the integer aliases (|k| <= ``aliases`` per axis). **Prior:** the scene's
    power spectrum is s^2 / |f|^2 (independent Gaussian gradients, the 1/f^2 law of natural
    images). The MMSE filter is then, per frequency,

        sum_k P(f+k) W(f+k) conj(K(f+k)) / (sum_k P(f+k) |K(f+k)|^2 + noise^2),

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

    Returns
    -------
    Tensor, shape (rows, cols)
    """
    rows, cols = image.shape
    # The FFT sees the image as periodic; its borders' jumps would ring through the whole image
    # at the frequencies the pixel aperture nearly erases. Deblur only the periodic part and
    # add the smooth rest back (Moisan 2011).
    p, smooth = periodic_smooth(image)
    fy = torch.fft.fftfreq(p.shape[0], dtype=image.dtype)[:, None]
    fx = torch.fft.rfftfreq(p.shape[1], dtype=image.dtype)[None, :]
    spectrum = torch.fft.rfft2(p) / (splat_transfer(fx, kernel_sigma) * splat_transfer(fy, kernel_sigma))

    if h == 1:  # nothing to deblur: only the splat's smoothing is undone
        return torch.fft.irfft2(spectrum, s=p.shape) + shift_image(smooth, offset)
    eps2 = (0.5 / max(p.shape)) ** 2  # keeps the prior finite at f = 0

    def kernel(kx: int, ky: int, pick: tuple[Tensor, Tensor] | None = None):
        """|K|, W, the lattice phase and |f + k|^2 of alias (kx, ky): on the whole spectrum's
        grid, or at the (row, column) pairs ``pick`` (then without the phase). The separable
        factors are computed along each axis once."""
        gx, gy = fx + kx, fy + ky  # (1, cols), (rows, 1)
        box_x, box_y = _box(gx, h * aperture), _box(gy, h * aperture)
        pix_x, pix_y = _box(gx, aperture), _box(gy, aperture)
        if pick is not None:
            rows, cols = pick
            gx, box_x, pix_x = (t[0].index_select(0, cols) for t in (gx, box_x, pix_x))
            gy, box_y, pix_y = (t[:, 0].index_select(0, rows) for t in (gy, box_y, pix_y))
        r2 = gx * gx + gy * gy + eps2
        optics = torch.ones_like(r2) if cutoff is None else diffraction_otf(torch.sqrt(r2) * h / cutoff)
        k_mag, w = optics * box_x * box_y, optics * pix_x * pix_y
        if pick is not None:
            return k_mag, w, None, r2
        # The lattice's phase factor is separable too: two 1-D exponentials, one product.
        phase = torch.exp(-2j * math.pi * gx * offset[0]) * torch.exp(-2j * math.pi * gy * offset[1])
        return k_mag, w, phase, r2

    shifts = [(kx, ky) for ky in range(-aliases, aliases + 1) for kx in range(-aliases, aliases + 1)]
    noise2 = max(noise, NOISE_FLOOR) ** 2
    s2, beta = fit_spectrum(spectrum, fx, fy, kernel, shifts, noise2)
    # The aliases one at a time (the whole-image arrays of all nine would not fit for a full
    # frame at h = 4); the unaliased term last, since its prior depends on the others' sum.
    cross = torch.zeros_like(spectrum)
    power = torch.zeros(spectrum.shape, dtype=image.dtype)
    for kx, ky in shifts:
        if (kx, ky) != (0, 0):
            k_mag, w, phase, r2 = kernel(kx, ky)
            weighted = s2 * r2 ** (-0.5 * beta) * k_mag
            cross += weighted * w * phase
            power += weighted * k_mag
    # Where the image holds more power than the power law explains (a grating, a texture), the
    # prior of the unaliased frequency is raised to what is measured (power smoothed over 3 x 3
    # frequencies, less the noise and the aliases' share), as long as the aperture passes it.
    k0, w0, phase0, r20 = kernel(0, 0)
    prior = s2 * r20 ** (-0.5 * beta)
    measured = torch.nn.functional.avg_pool2d(
        (spectrum.abs() ** 2 / (p.shape[0] * p.shape[1]))[None, None], 3, 1, 1, count_include_pad=False)[0, 0]
    seen = (k0 * k0).expand_as(measured)
    empirical = (measured - noise2 - power).clamp_min(0) / seen.clamp_min(1e-12)
    prior = torch.where(seen > 0.05, torch.maximum(prior, empirical), prior)
    cross += prior * w0 * k0 * phase0
    power += prior * k0 * k0
    filt = cross / (power + strength * noise2)
    return torch.fft.irfft2(spectrum * filt, s=p.shape) + shift_image(smooth, offset)


def shift_image(image: Tensor, offset: tuple[float, float]) -> Tensor:
    """A smooth image whose node j sits at coordinate j + offset, resampled at the integer
    coordinates (that is, at nodes j - offset): bicubic, borders mirrored. Used for the smooth
    part of the periodic + smooth split, which varies slowly, so a cubic needs no prefilter."""
    if offset == (0.0, 0.0):
        return image
    rows, cols = image.shape
    v = (torch.arange(rows, dtype=image.dtype) - offset[1]) * (2 / max(rows - 1, 1)) - 1
    u = (torch.arange(cols, dtype=image.dtype) - offset[0]) * (2 / max(cols - 1, 1)) - 1
    grid = torch.stack(torch.meshgrid(v, u, indexing="ij")[::-1], -1)[None]
    return torch.nn.functional.grid_sample(image[None, None], grid, mode="bicubic",
                                           padding_mode="reflection", align_corners=True)[0, 0]


def fit_spectrum(spectrum: Tensor, fx: Tensor, fy: Tensor, kernel, shifts, noise2: float) -> tuple[float, float]:
    """Fit the scene prior s^2 / |f|^beta to an image's power spectrum, the noise being known.

    The model of the (splat-corrected) image's power is E|Z(f)|^2 / n = s^2 S_beta(f) + sigma^2
    with S_beta(f) = sum_k |K(f+k)|^2 / |f+k|^beta over the aliases k in ``shifts`` ((kx, ky)
    pairs); ``kernel(kx, ky, (rows, cols))`` gives (|K|, W, phase, |f+k|^2) of alias k at
    those entries of the spectrum.
    In log-spaced frequency rings where the image stands clear of the noise (twice its power),
    log(power - sigma^2) - log S_beta is fitted by a constant (log s^2); the beta of a grid over
    [1.5, 4] (steps of 0.25) with the smallest scatter is kept.

    Returns
    -------
    s2, beta : float
    """
    rows, half = spectrum.shape
    cols = 2 * (half - 1) if half > 1 else 1
    measured = (spectrum.abs() ** 2 / (rows * cols)).reshape(-1)
    rad = torch.sqrt(fx * fx + fy * fy).expand(spectrum.shape).reshape(-1)
    edges = torch.logspace(math.log10(1.5 / max(rows, cols)), math.log10(0.71), 25, dtype=rad.dtype)
    ring = torch.bucketize(rad, edges) - 1  # -1 and 24: outside the rings
    inside = (ring >= 0) & (ring < 24)
    count = torch.bincount(ring[inside], minlength=24)
    m = torch.bincount(ring[inside], measured[inside], minlength=24) / count.clamp_min(1)
    # The model's shape is smooth in frequency: evaluate it on a subsample (about 16k points).
    stride = max(1, rad.numel() // 16384)
    pick = torch.arange(0, rad.numel(), stride)
    pick = pick[inside[pick]]
    sub_ring = ring[pick]
    sub_count = torch.bincount(sub_ring, minlength=24)
    at = [kernel(kx, ky, (pick // half, pick % half)) for kx, ky in shifts]
    k2 = torch.stack([t[0] * t[0] for t in at])  # (aliases, n)
    log_r2 = torch.stack([torch.log(t[3]) for t in at])
    clear = (count >= 8) & (sub_count >= 1) & (m > 2 * noise2)
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


def periodic_smooth(image: Tensor) -> tuple[Tensor, Tensor]:
    """Periodic plus smooth decomposition (Moisan, J. Math. Imaging Vis. 39, 2011).

    image = p + s with p periodic (no jump between opposite borders) and s smooth (its
    Laplacian vanishes inside; it carries the border jumps). Shapes (rows, cols).
    """
    M, N = image.shape
    v = torch.zeros_like(image)
    v[0, :] += image[-1, :] - image[0, :]
    v[-1, :] += image[0, :] - image[-1, :]
    v[:, 0] += image[:, -1] - image[:, 0]
    v[:, -1] += image[:, 0] - image[:, -1]
    q = torch.arange(M, dtype=image.dtype)[:, None]
    r = torch.arange(N, dtype=image.dtype)[None, :]
    den = 2 * torch.cos(2 * math.pi * q / M) + 2 * torch.cos(2 * math.pi * r / N) - 4
    den[0, 0] = 1.0
    S = torch.fft.fft2(v) / den
    S[0, 0] = 0
    s = torch.fft.ifft2(S).real
    return image - s, s


# --------------------------------------------------------------------------- public API


def classical_sr(
    frames,
    positions,
    h: int,
    deblur: bool = True,
    *,
    weights=None,
    kernel_sigma: float = 0.45,
    noise: float | None = None,
    fill_factor: float = 1.0,
    cutoff: float | None = None,
    strength: float = 2.0,
) -> Tensor:
    """Super-resolve frames whose samples' positions are known.

    Parameters
    ----------
    frames : Tensor or array, shape (F, H, W)
        Intensities in [0, 1].
    positions : Tensor or array, shape (F, H, W, 2)
        Position (u, v) of every sample in the reference frame's LR pixel coordinates
        (ROI-local), for example from :func:`optical_sample_positions`.
    h : int
        Resolution improvement factor: the output is (h*H, h*W).
    deblur : bool
        Apply the Wiener deblurring (False: the normalized-convolution interpolation alone,
        resampled onto the output grid).
    weights : Tensor, shape (F,) or (F, H, W), optional
        Per-frame or per-sample weights in [0, 1] (0 leaves a frame or sample out).
    kernel_sigma : float
        Splat Gaussian in HR px.
    noise : float, optional
        Noise standard deviation of the frames (default: estimated from them).
    fill_factor : float
        Light-sensitive fraction of a pixel's area, in (0, 1] (a centred square of side
        sqrt(fill_factor) times the pitch, as in the simulator's SensorModel).
    cutoff : float, optional
        Optical cutoff in cycles per LR pixel (:func:`optics_cutoff`); None ignores the optics.
    strength : float
        Scales the noise power in the Wiener filter. The default 2 was chosen on simulated
        stacks (8 scenes x h = 3, 4, 5, 64 px, seed 1): it beat 1, 1.5 and 3 in mean PSNR (by
        0.4 dB over 1), the estimated noise being the median level while shot noise grows with
        the signal, and the power-law prior overstating some scenes' fine detail.

    Returns
    -------
    Tensor, shape (h*H, h*W), float32 in [0, 1]
        Computed in float64 and rounded at the end.
    """
    h = check_h(h)
    frames = as_float64_tensor(frames, "frames")
    positions = as_float64_tensor(positions, "positions")
    if frames.ndim != 3 or min(frames.shape) < 1:
        raise HbisInputError(f"frames must have shape (F, H, W), got {tuple(frames.shape)}")
    F, H, W = frames.shape
    if tuple(positions.shape) != (F, H, W, 2):
        raise HbisInputError(
            f"positions must have shape {(F, H, W, 2)} to match the frames, got {tuple(positions.shape)}"
        )
    if not 0 < fill_factor <= 1:
        raise HbisInputError(f"fill_factor must lie in (0, 1], got {fill_factor!r}")
    if not 0.2 <= kernel_sigma <= 0.6:
        raise HbisInputError(f"kernel_sigma must lie in [0.2, 0.6] HR px, got {kernel_sigma!r}")
    if cutoff is not None and not (math.isfinite(cutoff) and cutoff > 0):
        raise HbisInputError(f"cutoff must be a positive number (cycles per pixel), got {cutoff!r}")
    if not (math.isfinite(strength) and strength > 0):
        raise HbisInputError(f"strength must be a positive number, got {strength!r}")
    if weights is not None:
        weights = as_float64_tensor(weights, "weights")
        if weights.shape == (F,):
            weights = weights[:, None, None].expand(F, H, W)
        if tuple(weights.shape) != (F, H, W) or bool((weights < 0).any()):
            raise HbisInputError(f"weights must be non-negative, shape ({F},) or {(F, H, W)}")
        if not bool((weights > 0).any()):
            raise HbisInputError("every sample has weight 0: nothing to reconstruct")
    if noise is not None and not (math.isfinite(noise) and noise >= 0):
        raise HbisInputError(f"noise must be a number >= 0, got {noise!r}")

    image, den, offset = lattice_image(frames, positions, h, kernel_sigma, weights, on_lattice=deblur)
    if deblur:
        # Samples that meet at a node (1 for an h x h scan): their noise averages down.
        samples_per_node = float(den[den > 0].median()) / max(_peak_weight(kernel_sigma), 1e-12)
        if noise is None:
            typical = float(den[den > 0].median())
            node_noise = lattice_noise(image, kernel_sigma, den > 0.5 * typical)
        else:
            node_noise = noise / math.sqrt(max(samples_per_node, 1.0))
        image = wiener_deblur(image, h, offset, kernel_sigma, node_noise, math.sqrt(fill_factor),
                              cutoff, strength)
    return image.clamp(0, 1).to(torch.float32)


def lattice_image(frames: Tensor, positions: Tensor, h: int, kernel_sigma: float,
                  weights: Tensor | None = None, on_lattice: bool = True):
    """Interpolate scattered samples onto an h-times grid (normalized convolution).

    Parameters
    ----------
    frames : Tensor, shape (F, H, W), float64
    positions : Tensor, shape (F, H, W, 2), float64
        ROI-local reference LR coordinates of the samples.
    h : int
    kernel_sigma : float
    weights : Tensor, shape (F, H, W), optional
    on_lattice : bool
        Put the grid's nodes where the scan lattice puts the samples (the output grid shifted
        by the samples' common sub-pixel ``offset``) and move every sample onto its node
        (:func:`snap_to_lattice`), as the deblurring needs; False interpolates onto the output
        grid itself.

    Returns
    -------
    image, den : Tensor, shape (h*H, h*W)
        The interpolated image and the splat weights' sum at each node.
    offset : (float, float)
        Where the nodes sit relative to the output pixels, HR px.
    """
    F, H, W = frames.shape
    X = (positions[..., 0] + 0.5) * h - 0.5
    Y = (positions[..., 1] + 0.5) * h - 0.5
    keep = torch.ones(F, H, W, dtype=torch.bool) if weights is None else weights > 0
    offset = (_common_offset(X[keep]), _common_offset(Y[keep])) if on_lattice else (0.0, 0.0)
    w = None if weights is None else weights.reshape(-1)
    values, x, y = frames.reshape(-1), (X - offset[0]).reshape(-1), (Y - offset[1]).reshape(-1)
    shape = (h * H, h * W)
    if on_lattice:
        values, x, y = snap_to_lattice(values, x, y, shape, kernel_sigma, w)
    num, den = splat(values, x, y, shape, kernel_sigma, w)
    return _fill_holes(num, den), den, offset


def lattice_noise(image: Tensor, kernel_sigma: float, valid: Tensor | None = None) -> float:
    """Noise level of the samples from the interpolated image on their lattice.

    On the h-times lattice neighbouring nodes hold samples of different frames a fraction of a
    pixel apart, so the scene is far smoother there than in any single (aliased) frame, and
    Immerkaer's operator [[1,-2,1],[-2,4,-2],[1,-2,1]] (median form) sees little but noise. The
    splat's 3-tap smoothing changes the operator's noise gain from 6 to the value computed here.

    Parameters
    ----------
    image : Tensor, shape (rows, cols)
        Normalized-convolution image with one sample per node.
    kernel_sigma : float
        The splat Gaussian (HR px).
    valid : Tensor of bool, shape (rows, cols), optional
        Nodes to use (those that received samples).
    """
    a = math.exp(-1 / (2 * kernel_sigma ** 2))
    taps = torch.tensor([1.0, -2.0, 1.0], dtype=image.dtype)
    smoothed = torch.nn.functional.conv1d(taps.view(1, 1, 3), torch.tensor([[[a, 1.0, a]]], dtype=image.dtype), padding=2)
    gain_1d = float(smoothed.norm()) / (1 + 2 * a)
    # The operator is [1, -2, 1] along rows times the same along columns: two second differences.
    d = image[:, :-2] - 2 * image[:, 1:-1] + image[:, 2:]
    out = d[:-2] - 2 * d[1:-1] + d[2:]
    if valid is not None:
        inner = valid[1:-1, 1:-1]
        for dy in (-1, 0, 1):  # all nine nodes of the operator must have samples
            for dx in (-1, 0, 1):
                inner = inner & valid[1 + dy:valid.shape[0] - 1 + dy, 1 + dx:valid.shape[1] - 1 + dx]
        out = out[inner]
    if out.numel() < 16:  # too few complete neighbourhoods: use every node
        out = d[:-2] - 2 * d[1:-1] + d[2:]
    return 1.4826 * float(out.abs().median()) / gain_1d ** 2


def _peak_weight(sigma: float) -> float:
    """Splat weight a node receives from a sample sitting on it plus its lattice neighbours."""
    d = torch.tensor([-1.0, 0.0, 1.0])
    g = torch.exp(-(d[:, None] ** 2 + d[None, :] ** 2) / (2 * sigma * sigma))
    return float(g.sum())


def optical_sample_positions(stack) -> Tensor:
    """Where every sample of every frame lies in the reference frame, from the exact tracer.

    Sample (u, v) of frame k sees the object point ``landing_map(system, phi_k, roi)[v, u]``;
    the reference frame would image that point at ``sensor_position(system, point, phi_ref)``.

    Parameters
    ----------
    stack : hbis_torch.stack_io.Stack

    Returns
    -------
    Tensor, shape (F, H, W, 2), float64
        (u, v) in the reference frame's ROI-local LR pixel coordinates.
    """
    from hbis_torch.optics import landing_map, sensor_position

    system = stack.system
    roi = stack.roi
    phases = torch.as_tensor(stack.phases_deg, dtype=torch.float64)
    ref = stack.reference_index
    origin = torch.tensor(roi[:2], dtype=torch.float64)
    out = []
    for phi1, phi2 in phases:  # one frame at a time keeps the memory to one landing map
        points = landing_map(system, phi1, phi2, roi)
        out.append(sensor_position(system, points, phases[ref, 0], phases[ref, 1]) - origin)
    return torch.stack(out)


def _stack_frames(stack) -> Tensor:
    frames = stack.to_float()
    if frames.ndim != 3:
        raise HbisInputError(f"the stack's frames must be (F, H, W), got {tuple(frames.shape)}")
    return frames


REGISTRATIONS = ("optics", "data", "auto")


def stack_fill_factor(stack) -> float:
    """The sensor's fill factor recorded in a stack's JSON (``sensor.fill_factor``, or the
    simulator's ``simulation.sensor.fill_factor``), else 1."""
    for block in (stack.meta.get("sensor"), (stack.meta.get("simulation") or {}).get("sensor")):
        if isinstance(block, dict) and "fill_factor" in block:
            value = block["fill_factor"]
            if isinstance(value, (int, float)) and not isinstance(value, bool) and 0 < value <= 1:
                return float(value)
            raise HbisInputError(f"the stack's fill_factor must be a number in (0, 1], got {value!r}")
    return 1.0


def reconstruct_classical(stack, registration: str = "auto", *, deblur: bool = True,
                          messages: list | None = None, fill_factor: float | None = None,
                          **kw) -> np.ndarray:
    """Classical super-resolution of a stack (see :func:`reconstruct`)."""
    from hbis_torch.registration import apply_homography, homographies_from_positions, register_stack

    if registration not in REGISTRATIONS:
        raise HbisInputError(f"registration must be one of {REGISTRATIONS}, got {registration!r}")
    frames = _stack_frames(stack)
    F, H, W = frames.shape
    positions = optical_sample_positions(stack)
    weights = None
    if registration != "optics" and F > 1:
        predicted = homographies_from_positions(positions)
        reg = register_stack(frames, stack.reference_index, prediction=predicted)
        if messages is not None:
            messages.extend(reg.messages)
        # The data's correction on top of the optics: C_k = H_k P_k^-1, applied to the exact
        # per-pixel positions (which carry the optics' non-homographic part).
        correction = reg.homographies @ torch.linalg.inv(predicted)
        corrected = apply_homography(correction, positions.reshape(F, -1, 2)).reshape(F, H, W, 2)
        use = reg.ok[:, None, None, None]
        positions = torch.where(use, corrected, positions)
        if registration == "data":
            weights = reg.ok.to(torch.float64)
            if messages is not None and not bool(reg.ok.all()):
                messages.append(f"left out {int((~reg.ok).sum())} frame(s) the registration could not trust")
    if fill_factor is None:
        fill_factor = stack_fill_factor(stack)
    image = classical_sr(frames, positions, stack.h, deblur, weights=weights,
                         cutoff=optics_cutoff(stack.system), fill_factor=fill_factor, **kw)
    return image.numpy()


# Reconstruction methods by name: function(stack, registration=..., messages=None, **kw) ->
# (h*H, h*W) float32 array in [0, 1] ("messages": a list that receives warnings, or None).
# Another method (for example "learned") is added with one entry here.
METHODS = {"classical": reconstruct_classical}


def reconstruct(stack, method: str = "classical", registration: str = "auto", **kw) -> np.ndarray:
    """Super-resolve a stack onto the h-times grid of its reference frame's ROI.

    Parameters
    ----------
    stack : hbis_torch.stack_io.Stack
    method : str
        A key of :data:`METHODS` ("classical").
    registration : {"optics", "data", "auto"}
        Where the samples' positions come from: the tracer alone (exact for simulated stacks
        whose phases are the true ones); the tracer corrected by registering the frames
        (frames that cannot be registered are left out); or that correction where the data is
        trusted and the tracer elsewhere ("auto").
    **kw
        Passed to the method (for classical: ``deblur``, ``messages`` (a list that receives the
        registration's warnings), ``fill_factor``, and :func:`classical_sr`'s keywords).

    Returns
    -------
    np.ndarray, shape (h*H, h*W), float32 in [0, 1]
    """
    if method not in METHODS:
        raise HbisInputError(f"unknown reconstruction method {method!r}; available: {', '.join(METHODS)}")
    return METHODS[method](stack, registration=registration, **kw)
