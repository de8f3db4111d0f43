"""Closed-form pixel values for grating scenes: an independent check of the forward model.

For a sinusoidal grating ``S(r) = m + a cos(2 pi k . r + phase)`` (k in cycles/mm on the object
plane) the landing map around a pixel centre c is affine to within its curvature, about 1e-4
pixel across the few pixels where the PSF has its energy: ``L(x) ~ L(c) + J (x - c)``. Then
``S o L`` is a grating on the sensor of frequency ``f = J^T k`` (cycles/pixel), and blurring it
with the shift-invariant kernel K = PSF * aperture multiplies its amplitude by the real transfer
``H(f)`` (lens OTF times the aperture's sinc). So

    I(c) = m + a H(J^T k) cos(2 pi k . L(c) + phase),

with L(c) traced exactly at the frame's own phases and J from exact traces at c +- 0.01 pixel.
None of the fast model's machinery (shared grid, FFT, interpolation, splines, sample positions,
the frames-are-translations argument) is used. Exact for the whole PSF, tails included.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

from hbis_torch.config import FoveaSystem
from hbis_torch.optics import landing_at
from hbis_torch.simulate.psf import defocus_waves, lens_otf, pixel_transfer
from hbis_torch.simulate.scenes import GratingScene
from hbis_torch.simulate.sensor import SensorModel


def grating_pixels(
    grating: GratingScene,
    system: FoveaSystem,
    phases_deg,
    centres_uv: Tensor,
    aperture_px: float,
    sensor: SensorModel = SensorModel(),
    spacing_mm: float | None = None,
) -> Tensor:
    """Noise-free values of pixels centred at ``centres_uv`` (N, 2) (sensor pixels, may be
    fractional) through an aperture of side ``aperture_px``; (N,) float64.

    ``grating`` must be placed (``center_mm`` set); ``spacing_mm`` applies the same cell average
    as ``grating.sample(..., spacing_mm)``.
    """
    cam = system.camera
    centres = torch.as_tensor(centres_uv, dtype=torch.float64)
    u, v = centres[:, 0], centres[:, 1]
    p1, p2 = float(phases_deg[0]), float(phases_deg[1])
    eps = 0.01
    landing = landing_at(system, u, v, p1, p2)
    du = (landing_at(system, u + eps, v, p1, p2) - landing_at(system, u - eps, v, p1, p2)) / (2 * eps)
    dv = (landing_at(system, u, v + eps, p1, p2) - landing_at(system, u, v - eps, p1, p2)) / (2 * eps)
    a = math.radians(grating.angle_deg)
    k = torch.tensor([math.cos(a), math.sin(a)], dtype=torch.float64) / grating.period_mm
    fu, fv = (du @ k).numpy(), (dv @ k).numpy()  # cycles per pixel on the sensor
    w20 = defocus_waves(sensor.defocus_um, cam.f_number, cam.wavelength_nm)
    transfer = lens_otf(np.hypot(fu, fv) / cam.pixel_pitch_um, cam.f_number, cam.wavelength_nm, w20)
    transfer = transfer * pixel_transfer(fu, fv, aperture_px)
    amplitude = grating.amplitude
    if spacing_mm:
        amplitude *= float(np.sinc(spacing_mm * k[0]) * np.sinc(spacing_mm * k[1]))
    local = landing - torch.tensor(grating.center_mm, dtype=torch.float64)
    phase = 2 * math.pi * (local @ k) + grating.phase
    return grating.mean + amplitude * torch.from_numpy(transfer) * torch.cos(phase)


def grating_frame(grating, system, phases_deg, pixels_uv, sensor=SensorModel(), spacing_mm=None) -> Tensor:
    """Values of sensor pixels (N, 2) of a frame taken at ``phases_deg``."""
    return grating_pixels(grating, system, phases_deg, pixels_uv, math.sqrt(sensor.fill_factor),
                          sensor, spacing_mm)


def grating_truth(grating, system, reference_phases, hr_pixels, roi, h, sensor=SensorModel(),
                  spacing_mm=None) -> Tensor:
    """Ground truth at HR pixels (N, 2) (U, V) of the output grid of ``roi`` (docs/data.md)."""
    hr = torch.as_tensor(hr_pixels, dtype=torch.float64)
    centres = torch.stack((roi[0] + (hr[:, 0] + 0.5) / h - 0.5, roi[1] + (hr[:, 1] + 0.5) / h - 0.5), -1)
    return grating_pixels(grating, system, reference_phases, centres, math.sqrt(sensor.fill_factor) / h,
                          sensor, spacing_mm)
