"""Synthetic hbis-stack/1 stacks: the forward model, the sensor, and the file's metadata."""

from __future__ import annotations

import numpy as np
import torch

from hbis_torch.checks import check_phases, check_roi
from hbis_torch.config import FoveaSystem
from hbis_torch.errors import HbisInputError
from hbis_torch.simulate.catalog import SceneSpec, load_scene
from hbis_torch.simulate.forward import grid_factor, render_scan
from hbis_torch.simulate.scenes import Scene
from hbis_torch.simulate.sensor import SensorModel, expose
from hbis_torch.stack_io import Stack, make_meta


def scene_for_roi(name_or_path: str, system: FoveaSystem, roi, h: int, seed: int = 0, size_mm=None,
                  margin_px: float = 4.0, oversample: int = 8) -> Scene:
    """A built-in scene or image file fitted to the view of ``roi``: it covers the roi's
    footprint on the object plane plus the forward model's margin (unless ``size_mm`` is given),
    with procedural detail down to the simulator's grid spacing."""
    u0, v0, w, hh = check_roi(system.camera, roi)
    pixel_mm = system.object_pixel_mm
    border = 2 * (margin_px + 4)
    spec = SceneSpec(((w + border) * pixel_mm, (hh + border) * pixel_mm), pixel_mm,
                     pixel_mm / (h * grid_factor(h, oversample)))
    return load_scene(name_or_path, spec, seed=seed, size_mm=size_mm)


def resolve_plan(system: FoveaSystem, plan):
    """(phases (F, 2) float64 tensor, reference_index, h) from a ScanPlan-like object or an int h.

    ``plan`` may be anything with ``phases_deg``, ``reference_index`` and ``h`` attributes (a
    :class:`hbis_torch.scan.ScanPlan`), or an integer h, planned with ``plan_scan(system, h)``.
    """
    if isinstance(plan, (int, np.integer)) and not isinstance(plan, bool):
        from hbis_torch.scan import plan_scan

        plan = plan_scan(system, int(plan))
    try:
        phases, reference, h = plan.phases_deg, plan.reference_index, plan.h
    except AttributeError:
        raise HbisInputError(
            "plan must be a ScanPlan (phases_deg, reference_index, h) or an integer h"
        ) from None
    return check_phases(phases), int(reference), int(h)


def simulate_stack(
    scene: Scene,
    system: FoveaSystem,
    plan,
    roi=None,
    sensor: SensorModel = SensorModel(),
    seed: int = 0,
    phase_error_deg: float = 0.0,
    oversample: int = 8,
    margin_px: float = 4.0,
) -> tuple[Stack, np.ndarray]:
    """Simulate the stack a scan of ``scene`` records, and its ground truth.

    Parameters
    ----------
    scene : Scene or str
        Object-plane scene, centred on the roi's view when its ``center_mm`` is None; or a
        built-in scene name or image path, fitted to the roi's view by :func:`scene_for_roi`.
    system : FoveaSystem
    plan : ScanPlan or int
        The scan (``phases_deg`` (F, 2), ``reference_index``, ``h``), or h to plan one with
        ``plan_scan(system, h)`` from the default initial phases.
    roi : (u0, v0, width, height) or None
        Frame region on the sensor (None: the whole sensor).
    sensor : SensorModel
        Fill factor, defocus, noise and quantisation.
    seed : int
        Seed of the noise and of the phase errors (same seed, same stack).
    phase_error_deg : float
        Standard deviation of a Gaussian error of every prism phase except the reference
        frame's: frames are rendered at the erroneous phases while the stack records the planned
        ones (the true ones go to ``meta["simulation"]["true_phases_deg"]``).
    oversample : int
        Fine-grid points per sensor pixel of the forward model (see render_scan).
    margin_px : float
        Forward-model margin around the frames, pixels (see render_scan and docs/data.md).

    Returns
    -------
    stack : Stack
        Frames (F, H, W) of ``sensor.dtype``; meta with ``bit_depth``, ``reference_index``,
        ``black_level`` and a ``simulation`` record (scene, sensor, seed).
    truth : np.ndarray, shape (h*H, h*W), float32 in [0, 1]
        What an ideal pitch-p/h sensor sees at the reference phases, noise free.
    """
    phases, reference, h = resolve_plan(system, plan)
    roi = check_roi(system.camera, roi)
    if isinstance(scene, str):
        scene = scene_for_roi(scene, system, roi, h, seed, margin_px=margin_px, oversample=oversample)
    elif not isinstance(scene, Scene):
        raise HbisInputError(f"scene must be a Scene, a built-in scene name or an image path, got {type(scene).__name__}")
    generator = torch.Generator().manual_seed(int(seed))
    true_phases = phases.clone()
    if phase_error_deg:
        if not np.isfinite(phase_error_deg) or phase_error_deg < 0:
            raise HbisInputError(f"phase error must be a finite number >= 0, got {phase_error_deg!r}")
        jitter = phase_error_deg * torch.randn(phases.shape, generator=generator, dtype=torch.float64)
        jitter[reference] = 0.0
        true_phases = phases + jitter
    rendered = render_scan(scene, system, true_phases, reference, h, roi, sensor,
                           oversample=oversample, margin_px=margin_px, return_positions=False)
    frames = expose(rendered.irradiance, sensor, generator)
    placed = rendered.scene
    record = {
        "scene": placed.name,
        "scene_size_mm": list(placed.size_mm),
        "scene_center_mm": list(placed.center_mm),
        "sensor": sensor.to_dict(),
        "seed": int(seed),
        "oversample": int(oversample),
        "margin_px": float(margin_px),
        "phase_error_deg": float(phase_error_deg),
    }
    if phase_error_deg:
        record["true_phases_deg"] = true_phases.tolist()
    extra = {"simulation": record}
    if sensor.bit_depth is not None:
        extra["black_level"] = float(sensor.black_level_dn)
    meta = make_meta(system, h, roi, phases.numpy(), bit_depth=sensor.bit_depth,
                     reference_index=reference, **extra)
    stack = Stack(frames, meta).validate("simulated stack")
    return stack, rendered.truth.numpy()
