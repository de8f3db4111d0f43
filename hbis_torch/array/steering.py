"""Steering the fovea onto an object: prism phases, the ROI around the object, the scan field.

The policy: the fovea's axis is deviated toward the object, as far as needed to centre it but
no further than the phase difference window ``phase_difference_deg`` allows (near 0 deg the
pair cannot make the sub-pixel pattern, near 180 deg it is singular: the paper's section 3.2);
whatever the axis cannot cover, the ROI's place on the sensor does. An object is inside the
fovea's *scan field* when, so steered, a ROI of the requested size centred on it fits on the
sensor.

Phases for an axis target come first from the first-order model (eqs. 5-9: the axis lands at
k (e(phi1) + e(phi2)), k = half the largest deviation on the plane), then from Newton's method
on the exact tracer. NOTE for the lead: the coarse and exact inverses and the sub-pixel scan
plan below are stand-ins, used only because the scan branch's pointing / ``plan_scan`` API was
not there when this was written; :func:`plan_fovea_scan` already prefers ``hbis_torch.scan``
when it is importable. Swap ``_axis_phases`` for the scan helper's inverse when it lands.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from ..config import System
from ..errors import HbisInputError
from ..optics import check_roi, exit_directions, land_on_plane, sensor_position

#: Default phase-difference window (deg): keeps clear of phi1 = phi2 and of |phi1 - phi2| = 180.
PHASE_DIFFERENCE_DEG = (30.0, 150.0)
#: Azimuth (deg) used when an object sits right on the original axis: that of phases (5, 70).
DEFAULT_AZIMUTH_DEG = 37.5


class OutOfScanField(HbisInputError):
    """The object cannot be brought into a ROI of the requested size."""


def axis_landing(system: System, phi1_deg, phi2_deg) -> Tensor:
    """Where the fovea's optical axis meets the object plane, (..., 2) mm (exact trace)."""
    axis = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    return land_on_plane(exit_directions(axis, phi1_deg, phi2_deg, system.prisms), system.object_distance_mm)


def _wrap(angle_deg: float) -> float:
    """Angle wrapped into (-180, 180]."""
    return -((-angle_deg + 180.0) % 360.0 - 180.0)


def coarse_phases(system: System, target_mm, near_deg=None) -> tuple[float, float]:
    """First-order phases that put the axis on ``target_mm`` (2,), nearest to ``near_deg``."""
    x, y = (float(v) for v in target_mm)
    k = float(axis_landing(system, 0.0, 0.0).norm()) / 2.0
    r = math.hypot(x, y)
    if r > 2 * k:
        raise OutOfScanField(f"the axis cannot reach {r:.3f} mm off centre (at most {2 * k:.3f} mm)")
    azimuth = math.degrees(math.atan2(y, x)) if r > 0 else DEFAULT_AZIMUTH_DEG
    half = math.degrees(math.acos(min(1.0, r / (2 * k))))
    candidates = [(azimuth + half, azimuth - half), (azimuth - half, azimuth + half)]
    if near_deg is None:
        return candidates[0]
    return min(candidates, key=lambda c: abs(_wrap(c[0] - near_deg[0])) + abs(_wrap(c[1] - near_deg[1])))


def _axis_phases(system: System, target_mm, near_deg=None, tol_mm: float = 1e-10,
                 max_iter: int = 20) -> tuple[Tensor, Tensor, float, int]:
    """Stand-in exact inverse: coarse phases, then Newton on the exact axis landing.

    ``target_mm`` is (2,) or (N, 2); all targets are solved together (Jacobians by central
    differences, batched). Returns (phases (N, 2), coarse phases (N, 2), largest residual mm,
    iterations), float64.
    """
    target = torch.as_tensor(target_mm, dtype=torch.float64).reshape(-1, 2)
    coarse, near = [], near_deg
    for point in target:
        coarse.append(coarse_phases(system, point, near))
        near = coarse[-1]
    coarse = torch.tensor(coarse, dtype=torch.float64)
    phases = coarse.clone()
    eps = 1e-5  # deg; the landing is smooth, central differences are good to ~1e-10 relative

    def landing(p: Tensor) -> Tensor:
        return axis_landing(system, p[..., 0], p[..., 1])

    residual = landing(phases) - target
    iterations = 0
    while float(residual.norm(dim=-1).max()) > tol_mm and iterations < max_iter:
        steps = torch.tensor([[eps, 0.0], [0.0, eps]], dtype=torch.float64)
        plus = landing(phases[:, None, :] + steps)  # (N, 2 params, 2 coords)
        minus = landing(phases[:, None, :] - steps)
        jac = ((plus - minus) / (2 * eps)).transpose(1, 2)  # (N, coords, params)
        phases = phases - torch.linalg.solve(jac, residual[..., None])[..., 0]
        residual = landing(phases) - target
        iterations += 1
    worst = float(residual.norm(dim=-1).max())
    if worst > 1e-6:
        raise OutOfScanField(f"Newton did not converge onto the axis target (residual {worst:.2e} mm)")
    return phases, coarse, worst, iterations


def deviation_window_mm(system: System, phase_difference_deg=PHASE_DIFFERENCE_DEG) -> tuple[float, float]:
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
    coarse_phases_deg : (phi1, phi2), the first-order estimate the solver started from
    axis_mm : (x, y), where the axis lands on the plane
    object_mm : (x, y), the target
    object_px : (u, v), where the target is imaged on the full sensor at ``phases_deg``
    roi : (u0, v0, width, height), centred on ``object_px``
    residual_mm : float, the solver's axis residual
    iterations : int, Newton steps
    """

    phases_deg: tuple[float, float]
    coarse_phases_deg: tuple[float, float]
    axis_mm: tuple[float, float]
    object_mm: tuple[float, float]
    object_px: tuple[float, float]
    roi: tuple[int, int, int, int]
    residual_mm: float
    iterations: int


def steer(system: System, object_mm, roi_size: int | tuple[int, int] = 128, near_deg=None,
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
    solved, coarse, residual, iterations = _axis_phases(system, axis, near_deg)
    phases = (float(solved[0, 0]), float(solved[0, 1]))
    coarse = (float(coarse[0, 0]), float(coarse[0, 1]))
    u, v = (float(c) for c in sensor_position(system, obj, *phases))
    # ROI pixel centres u0 .. u0 + w - 1 are centred on u when u0 = u - (w - 1) / 2.
    u0, v0 = round(u - (w - 1) / 2), round(v - (h - 1) / 2)
    if not (0 <= u0 <= cam.cols - w and 0 <= v0 <= cam.rows - h):
        raise OutOfScanField(
            f"object at ({float(obj[0]):.2f}, {float(obj[1]):.2f}) mm is outside the fovea's scan field "
            f"for a {w} x {h} ROI (it would be imaged at pixel ({u:.0f}, {v:.0f}))")
    return Pointing(phases, coarse, tuple(float(a) for a in axis_landing(system, *phases)),
                    (float(obj[0]), float(obj[1])), (u, v), (u0, v0, w, h), residual, iterations)


def in_scan_field(system: System, object_mm, roi_size=128, phase_difference_deg=PHASE_DIFFERENCE_DEG) -> bool:
    """Whether :func:`steer` can bring ``object_mm`` into a ROI of ``roi_size``."""
    try:
        steer(system, object_mm, roi_size, phase_difference_deg=phase_difference_deg)
    except OutOfScanField:
        return False
    return True


def parked_phases_near(phases_deg) -> tuple[float, float]:
    """The opposed phase pair (|phi1 - phi2| = 180: the axis undeviated) nearest ``phases_deg``:
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
    source : str, which planner made it ('hbis_torch.scan' or the stand-in)
    """

    phases_deg: Tensor
    reference_index: int
    h: int
    source: str


def plan_fovea_scan(system: System, h: int, pointing: Pointing) -> ScanPoints:
    """The sub-pixel scan at the pointing's phases: the scan helper's ``plan_scan`` when
    available, else a stand-in that solves eq. 7's grid of axis targets with :func:`_axis_phases`."""
    if int(h) != h or h < 1:
        raise HbisInputError(f"h must be a positive integer, got {h!r}")
    try:
        from ..scan import plan_scan  # the scan helper's planner (branch `scan`)
    except ImportError:
        plan_scan = None
    if plan_scan is not None:
        plan = plan_scan(system, h, initial_phases_deg=pointing.phases_deg, method="exact")
        return ScanPoints(torch.as_tensor(plan.phases_deg, dtype=torch.float64),
                          int(plan.reference_index), int(h), "hbis_torch.scan.plan_scan")
    step = system.object_pixel_mm / h  # SL = (p / h) v / f'
    centre = (h - 1) // 2 if h % 2 else h // 2
    index = torch.arange(h * h)
    offsets = torch.stack((index % h - centre, index // h - centre), dim=-1).to(torch.float64)
    axis = torch.tensor(pointing.axis_mm, dtype=torch.float64)
    phases, _, _, _ = _axis_phases(system, axis + step * offsets, pointing.phases_deg)
    reference = centre * h + centre
    phases[reference] = torch.tensor(pointing.phases_deg, dtype=torch.float64)
    return ScanPoints(phases, reference, int(h), "stand-in (eq. 7 + Newton)")
