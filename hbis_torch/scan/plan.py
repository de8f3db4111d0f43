"""Sub-pixel scan plans (paper section 2.2, Fig. 3, eq. 7).

A scan of resolution improvement factor h moves the optical axis over an h x h grid of points
spaced by the step SL = (p / h) v / f' on the object plane, around the point DV^0 where the axis
lands at the initial phases (traced exactly, as the sentence after eq. 7 says).

Scan order (eq. 7 with 0-based frame index i): raster, row by row, x fastest,

    offset_i = (i mod h - floor(h/2), floor(i / h) - floor(h/2))     in units of SL,

so x and y both run from -floor(h/2) to h - 1 - floor(h/2). For odd h the initial point is the
centre of the grid; for even h it is the point just past the centre (Fig. 3b), offsets -h/2 ..
h/2 - 1. The frame at the initial phases has index floor(h/2) (h + 1). (Eq. 7 as printed
subtracts (h+1)/2 with 1-based i, which does not give DV^13 = DV^0 for h = 5; the form above
does, and matches the figure.)

The alignment error of a plan is in :mod:`hbis_torch.scan.alignment`.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from hbis_torch.config import FoveaSystem
from hbis_torch.checks import check_h, check_phase_pair
from hbis_torch.errors import HbisInputError
from hbis_torch.optics.inverse import axis_landing, exact_inverse, paper_inverse, paper_norms

METHODS = ("paper", "exact")


@dataclass
class ScanPlan:
    """A sub-pixel scan: where the axis should land, and the prism phases that put it there.

    Attributes
    ----------
    h : int
        Resolution improvement factor; the plan has F = h * h frames.
    initial_phases_deg : (float, float)
        Phases at which the reference frame is taken.
    step_mm : float
        SL, the step on the object plane, (p / h) v / f' in mm.
    offsets : Tensor, shape (F, 2), float64
        Target offsets of the axis in units of SL, (x, y), scan order.
    targets_mm : Tensor, shape (F, 2), float64
        Axis landing targets on the object plane, mm: DV^0 + SL * offsets.
    phases_deg : Tensor, shape (F, 2), float64
        [phi1, phi2] per frame, degrees, scan order, each within 180 deg of its initial value.
    reference_index : int
        Index of the frame at the initial phases (offset (0, 0)).
    method : str
        "paper" (eqs. 8-9) or "exact" (non-paraxial inverse).
    """

    h: int
    initial_phases_deg: tuple[float, float]
    step_mm: float
    offsets: Tensor
    targets_mm: Tensor
    phases_deg: Tensor
    reference_index: int
    method: str

    @property
    def frames(self) -> int:
        return self.offsets.shape[0]

    def phase_range_deg(self) -> Tensor:
        """Range (max - min) of each prism's phase over the scan, shape (2,), degrees."""
        return phase_range_deg(self.phases_deg)


def step_mm(system: FoveaSystem, h: int) -> float:
    """SL = (p / h) v / f', the scan step on the object plane, mm."""
    return system.object_pixel_mm / check_h(h)


def scan_offsets(h: int) -> tuple[Tensor, int]:
    """Eq. 7 offsets in units of SL, shape (h*h, 2) float64 in scan order, and the reference index."""
    h = check_h(h)
    i = torch.arange(h * h)
    centre = h // 2
    offsets = torch.stack((i % h - centre, i // h - centre), -1).to(torch.float64)
    return offsets, centre * h + centre


def phase_range_deg(phases_deg: Tensor) -> Tensor:
    """Range (max - min) of each column of (F, 2) phases, degrees."""
    return phases_deg.max(0).values - phases_deg.min(0).values


def plan_scan(
    system: FoveaSystem, h: int, initial_phases_deg=(5.0, 70.0), method: str = "exact"
) -> ScanPlan:
    """The h x h sub-pixel scan around the initial phases, and the phases of every frame.

    Parameters
    ----------
    system : FoveaSystem
        Camera, prisms and object distance.
    h : int
        Resolution improvement factor (>= 1), odd or even.
    initial_phases_deg : (float, float)
        [phi1, phi2] of the reference frame, degrees.
    method : {"exact", "paper"}
        "exact": the non-paraxial inverse, axis on target to rounding. "paper": eqs. 8-9.

    Returns
    -------
    ScanPlan

    Examples
    --------
    A 4 x 4 scan from the default initial phases; the reference frame keeps them:

    >>> from hbis_torch import FoveaSystem
    >>> from hbis_torch.scan.plan import plan_scan
    >>> system = FoveaSystem()
    >>> plan = plan_scan(system, 4)
    >>> plan.frames, plan.reference_index, tuple(plan.phases_deg.shape)
    (16, 10, (16, 2))
    >>> plan.phases_deg[plan.reference_index].tolist()
    [5.0, 70.0]
    >>> plan.step_mm == system.object_pixel_mm / 4
    True

    The exact inverse puts the axis on every target to rounding (error in units of SL):

    >>> from hbis_torch.optics.inverse import axis_landing
    >>> landed = axis_landing(system, plan.phases_deg[:, 0], plan.phases_deg[:, 1])
    >>> float((landed - plan.targets_mm).norm(dim=-1).max() / plan.step_mm) < 1e-9
    True
    """
    h = check_h(h)
    if method not in METHODS:
        raise HbisInputError(f"method must be one of {', '.join(METHODS)}, got {method!r}")
    initial = check_phase_pair(initial_phases_deg)
    sl = step_mm(system, h)
    offsets, reference = scan_offsets(h)
    dv0 = axis_landing(system, initial[0], initial[1])
    targets = dv0 + sl * offsets
    current = torch.tensor(initial, dtype=torch.float64)
    if method == "exact":
        phases = exact_inverse(system, targets, current)
    else:
        k1, k2 = paper_norms(system, initial)
        phases = paper_inverse(targets, k1, k2, current)
    # The reference frame is taken at the initial phases themselves, not at a re-solved copy.
    phases[reference] = current
    return ScanPlan(h, initial, sl, offsets, targets, phases, reference, method)
