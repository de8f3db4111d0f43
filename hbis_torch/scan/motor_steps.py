"""Stepping motors: phases quantised to whole steps, the alignment error that costs, and the
resolution (steps per degree of prism rotation) a scan needs.

A motor turns its prism by whole steps of 1 / steps_per_deg degrees (belt or gear ratio and
microstepping included). For a scan the motors start at the initial phases (the reference frame),
so each frame is reached by a whole number of steps from there: the quantisation grid is anchored
at the initial phases and the reference frame itself stays exact.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from hbis_torch.config import FoveaSystem
from hbis_torch.errors import HbisInputError
from hbis_torch.optics.inverse import axis_landing
from hbis_torch.scan.alignment import axis_alignment_error
from hbis_torch.checks import check_phase_pair, check_phases
from hbis_torch.scan.plan import ScanPlan, plan_scan


def _check_steps(steps_per_deg) -> tuple[float, float]:
    try:
        values = [float(s) for s in steps_per_deg]
    except (TypeError, ValueError):
        raise HbisInputError(f"steps per degree must be two numbers, got {steps_per_deg!r}")
    if len(values) != 2 or not all(math.isfinite(s) and s > 0 for s in values):
        raise HbisInputError(
            f"steps per degree must be two finite positive numbers (one per prism axis), "
            f"got {steps_per_deg!r}"
        )
    return values[0], values[1]


def phase_steps(phases_deg: Tensor, steps_per_deg, origin_deg=(0.0, 0.0)) -> Tensor:
    """Whole motor steps from ``origin_deg`` nearest each phase; (F, 2) int64."""
    p = check_phases(phases_deg)
    spd = torch.tensor(_check_steps(steps_per_deg), dtype=torch.float64)
    origin = torch.tensor(check_phase_pair(origin_deg), dtype=torch.float64)
    return torch.round((p - origin) * spd).to(torch.int64)


def quantise_phases(phases_deg: Tensor, steps_per_deg, origin_deg=(0.0, 0.0)) -> Tensor:
    """Phases rounded to the nearest whole motor step; (F, 2) float64 degrees.

    Parameters
    ----------
    phases_deg : Tensor, shape (F, 2)
        Wanted [phi1, phi2], degrees.
    steps_per_deg : (float, float)
        Motor steps per degree of rotation of prism 1 and prism 2.
    origin_deg : (float, float)
        Phases at step count zero (default 0, 0: an absolute step grid).
    """
    spd = torch.tensor(_check_steps(steps_per_deg), dtype=torch.float64)
    origin = torch.tensor(check_phase_pair(origin_deg), dtype=torch.float64)
    return origin + phase_steps(phases_deg, steps_per_deg, origin_deg).to(torch.float64) / spd


def step_alignment_error(system: FoveaSystem, plan: ScanPlan, steps_per_deg) -> dict:
    """Axis AE of a plan run on stepping motors (steps counted from the initial phases).

    Returns
    -------
    dict with ``ae_axis_max`` and ``ae_axis_mean`` (float, fractions of SL), ``ae_axis``
    (Tensor (F,)), ``quantised_phases_deg`` (Tensor (F, 2)), ``steps`` (Tensor (F, 2) int64,
    from the initial phases), ``steps_per_deg`` [s1, s2] and ``ae_axis_max_unquantised``.
    """
    spd = _check_steps(steps_per_deg)
    steps = phase_steps(plan.phases_deg, spd, plan.initial_phases_deg)
    quantised = quantise_phases(plan.phases_deg, spd, plan.initial_phases_deg)
    ae = axis_alignment_error(system, plan, quantised)
    return {
        "ae_axis_max": float(ae.max()),
        "ae_axis_mean": float(ae.mean()),
        "ae_axis": ae,
        "quantised_phases_deg": quantised,
        "steps": steps,
        "steps_per_deg": list(spd),
        "ae_axis_max_unquantised": float(axis_alignment_error(system, plan).max()),
    }


def landing_jacobian(system: FoveaSystem, phases_deg: Tensor, step_deg: float = 1e-5) -> Tensor:
    """d(axis landing)/d(phi1, phi2) by central differences; (F, 2, 2) in mm per degree.

    Column k is the landing's response to prism k.
    """
    p = check_phases(phases_deg)
    columns = []
    for k in range(2):
        dp = torch.zeros(2, dtype=torch.float64)
        dp[k] = step_deg
        plus, minus = p + dp, p - dp
        columns.append(
            (axis_landing(system, plus[:, 0], plus[:, 1])
             - axis_landing(system, minus[:, 0], minus[:, 1])) / (2 * step_deg)
        )
    return torch.stack(columns, dim=-1)


def required_steps_per_deg(
    system: FoveaSystem, h: int, initial_phases_deg, ae_bound: float, method: str = "exact"
) -> float:
    """Steps per degree (the same on both axes) that keep the axis AE at or under ``ae_bound``
    for every frame, whatever the rounding.

    Rounding moves each phase by at most half a step, 1 / (2 s) degrees, so the landing moves by
    at most max(abs(J1 + J2), abs(J1 - J2)) / (2 s) (J = :func:`landing_jacobian`; the worst corner of
    the rounding box; second-order terms are below 1e-9 SL at these step sizes). Added to the
    plan's own AE this must stay under the bound, frame by frame.

    Raises HbisInputError if the bound is not above the plan's own AE (no motor can help then).
    """
    bound = float(ae_bound)
    if not math.isfinite(bound) or bound <= 0:
        raise HbisInputError(f"AE bound must be a finite positive number, got {ae_bound!r}")
    plan = plan_scan(system, h, initial_phases_deg, method)
    own = axis_alignment_error(system, plan)
    headroom = bound - own
    if float(headroom.min()) <= 0:
        raise HbisInputError(
            f"the {method} plan's own axis AE {float(own.max()):.4g} already reaches the bound "
            f"{bound:g}; use a larger bound or the exact method"
        )
    jac = landing_jacobian(system, plan.phases_deg)
    worst_mm_per_deg = torch.maximum(
        (jac[..., 0] + jac[..., 1]).norm(dim=-1), (jac[..., 0] - jac[..., 1]).norm(dim=-1)
    )
    moved = plan.phases_deg != plan.phases_deg[plan.reference_index]
    need = worst_mm_per_deg / (2 * plan.step_mm * headroom)
    need = torch.where(moved.any(-1), need, torch.zeros_like(need))  # the reference is exact
    return float(need.max())
