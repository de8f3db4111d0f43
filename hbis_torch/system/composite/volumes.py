"""Foveal ratio and bandwidth saving ratio (BSR) from what the system actually sampled.

Foveal ratio (paper section 3.3): the ratio of the fovea's to the periphery's spatial sampling
frequency. Measured here from the geometry of the data: at the inlay's centre, the scene-plane
area of one periphery pixel (the parked fovea's own pixel, a Table 1 pixel like every other
camera's) over the area of one SR pixel (traced through the prisms at the reference phases),
square-rooted. Eq. 10's model says h.

BSR (eq. 10) counts pixels: BSR = 1 - transmitted / uniform, where "uniform" is one capture of
the whole FOV at the fovea's SR sampling (whole-FOV area in native pixels x h^2). Eq. 10's
accounting transmits the whole FOV once at native sampling plus the fovea's h^2 - 1 extra full
frames: 1 - (A + (h^2 - 1) M N) / (h^2 A) with A = FER_h FER_v M N. :func:`bandwidth` evaluates
that with A measured from the panorama's coverage, and also the demo's real traffic: nine whole
raw frames (overlaps included) plus h^2 + 1 ROI frames (the scan and its check frame).
"""

from __future__ import annotations

import math

import torch

from hbis_torch.config import FoveaSystem
from hbis_torch.design import bsr as bsr_eq10
from hbis_torch.optics import exit_directions, land_on_plane, rays_at
from hbis_torch.system.stitch.stitch import Canvas


def _pixel_area_mm2(system: FoveaSystem, u: float, v: float, step: float, phases) -> float:
    """Scene-plane area (mm^2) of a sensor cell of side ``step`` pixels centred at (u, v)."""
    du = torch.tensor([[-0.5, -0.5], [0.5, -0.5], [0.5, 0.5], [-0.5, 0.5]], dtype=torch.float64) * step
    rays = rays_at(system.camera, u + du[:, 0], v + du[:, 1])
    corners = land_on_plane(exit_directions(rays, *phases, system.prisms), system.object_distance_mm)
    x, y = corners[:, 0], corners[:, 1]
    return 0.5 * abs(float((x * y.roll(-1) - x.roll(-1) * y).sum()))  # shoelace


def foveal_ratio(system: FoveaSystem, roi, h: int, reference_phases_deg, parked_phases_deg=(0.0, 180.0)) -> float:
    """Measured foveal ratio at the centre of ``roi`` (see the module's notes)."""
    u0, v0, w, hh = roi
    u, v = u0 + (w - 1) / 2, v0 + (hh - 1) / 2
    sr_area = _pixel_area_mm2(system, u, v, 1.0 / h, reference_phases_deg)
    # the periphery pixel looking at the same scene point: trace it back through the parked pair
    rays = rays_at(system.camera, torch.tensor(u, dtype=torch.float64), torch.tensor(v, dtype=torch.float64))
    point = land_on_plane(exit_directions(rays, *reference_phases_deg, system.prisms), system.object_distance_mm)
    from hbis_torch.optics import sensor_position

    pu, pv = (float(c) for c in sensor_position(system, point, *parked_phases_deg))
    native_area = _pixel_area_mm2(system, pu, pv, 1.0, parked_phases_deg)
    return math.sqrt(native_area / sr_area)


def covered_native_pixels(coverage: torch.Tensor, canvas: Canvas, binning: int) -> float:
    """Whole-FOV area in native (unbinned) sensor pixels, from a panorama's coverage."""
    native_per_canvas = binning / float(canvas.A[0, 0])
    return float((torch.as_tensor(coverage) > 0).sum()) * native_per_canvas**2


def bandwidth(system: FoveaSystem, h: int, whole_fov_native_px: float, roi, fer_h: float, fer_v: float,
              design_fer: tuple[float, float] | None = None, cameras: int = 9) -> dict:
    """BSR by eq. 10's accounting and by the demo's real traffic (see the module's notes).

    Returns a dict of pixel counts and ratios (all plain floats).
    """
    frame = system.camera.rows * system.camera.cols
    uniform = whole_fov_native_px * h * h
    eq10_traffic = whole_fov_native_px + (h * h - 1) * frame
    roi_px = roi[2] * roi[3]
    demo_traffic = cameras * frame + (h * h + 1) * roi_px
    out = {
        "uniform_capture_px": uniform,
        "eq10_traffic_px": eq10_traffic,
        "demo_traffic_px": demo_traffic,
        "bsr_from_coverage": 1.0 - eq10_traffic / uniform,
        "bsr_eq10_measured_fer": bsr_eq10(h, fer_h, fer_v),
        "bsr_demo_traffic": 1.0 - demo_traffic / uniform,
        "whole_fov_frames": whole_fov_native_px / frame,
    }
    if design_fer is not None:
        out["bsr_eq10_design_fer"] = bsr_eq10(h, *design_fer)
    return out
