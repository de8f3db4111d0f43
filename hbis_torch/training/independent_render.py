"""A second forward model, written apart from ``hbis_torch.simulate``, for the held-out matrix.

The project's simulator renders the scene once on the reference frame's grid, blurs it there by
the lens's and the pixel's transfer functions, and reads every frame's samples from that blurred
image at their positions. This one does what a camera does, frame by frame:

- the lens's PSF (the Airy pattern of the f-number at the camera's wavelength, and optionally a
  Gaussian) is convolved with the scene raster on the object plane, in the raster's own pixels;
- each pixel of each frame averages the blurred scene over its own footprint at its own prism
  phases: the chief rays of ``points`` x ``points`` points spread over its light-sensitive
  square, traced through the prisms to the object plane and read there with cubic splines;
- Poisson shot noise, Gaussian read noise and quantisation are drawn with numpy;
- the truth is the same blurred scene averaged over the output pixels' squares (side
  sqrt(fill factor) / h sensor pixels) at the reference phases.

It shares with the simulator only the exact ray trace (``hbis_torch.optics``, checked against the
paper) and where the scene sits on the object plane (read from the stack's metadata). Nothing of
the simulator's grid, transfer functions, B-spline sampling or noise is used.

    frames, truth = render_like(stack, scene, sensor, seed=1)
"""

from __future__ import annotations

import math

import numpy as np
import scipy.ndimage
import scipy.signal
import scipy.special
import torch

from hbis_torch.optics import landing_at
from hbis_torch.simulate import SensorModel
from hbis_torch.stack_io import Stack

# The Airy pattern is cut at this many radii of its first dark ring (it keeps 99 % of the light
# at 8; the kernel is normalised to sum 1).
AIRY_RINGS = 8


def airy_kernel(system, raster_mm: tuple[float, float], supersample: int = 5) -> np.ndarray:
    """The lens's Airy PSF on the scene raster's pixels (rows, cols), normalised to sum 1.

    ``raster_mm`` is one raster pixel's (width, height) on the object plane. Each raster pixel
    holds the PSF averaged over ``supersample`` x ``supersample`` points.
    """
    cam = system.camera
    lam_f_px = cam.wavelength_nm * 1e-3 * cam.f_number / cam.pixel_pitch_um  # lambda F, sensor px
    reach_px = AIRY_RINGS * 1.22 * lam_f_px
    to_px = 1.0 / system.object_pixel_mm  # object-plane mm -> sensor px
    half = [max(1, math.ceil(reach_px / (side * to_px))) for side in raster_mm]  # (x, y) in raster px
    sub = (np.arange(supersample) + 0.5) / supersample - 0.5
    x = (np.arange(-half[0], half[0] + 1)[:, None] + sub[None, :]).ravel() * raster_mm[0] * to_px
    y = (np.arange(-half[1], half[1] + 1)[:, None] + sub[None, :]).ravel() * raster_mm[1] * to_px
    r = np.hypot(x[None, :], y[:, None])  # sensor px
    arg = np.pi * r / lam_f_px
    with np.errstate(invalid="ignore", divide="ignore"):
        psf = np.where(arg > 1e-8, (2 * scipy.special.j1(arg) / arg) ** 2, 1.0)
    psf = psf.reshape(2 * half[1] + 1, supersample, 2 * half[0] + 1, supersample).mean(axis=(1, 3))
    return psf / psf.sum()


def blurred_scene(system, scene, gaussian_psf_px: float = 0.0) -> np.ndarray:
    """The scene raster (rows, cols) through the lens on the object plane: the Airy PSF of the
    system's f-number, then a Gaussian of ``gaussian_psf_px`` sensor px (0: none); borders
    mirrored, as the scene is outside its extent."""
    image = np.asarray(scene.image, dtype=np.float64)
    rows, cols = image.shape
    raster_mm = (scene.size_mm[0] / cols, scene.size_mm[1] / rows)
    kernel = airy_kernel(system, raster_mm)
    ky, kx = kernel.shape[0] // 2, kernel.shape[1] // 2
    padded = np.pad(image, ((ky, ky), (kx, kx)), mode="symmetric")
    out = scipy.signal.fftconvolve(padded, kernel, mode="valid")
    if gaussian_psf_px:
        sigma = [gaussian_psf_px * system.object_pixel_mm / side for side in (raster_mm[1], raster_mm[0])]
        out = scipy.ndimage.gaussian_filter(out, sigma, mode="mirror")
    return out


def area_average(coeffs: np.ndarray, scene, center_mm, system, u: np.ndarray, v: np.ndarray,
                 side_px: float, phases_deg, points: int) -> np.ndarray:
    """The blurred scene averaged over squares of side ``side_px`` sensor px centred on sensor
    coordinates (u, v) (equal shapes), seen at ``phases_deg``: ``points`` x ``points`` chief
    rays per square. ``coeffs`` are the blurred raster's cubic spline coefficients."""
    rows, cols = coeffs.shape
    offsets = ((np.arange(points) + 0.5) / points - 0.5) * side_px
    total = np.zeros(u.shape)
    for dy in offsets:
        for dx in offsets:
            mm = landing_at(system, torch.from_numpy(u + dx), torch.from_numpy(v + dy),
                            float(phases_deg[0]), float(phases_deg[1])).numpy()  # the exact trace, mm
            # scene-local mm -> raster coordinates: pixel (i, j) covers its cell of the extent
            col = ((mm[..., 0] - center_mm[0]) / scene.size_mm[0] + 0.5) * cols - 0.5
            row = ((mm[..., 1] - center_mm[1]) / scene.size_mm[1] + 0.5) * rows - 0.5
            total += scipy.ndimage.map_coordinates(coeffs, [row.ravel(), col.ravel()], order=3,
                                                   mode="mirror", prefilter=False).reshape(u.shape)
    return total / points ** 2


def render_like(stack: Stack, scene, sensor: SensorModel, seed: int, gaussian_psf_px: float = 0.0,
                points: int = 6) -> tuple[np.ndarray, np.ndarray]:
    """Frames and truth of ``stack``'s scan of ``scene``, rendered by this module's model.

    Parameters
    ----------
    stack : Stack
        A stack simulated by the project (its system, roi, scan and the scene's placement,
        ``meta["simulation"]["scene_center_mm"]``, and the true phases where it has phase errors):
        only its metadata is read.
    scene : ImageScene
        The scene raster (``image`` (rows, cols) in [0, 1]) and its extent ``size_mm``.
    sensor : SensorModel
        Fill factor, full well, read noise and bit depth.
    seed : int
        Seed of the noise.
    gaussian_psf_px : float
        A Gaussian lens blur (sigma, sensor px) on top of the Airy pattern.
    points : int
        Chief rays per side of each pixel's square.

    Returns
    -------
    frames : np.ndarray, shape (F, H, W), the sensor's dtype
    truth : np.ndarray, shape (h H, h W), float32 in [0, 1]
    """
    system, h = stack.system, stack.h
    u0, v0, width, height = stack.roi
    sim = stack.meta["simulation"]
    phases = np.asarray(sim.get("true_phases_deg", stack.phases_deg), dtype=np.float64).reshape(-1, 2)
    center = sim["scene_center_mm"]
    coeffs = scipy.ndimage.spline_filter(blurred_scene(system, scene, gaussian_psf_px), order=3, mode="mirror")
    side = math.sqrt(sensor.fill_factor)

    v, u = np.mgrid[v0:v0 + height, u0:u0 + width].astype(np.float64)
    irradiance = np.stack([area_average(coeffs, scene, center, system, u, v, side, p, points) for p in phases])
    # output pixel i sits at ROI-local LR coordinate (i - (h - 1) / 2) / h
    yy, xx = np.mgrid[0:h * height, 0:h * width].astype(np.float64)
    truth = area_average(coeffs, scene, center, system, u0 + (xx - (h - 1) / 2) / h,
                         v0 + (yy - (h - 1) / 2) / h, side / h, phases[stack.reference_index], points)

    electrons = np.clip(irradiance, 0, 1) * sensor.full_well_e
    if sensor.noise:
        rng = np.random.default_rng(seed)
        electrons = rng.poisson(electrons).astype(np.float64)
        electrons += sensor.read_noise_e * rng.standard_normal(electrons.shape)
    if sensor.bit_depth is None:  # float frames in [0, 1]
        return np.clip(electrons / sensor.full_well_e, 0, 1).astype(np.float32), np.clip(truth, 0, 1).astype(np.float32)
    dn = np.round(sensor.black_level_dn + electrons * sensor.gain_dn_per_e)
    frames = np.clip(dn, 0, sensor.white_level).astype(sensor.dtype)
    return frames, np.clip(truth, 0, 1).astype(np.float32)
