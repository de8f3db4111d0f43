"""Steering the fovea onto an object: prism phases, the ROI around the object, the scan field.

The policy: the fovea's axis is deviated toward the object, as far as needed to centre it but
no further than the phase difference window ``phase_difference_deg`` allows (near 0 deg the
pair cannot make the sub-pixel pattern, near 180 deg it is singular: the paper's section 3.2);
whatever the axis cannot cover, the ROI's place on the sensor does. An object is inside the
fovea's *scan field* when, so steered, a ROI of the requested size centred on it fits on the
sensor.

Phases for an axis target come from the scan branch's solvers: first the paraxial (coarse)
inverse of section 2.3 (``scan.pointing.point_axis``), then the exact non-paraxial inverse
(``optics.inverse.exact_inverse``) started from it. The sub-pixel scan around the pointing is
``scan.plan_scan`` (method "exact").
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from hbis_torch.config import FoveaSystem
from hbis_torch.errors import HbisInputError, OutOfScanField
from hbis_torch.checks import check_roi
from hbis_torch.optics import sensor_position
from hbis_torch.optics.inverse import axis_landing, exact_inverse, max_landing_radius_mm
from hbis_torch.scan import plan_scan
from hbis_torch.scan.pointing import point_axis

#: Default phase-difference window (deg): keeps clear of phi1 = phi2 and of abs(phi1 - phi2) = 180.
PHASE_DIFFERENCE_DEG = (30.0, 150.0)
#: Azimuth (deg) used when an object sits right on the original axis: that of phases (5, 70).
DEFAULT_AZIMUTH_DEG = 37.5
#: Phases assumed when no current phases are given (the scan plans' default initial phases).
DEFAULT_INITIAL_PHASES_DEG = (5.0, 70.0)


def _wrap(angle_deg: float) -> float:
    """Angle wrapped into (-180, 180]."""
    return -((-angle_deg + 180.0) % 360.0 - 180.0)


def solve_axis_phases(system: FoveaSystem, target_mm, near_deg=None):
    """Phases that land the axis on ``target_mm`` (2,), nearest ``near_deg``.

    Returns (exact phases, coarse phases, residual mm) with the phases as float pairs.
    """
    target = torch.as_tensor(target_mm, dtype=torch.float64).reshape(1, 2)
    near = torch.as_tensor(DEFAULT_INITIAL_PHASES_DEG if near_deg is None else near_deg, dtype=torch.float64)
    radius = float(target.norm())
    if radius > max_landing_radius_mm(system):
        raise OutOfScanField(f"the axis cannot reach {radius:.3f} mm off centre "
                             f"(at most {max_landing_radius_mm(system):.3f} mm)")
    deviation = math.degrees(math.atan2(radius, system.object_distance_mm))
    azimuth = math.degrees(math.atan2(float(target[0, 1]), float(target[0, 0])))
    coarse = point_axis(system, deviation, azimuth, near, exact=False).phases_deg
    exact = exact_inverse(system, target, coarse[0])
    residual = float((axis_landing(system, exact[0, 0], exact[0, 1]) - target[0]).norm())
    return ((float(exact[0, 0]), float(exact[0, 1])), (float(coarse[0, 0]), float(coarse[0, 1])), residual)


def deviation_window_mm(system: FoveaSystem, phase_difference_deg=PHASE_DIFFERENCE_DEG) -> tuple[float, float]:
    """Smallest and largest axis offsets (mm on the plane) the phase-difference window allows."""
    lo, hi = sorted(phase_difference_deg)
    if not 0.0 <= lo < hi <= 180.0:
        raise HbisInputError(f"phase difference window must lie in [0, 180] deg, got {phase_difference_deg!r}")
    return (float(axis_landing(system, hi / 2, -hi / 2).norm()),
            float(axis_landing(system, lo / 2, -lo / 2).norm()))


@dataclass
class Pointing:
    """Where the fovea looks after steering.

    Attributes
    ----------
    phases_deg : (phi1, phi2), exact
    coarse_phases_deg : (phi1, phi2), the paraxial estimate the exact solver started from
    axis_mm : (x, y), where the axis lands on the plane
    object_mm : (x, y), the target
    object_px : (u, v), where the target is imaged on the full sensor at ``phases_deg``
    roi : (u0, v0, width, height), centred on ``object_px``
    residual_mm : float, how far the exact phases land the axis from its target
    """

    phases_deg: tuple[float, float]
    coarse_phases_deg: tuple[float, float]
    axis_mm: tuple[float, float]
    object_mm: tuple[float, float]
    object_px: tuple[float, float]
    roi: tuple[int, int, int, int]
    residual_mm: float


def steer(system: FoveaSystem, object_mm, roi_size: int | tuple[int, int] = 128, near_deg=None,
          phase_difference_deg=PHASE_DIFFERENCE_DEG) -> Pointing:
    """Point the fovea at ``object_mm`` (2,) and place a ROI of ``roi_size`` (w, h) around it.

    Raises OutOfScanField when the object is outside the scan field for this ROI size.
    """
    obj = torch.as_tensor(object_mm, dtype=torch.float64).reshape(-1)
    if obj.shape != (2,) or not torch.isfinite(obj).all():
        raise HbisInputError(f"object position must be two finite numbers (mm), got {object_mm!r}")
    w, h = (roi_size, roi_size) if isinstance(roi_size, int) else (int(roi_size[0]), int(roi_size[1]))
    cam = system.camera
    check_roi(cam, (0, 0, w, h))
    r_min, r_max = deviation_window_mm(system, phase_difference_deg)
    r = float(obj.norm())
    direction = obj / r if r > 1e-12 else torch.tensor(
        [math.cos(math.radians(DEFAULT_AZIMUTH_DEG)), math.sin(math.radians(DEFAULT_AZIMUTH_DEG))],
        dtype=torch.float64)
    axis = direction * min(max(r, r_min), r_max)
    phases, coarse, residual = solve_axis_phases(system, axis, near_deg)
    u, v = (float(c) for c in sensor_position(system, obj, *phases))
    # ROI pixel centres u0 .. u0 + w - 1 are centred on u when u0 = u - (w - 1) / 2.
    u0, v0 = round(u - (w - 1) / 2), round(v - (h - 1) / 2)
    if not (0 <= u0 <= cam.cols - w and 0 <= v0 <= cam.rows - h):
        raise OutOfScanField(
            f"object at ({float(obj[0]):.2f}, {float(obj[1]):.2f}) mm is outside the fovea's scan field "
            f"for a {w} x {h} ROI (it would be imaged at pixel ({u:.0f}, {v:.0f}))")
    return Pointing(phases, coarse, tuple(float(a) for a in axis_landing(system, *phases)),
                    (float(obj[0]), float(obj[1])), (u, v), (u0, v0, w, h), residual)


def in_scan_field(system: FoveaSystem, object_mm, roi_size=128, phase_difference_deg=PHASE_DIFFERENCE_DEG) -> bool:
    """Whether :func:`steer` can bring ``object_mm`` into a ROI of ``roi_size``."""
    try:
        steer(system, object_mm, roi_size, phase_difference_deg=phase_difference_deg)
    except OutOfScanField:
        return False
    return True


def parked_phases_near(phases_deg) -> tuple[float, float]:
    """The opposed phase pair (abs(phi1 - phi2) = 180: the axis undeviated) nearest ``phases_deg``:
    both prisms turn by the same amount in opposite directions."""
    p1, p2 = (float(p) for p in phases_deg)
    delta = _wrap(p1 - p2)
    turn = (180.0 - delta) / 2 if delta >= 0 else (-180.0 - delta) / 2
    return p1 + turn, p2 - turn


def slew_deg(start_deg, end_deg) -> float:
    """The larger of the two prisms' turns (deg, shortest way) between two phase pairs."""
    return max(abs(_wrap(float(e) - float(s))) for s, e in zip(start_deg, end_deg))


@dataclass
class ScanPoints:
    """The h x h sub-pixel scan around a pointing.

    Attributes
    ----------
    phases_deg : Tensor (h^2, 2) float64, in scan order
    reference_index : int, the frame taken at the pointing's own phases
    h : int
    source : str, which planner made it
    """

    phases_deg: Tensor
    reference_index: int
    h: int
    source: str


def plan_fovea_scan(system: FoveaSystem, h: int, pointing: Pointing) -> ScanPoints:
    """The h x h sub-pixel scan at the pointing's phases (``scan.plan_scan``, exact method)."""
    plan = plan_scan(system, h, initial_phases_deg=pointing.phases_deg, method="exact")
    return ScanPoints(torch.as_tensor(plan.phases_deg, dtype=torch.float64), int(plan.reference_index),
                      int(h), "hbis_torch.scan.plan_scan (exact)")
