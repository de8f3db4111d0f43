"""Transfer functions of the classical method's image model, per frequency (cycles per px).

The optics (:func:`optics_cutoff`, :func:`diffraction_otf`), a pixel's aperture (:func:`box`)
and the normalized-convolution splat (:func:`splat_transfer`); :mod:`.wiener` combines them.
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
