"""The lens's point spread function and the pixel aperture, as transfer functions on the sensor.

Everything here is in sensor-plane units: lengths in micrometres, spatial frequencies in cycles
per micrometre (or cycles per pixel where a name says so). The lens is diffraction limited with a
circular pupil of working F-number F at wavelength lambda: its incoherent PSF is the Airy pattern
``(2 J1(x) / x)**2`` with ``x = pi r / (lambda F)``, first zero at ``r = 1.22 lambda F`` (0.94 um for
Table 1), and its OTF is the pupil's autocorrelation, zero beyond ``1 / (lambda F)``. Defocus adds
the wavefront ``W20 rho**2`` (W20 in waves; a sensor ``dz`` out of focus gives
``W20 = dz / (8 F**2 lambda)``), and its OTF is computed numerically from the pupil.

A pixel integrates light over a centred square of side ``sqrt(fill_factor) * pitch`` (the fill
factor is an area ratio); its transfer is ``sinc(a fx) sinc(a fy)``.

The renderer multiplies a scene's spectrum (its DCT) by the product of both
(:func:`blur_transfer`): exact convolution with PSF * pixel aperture for a band-limited scene,
with no truncated kernel.
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np
import torch

from hbis_torch.errors import HbisInputError


def airy_psf(r_um, f_number: float, wavelength_nm: float) -> np.ndarray:
    """Diffraction-limited PSF of a circular pupil, normalised to unit integral over the plane.

    Parameters
    ----------
    r_um : array-like
        Radius from the PSF centre on the sensor, micrometres.
    f_number : float
        Working F-number F.
    wavelength_nm : float
        Wavelength lambda, nanometres.

    Returns
    -------
    np.ndarray, same shape as r_um
        PSF in 1/um^2; first zero at r = 1.22 lambda F.
    """
    from scipy.special import j1

    lam_f = wavelength_nm * 1e-3 * f_number
    x = np.pi * np.asarray(r_um, dtype=np.float64) / lam_f
    safe = np.where(x == 0, 1.0, x)
    amplitude = np.where(x == 0, 1.0, 2 * j1(safe) / safe)
    peak = np.pi / (4 * lam_f**2)  # makes the integral over the plane one
    return peak * amplitude**2


def airy_otf(nu) -> np.ndarray:
    """OTF of an aberration-free circular pupil at normalised frequency nu = f lambda F.

    ``(2/pi) (arccos nu - nu sqrt(1 - nu^2))`` for nu <= 1, zero beyond.
    """
    nu = np.clip(np.abs(np.asarray(nu, dtype=np.float64)), 0.0, 1.0)
    return (2 / np.pi) * (np.arccos(nu) - nu * np.sqrt(1 - nu * nu))


def defocus_waves(defocus_um: float, f_number: float, wavelength_nm: float) -> float:
    """Peak defocus wavefront W20 in waves for a sensor ``defocus_um`` out of focus: dz/(8 F^2 lambda)."""
    return defocus_um / (8 * f_number**2 * wavelength_nm * 1e-3)


@lru_cache(maxsize=16)
def _defocus_otf_table(w20_waves: float, radius: int = 128) -> tuple[np.ndarray, np.ndarray]:
    """OTF(nu) of a circular pupil with defocus W20, tabulated on nu in [0, 1].

    The pupil is sampled with ``radius`` samples per radius; its autocorrelation (by FFT, on a
    grid wide enough not to wrap) is real for this symmetric aberration and may be negative.
    """
    n = 4 * radius + 8
    c = np.arange(n) - n // 2
    y, x = np.meshgrid(c, c, indexing="ij")
    rho2 = (x * x + y * y) / radius**2
    pupil = np.where(rho2 <= 1.0, np.exp(2j * np.pi * w20_waves * rho2), 0.0)
    spectrum = np.fft.fft2(pupil)
    autocorr = np.fft.ifft2(np.abs(spectrum) ** 2).real
    shifts = np.arange(2 * radius + 1)
    otf = autocorr[0, shifts] / autocorr[0, 0]
    return shifts / (2 * radius), otf


def lens_otf(freq_cyc_per_um, f_number: float, wavelength_nm: float, w20_waves: float = 0.0):
    """OTF of the lens at radial frequency ``freq_cyc_per_um`` on the sensor (cycles/um).

    Analytic (:func:`airy_otf`) in focus; tabulated from the pupil with defocus W20 (waves).
    """
    nu = np.abs(np.asarray(freq_cyc_per_um, dtype=np.float64)) * wavelength_nm * 1e-3 * f_number
    if w20_waves == 0.0:
        return airy_otf(nu)
    table_nu, table_otf = _defocus_otf_table(float(w20_waves))
    return np.interp(np.minimum(nu, 1.0), table_nu, table_otf, right=0.0) * (nu < 1.0)


def pixel_transfer(fx_cyc_per_px, fy_cyc_per_px, aperture_px: float) -> np.ndarray:
    """Transfer of a square aperture of side ``aperture_px`` pixels: sinc(a fx) sinc(a fy)."""
    return np.sinc(aperture_px * np.asarray(fx_cyc_per_px)) * np.sinc(
        aperture_px * np.asarray(fy_cyc_per_px)
    )


def dct_frequencies(n: int, spacing: float) -> np.ndarray:
    """Frequencies (cycles per unit of ``spacing``) of the n DCT-II coefficients of samples
    ``spacing`` apart: k / (2 n spacing), those of the signal's even, 2n-periodic extension."""
    return np.arange(n) / (2 * n * spacing)


@lru_cache(maxsize=64)
def _lens_table(shape, spacing_px, pitch_um, f_number, wavelength_nm, w20, dtype) -> torch.Tensor:
    ny, nx = shape
    fy = dct_frequencies(ny, spacing_px)[:, None]  # cycles per pixel of the sensor's pitch
    fx = dct_frequencies(nx, spacing_px)[None, :]
    return torch.from_numpy(lens_otf(np.hypot(fx, fy) / pitch_um, f_number, wavelength_nm, w20)).to(dtype)


def aperture_vectors(shape, spacing_px: float, aperture_px: float, dtype=torch.float32):
    """The square aperture's separable transfer on DCT-II frequencies: (Ny, 1) and (1, Nx)."""
    fy = dct_frequencies(int(shape[0]), spacing_px)
    fx = dct_frequencies(int(shape[1]), spacing_px)
    return (torch.from_numpy(np.sinc(aperture_px * fy)).to(dtype)[:, None],
            torch.from_numpy(np.sinc(aperture_px * fx)).to(dtype)[None, :])


def blur_transfer(
    shape: tuple[int, int],
    spacing_px: float,
    pitch_um: float,
    f_number: float,
    wavelength_nm: float,
    aperture_px: float,
    w20_waves: float = 0.0,
    dtype=torch.float32,
) -> torch.Tensor:
    """PSF * pixel-aperture transfer on the DCT-II frequencies of a regular sensor grid.

    Multiplying the 2-D DCT-II of a grid by it and inverting convolves the grid's mirror-image
    (even) extension with the kernel: the extension is continuous at the borders, so the PSF's
    long tails see mirrored scene there rather than the far side of the grid.

    Parameters
    ----------
    shape : (Ny, Nx)
        Size of the grid the transfer will multiply (``scipy.fft.dctn(grid, type=2)`` of it).
    spacing_px : float
        Grid spacing in pixels of pitch ``pitch_um``.
    pitch_um : float
        Pixel pitch of the sensor the grid is measured in, micrometres.
    f_number, wavelength_nm : float
        Lens F-number and wavelength (nm).
    aperture_px : float
        Side of the pixel's light-sensitive square in the same pixels (sqrt(fill factor) for the
        sensor itself, sqrt(fill factor) / h for the ideal pitch p/h sensor of the ground truth).
    w20_waves : float
        Defocus wavefront in waves (0: in focus).

    Returns
    -------
    Tensor, shape (Ny, Nx)
        Real transfer values (the PSF and aperture are symmetric, so the transfer is real). The
        lens part is cached per grid; the aperture part is separable and cheap.
    """
    values = (spacing_px, pitch_um, f_number, wavelength_nm, aperture_px, w20_waves)
    if not all(math.isfinite(v) for v in values) or min(values[:5]) <= 0:
        raise HbisInputError(f"blur parameters must be finite and positive, got {values}")
    shape = (int(shape[0]), int(shape[1]))
    lens = _lens_table(shape, float(spacing_px), float(pitch_um), float(f_number),
                       float(wavelength_nm), float(w20_waves), dtype)
    sy, sx = aperture_vectors(shape, spacing_px, aperture_px, dtype)
    return lens * sy * sx
