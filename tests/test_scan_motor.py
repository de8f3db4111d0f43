"""Motor steps: quantised phases, the alignment error they cause, the steps/deg a scan needs."""

import itertools

import pytest
import torch

from hbis_torch.config import FoveaSystem
from hbis_torch.errors import HbisInputError
from hbis_torch.scan import (
    axis_alignment_error,
    landing_jacobian,
    phase_steps,
    plan_scan,
    quantise_phases,
    required_steps_per_deg,
    step_alignment_error,
)

SYSTEM = FoveaSystem()


def test_quantise_rounds_to_whole_steps_per_axis():
    phases = torch.tensor([[0.26, 10.04], [-0.26, 9.96]], dtype=torch.float64)
    q = quantise_phases(phases, (2.0, 10.0))
    assert torch.allclose(q, torch.tensor([[0.5, 10.0], [-0.5, 10.0]], dtype=torch.float64))
    q = quantise_phases(phases, (2.0, 10.0), origin_deg=(0.1, 0.02))
    assert torch.allclose(q, torch.tensor([[0.1, 10.02], [-0.4, 9.92]], dtype=torch.float64))
    assert phase_steps(phases, (2.0, 10.0)).tolist() == [[1, 100], [-1, 100]]


def test_step_error_shrinks_to_the_plan_error_with_fine_steps():
    plan = plan_scan(SYSTEM, 4, (45.0, 130.0))
    coarse = step_alignment_error(SYSTEM, plan, (50.0, 50.0))
    fine = step_alignment_error(SYSTEM, plan, (1e6, 1e6))
    assert coarse["ae_axis_max"] > 0.05
    assert fine["ae_axis_max"] < 1e-3
    # The reference frame is reached with zero steps and stays exact.
    assert coarse["steps"][plan.reference_index].tolist() == [0, 0]
    assert float(coarse["ae_axis"][plan.reference_index]) < 1e-9
    assert torch.equal(coarse["ae_axis"], axis_alignment_error(SYSTEM, plan, coarse["quantised_phases_deg"]))


def test_jacobian_matches_the_paper_norms_in_size():
    plan = plan_scan(SYSTEM, 3, (5.0, 70.0))
    jac = landing_jacobian(SYSTEM, plan.phases_deg)  # mm per degree
    per_prism = jac.norm(dim=-2)
    # Each prism swings the landing by about k = r_max / 2 per radian.
    assert torch.allclose(per_prism, torch.full_like(per_prism, 3.5035 / 2 * torch.pi / 180), rtol=0.02)


@pytest.mark.parametrize("bound", [0.05, 0.2])
def test_required_steps_keep_the_bound_for_any_rounding(bound):
    h, initial = 7, (5.0, 70.0)
    s = required_steps_per_deg(SYSTEM, h, initial, bound)
    plan = plan_scan(SYSTEM, h, initial)
    # Worst case: every corner of the half-step rounding box, at every frame.
    worst = 0.0
    for signs in itertools.product((-1.0, 1.0), repeat=2):
        shifted = plan.phases_deg + torch.tensor(signs, dtype=torch.float64) / (2 * s)
        shifted[plan.reference_index] = plan.phases_deg[plan.reference_index]
        worst = max(worst, float(axis_alignment_error(SYSTEM, plan, shifted).max()))
    assert worst <= bound * (1 + 1e-6)
    assert worst > 0.9 * bound  # and it is not much more than needed
    assert step_alignment_error(SYSTEM, plan, (s, s))["ae_axis_max"] <= bound * (1 + 1e-6)


def test_required_steps_scale_with_h():
    s4 = required_steps_per_deg(SYSTEM, 4, (45.0, 130.0), 0.1)
    s8 = required_steps_per_deg(SYSTEM, 8, (45.0, 130.0), 0.1)
    assert s8 == pytest.approx(2 * s4, rel=0.02)  # half the step, twice the resolution


def test_bound_below_the_paper_plans_own_error_is_refused():
    with pytest.raises(HbisInputError, match="already reaches the bound"):
        required_steps_per_deg(SYSTEM, 7, (5.0, 70.0), 0.001, method="paper")
    with pytest.raises(HbisInputError, match="bound"):
        required_steps_per_deg(SYSTEM, 7, (5.0, 70.0), float("nan"))


@pytest.mark.parametrize("steps", [(0.0, 1.0), (1.0,), ("a", 1.0), (float("inf"), 2.0)])
def test_bad_steps_per_deg(steps):
    with pytest.raises(HbisInputError, match="steps per degree"):
        quantise_phases(torch.zeros(2, 2), steps)
