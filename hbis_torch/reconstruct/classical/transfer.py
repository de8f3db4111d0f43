"""Transfer functions of the classical method's image model, per frequency (cycles per px).

The optics (:func:`optics_cutoff`, :func:`diffraction_otf`), a pixel's aperture (:func:`box`)
the normalized-convolution splat (:func:`splat_transfer`) and a lens blur known to a spread
(:func:`lens_transfer`); :mod:`.wiener` combines them.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor


def optics_cutoff(system) -> float:
    """Incoherent diffraction cutoff of the lens, in cycles per LR (sensor) pixel: p / (lambda F)."""
    cam = system.camera
    return cam.pixel_pitch_um / (cam.wavelength_nm * 1e-3 * cam.f_number)


def diffraction_otf(rho: Tensor) -> Tensor:
    """OTF of an aberration-free circular pupil at normalised frequency rho = f / f_cutoff.

    (2/pi) (acos(rho) - rho sqrt(1 - rho^2)) for rho < 1, else 0.
    """
    r = rho.clamp(0, 1)
    chord = r.square().neg_().add_(1).sqrt_().mul_(r)  # r sqrt(1 - r^2), in place
    return torch.acos(r).sub_(chord).mul_(2 / math.pi)


def box(f: Tensor, width: float) -> Tensor:
    """Transfer function of a box of ``width`` px at frequency f (cycles/px): sinc(width f)."""
    return torch.sinc(width * f)


def gaussian_transfer(f2: Tensor, sigma: float) -> Tensor:
    """Transfer function of a Gaussian blur of standard deviation ``sigma`` px at squared
    frequency f2 (cycles^2 per px^2): exp(-2 pi^2 sigma^2 f2)."""
    return torch.exp(f2 * (-2 * math.pi ** 2 * sigma * sigma))


def splat_transfer(f: Tensor, sigma: float) -> Tensor:
    """Transfer function, along one axis, of normalized convolution with the 3-tap Gaussian
    splat on a lattice with one sample per node: (1 + 2a cos 2 pi f) / (1 + 2a), a = e^(-1/2s^2).
    """
    a = math.exp(-1 / (2 * sigma * sigma))
    return (1 + 2 * a * torch.cos(2 * math.pi * f)) / (1 + 2 * a)


# The lens blur's relative spread: its variance is taken as uniform over (1 -+ LENS_SPREAD) times
# the square of the sigma given (a burst's estimate or --psf-sigma), and the filter is the MMSE one
# over that spread (:func:`lens_transfer`: E[g] where the Wiener filter has the lens's transfer g, E[g^2]
# where it has g^2). Undoing a lens larger than the true one multiplies the scene's detail by their
# transfers' ratio, which grows without bound with the frequency: 40 % too large (0.42 LR px for
# 0.3) had cost up to 3.5 dB there; the spread caps the gain where the lens is uncertain. Chosen on
# development bursts (training/dev_lens_spread.py: the training simulator's five of seed 1 and the
# third renderer's five with the training photographs of seed 12, 640 x 480, S = 2 to 4): the
# largest of 0.3 / 0.6 / 0.9 that cost no burst more than 0.1 dB with the burst's own estimate or
# with the true lens (0.6: at most 0.05 and 0.08 dB; 0.9: 0.12 and 0.20), where it gains +0.49 to
# +1.19 dB with the lens 40 % too large (benchmarks/results/dev_lens_spread_sim.json, _third.json).
LENS_SPREAD = 0.6


def lens_transfer(r2: Tensor, sigma: float, spread: float) -> tuple[Tensor, Tensor]:
    """The mean Gaussian lens transfer and the mean of its square, E[g] and E[g^2], at squared
    frequencies ``r2`` (cycles^2 per px^2) where g = exp(-2 pi^2 s^2 r2) and s^2 is uniform over
    (1 -+ ``spread``) ``sigma``^2 (px): with a = 2 pi^2 sigma^2 r2,
    E[g] = exp(-a (1 - spread)) (1 - exp(-2 a spread)) / (2 a spread), E[g^2] the same at 2 a.
    ``spread`` 0: g and g^2 of ``sigma`` itself."""
    a = r2 * (2 * math.pi ** 2 * sigma * sigma)
    if spread <= 0:
        g = torch.exp(-a)
        return g, g * g

    def mean(a: Tensor) -> Tensor:
        x = a * (2 * spread)
        share = torch.where(x > 1e-6, -torch.expm1(-x) / x.clamp_min(1e-6), 1 - 0.5 * x)
        return torch.exp(-a * (1 - spread)) * share

    return mean(a), mean(2 * a)
