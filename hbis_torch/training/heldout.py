"""The held-out matrix: stacks the training never saw, shared by training/eval_matrix.py (the
learned method against the classical one), training/variants_ab.py and benchmarks/bench_ensemble.py.

Held out from training on every axis at once (training/eval_matrix.py's docstring says more):
scenes (the photographs of :data:`PHOTOS`), forward models the training never used (a Gaussian
lens PSF, vignetting with fixed-pattern noise, and a second renderer,
:mod:`hbis_torch.training.independent_render`), settings outside the training ranges, and
captured-like metadata (no noise model). A cell is a condition of :data:`CONDITIONS` x a
photograph x h: :func:`make_stack` simulates it, :func:`score` scores a reconstruction of it.
"""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import skimage.filters

from hbis_torch.config import FoveaSystem
from hbis_torch.metrics import psnr
from hbis_torch.reconstruct.learned.domain import noise_at_mid_grey
from hbis_torch.reconstruct.learned.inputs import sensor_noise_params
from hbis_torch.scan import plan_scan
from hbis_torch.simulate import SensorModel, simulate_stack
from hbis_torch.simulate.rasters import HELD_OUT_PHOTOS
from hbis_torch.simulate.stacks import scene_for_roi
from hbis_torch.stack_io import Stack
from hbis_torch.training.independent_render import render_like

PHOTOS = HELD_OUT_PHOTOS  # kept out of every training pool


@dataclasses.dataclass(frozen=True)
class Condition:
    """One held-out setting of the forward model and the scan."""

    name: str
    f_number: float = 1.4
    full_well_e: float = 10_000.0
    read_noise_e: float = 2.0
    bit_depth: int = 12
    reference: str = "first"  # "first", "centre" (the plan's) or "last" frame of the scan
    corner: bool = False  # the ROI at the sensor's top-left corner (else its centre)
    phase_error_deg: float = 0.0
    plan_method: str = "exact"
    gaussian_psf_px: float = 0.0  # Gaussian lens PSF, sigma in sensor pixels (F 1's Airy on top)
    vignetting: bool = False  # 30 % fall-off across the ROI, 1 % pixel gain and 0.2 % dark offsets
    noise_in_metadata: bool = False
    independent: bool = False  # frames and truth from independent_render


CONDITIONS = (
    Condition("F1.4, 10k e-, reference frame 0"),
    Condition("F1.4, 10k e-, reference at the centre", reference="centre"),
    Condition("noise in the metadata (F1.4, 10k e-, ref 0)", noise_in_metadata=True),
    Condition("low noise, no blur (F1, 50k e-)", f_number=1.0, full_well_e=50_000),
    Condition("low noise, Airy F2.8 (50k e-)", f_number=2.8, full_well_e=50_000),
    Condition("high noise (2k e-, 8 e- read, 10 bit)", full_well_e=2_000, read_noise_e=8.0, bit_depth=10),
    Condition("corner, paper scan, phase error, last ref", corner=True, plan_method="paper",
              phase_error_deg=0.02, reference="last"),
    Condition("Gaussian PSF 0.7 px [unseen model]", f_number=1.0, gaussian_psf_px=0.7),
    Condition("vignetting + fixed pattern [unseen model]", full_well_e=20_000, vignetting=True),
    Condition("F11, 300k e-, 16 bit [outside ranges]", f_number=11.0, full_well_e=300_000, bit_depth=16),
    Condition("F1.4, 10k e-, ref 0 [independent renderer]", independent=True),
    Condition("low noise, no blur (F1, 50k e-) [independent renderer]", f_number=1.0, full_well_e=50_000,
              independent=True),
    Condition("low noise, Airy F2.8 (50k e-) [independent renderer]", f_number=2.8, full_well_e=50_000,
              independent=True),
    Condition("high noise (2k e-, 8 e- read, 10 bit) [independent renderer]", full_well_e=2_000,
              read_noise_e=8.0, bit_depth=10, independent=True),
)


def make_stack(cond: Condition, photo: str, h: int, size: int, seed: int):
    """The stack and ground truth of one cell.

    Parameters
    ----------
    cond : Condition
    photo : str
        One of :data:`PHOTOS`.
    h : int
        Resolution improvement factor.
    size : int
        Side of the sensor ROI, LR pixels.
    seed : int
        Seed of the noise (and of the fixed pattern).

    Returns
    -------
    stack : Stack
        h^2 frames of size x size.
    truth : ndarray, shape (h size, h size), float32 in [0, 1]
    """
    base = FoveaSystem()
    system = dataclasses.replace(base, camera=dataclasses.replace(base.camera, f_number=cond.f_number))
    plan = plan_scan(system, h, method=cond.plan_method)
    index = {"first": 0, "centre": plan.reference_index, "last": h * h - 1}[cond.reference]
    plan = dataclasses.replace(plan, reference_index=index)
    cam = system.camera
    roi = (8, 8, size, size) if cond.corner else ((cam.cols - size) // 2, (cam.rows - size) // 2, size, size)
    scene = scene_for_roi(photo, system, roi, h)
    if cond.gaussian_psf_px:
        sigma = cond.gaussian_psf_px * system.object_pixel_mm / scene.pixel_mm  # raster pixels
        blurred = skimage.filters.gaussian(scene.image.numpy(), sigma, mode="reflect")
        scene = dataclasses.replace(scene, image=blurred.astype(np.float32))
    sensor = SensorModel(full_well_e=cond.full_well_e, read_noise_e=cond.read_noise_e, bit_depth=cond.bit_depth)
    stack, truth = simulate_stack(scene, system, plan, roi=roi, sensor=sensor, seed=seed,
                                  phase_error_deg=cond.phase_error_deg)
    meta = json.loads(json.dumps(stack.meta))
    frames = stack.frames
    if cond.independent:  # the simulator's stack gives the metadata only
        frames, truth = render_like(stack, scene, sensor, seed)
    if cond.vignetting:
        frames, truth = fixed_pattern(stack, truth, np.random.default_rng(seed))
    if not cond.noise_in_metadata:
        for key in ("full_well_e", "read_noise_e"):
            meta["simulation"]["sensor"].pop(key, None)
    return Stack(frames, meta).validate("held-out stack"), truth


def vignetting(x, y, cols: int, rows: int):
    """Relative illumination at ROI pixel coordinates (x, y): 30 % fall-off to the ROI's corners."""
    cx, cy = (cols - 1) / 2, (rows - 1) / 2
    return 1 - 0.3 * ((x - cx) ** 2 + (y - cy) ** 2) / (cx**2 + cy**2)


def fixed_pattern(stack: Stack, truth, rng: np.random.Generator):
    """The stack's frames through a vignetted lens and a sensor with fixed-pattern noise (1 %
    pixel gain, dark offsets of 0.2 % of full scale), and the truth vignetted the same way (the
    fixed pattern is the sensor's, not the scene's)."""
    h = stack.h
    x = stack.to_float().numpy()
    _, rows, cols = x.shape
    yy, xx = np.mgrid[0:rows, 0:cols]
    gain = vignetting(xx, yy, cols, rows) * (1 + 0.01 * rng.standard_normal((rows, cols)))
    dark = 0.002 * np.abs(rng.standard_normal((rows, cols)))
    white = 2 ** stack.bit_depth - 1
    frames = np.round(np.clip(x * gain + dark, 0, 1) * white).astype(stack.frames.dtype)
    # output pixel i sits at LR coordinate (i - (h - 1) / 2) / h
    yy, xx = (np.mgrid[0:h * rows, 0:h * cols] - (h - 1) / 2) / h
    return frames, (np.asarray(truth) * vignetting(xx, yy, cols, rows)).astype(np.float32)


def noise_ratio(params, cond: Condition) -> float:
    """Standard deviation at mid grey of noise parameters (a, b) over the condition's sensor's."""
    sensor = sensor_noise_params(cond.full_well_e, cond.read_noise_e, cond.bit_depth)
    return noise_at_mid_grey(params) / noise_at_mid_grey(sensor)


def score(image, truth, h: int) -> float:
    """PSNR (dB) of a reconstruction (hH, hW) against the truth, without a border of 2 LR pixels."""
    b = 2 * h
    return psnr(np.asarray(truth)[b:-b, b:-b], np.asarray(image)[b:-b, b:-b])
