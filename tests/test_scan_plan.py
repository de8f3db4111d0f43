"""Scan plans: eq. 7 offsets, the reference frame, and the exact inverse landing on target."""

import pytest
import torch

from hbis_torch.config import Prisms, FoveaSystem
from hbis_torch.errors import HbisInputError
from hbis_torch.scan import axis_alignment_error, plan_scan, scan_offsets, step_mm

SYSTEM = FoveaSystem()


@pytest.mark.parametrize("h", [1, 2, 3, 4, 5, 7, 8])
def test_offsets_cover_a_full_grid_with_the_reference_at_zero(h):
    offsets, ref = scan_offsets(h)
    assert offsets.shape == (h * h, 2) and offsets.dtype == torch.float64
    assert offsets[ref].tolist() == [0.0, 0.0]
    # Every (x, y) of the h x h grid appears once, in raster order with x fastest.
    assert len({tuple(o) for o in offsets.tolist()}) == h * h
    assert offsets[:, 0].min() == -(h // 2) and offsets[:, 0].max() == h - 1 - h // 2
    if h > 1:
        assert offsets[1, 0] - offsets[0, 0] == 1 and offsets[1, 1] == offsets[0, 1]
        assert offsets[h, 1] - offsets[0, 1] == 1


def test_paper_figure_3_examples():
    # h = 5 (odd): the initial point is the 13th of 25 (1-based), the centre of the grid.
    offsets, ref = scan_offsets(5)
    assert ref == 12 and offsets[0].tolist() == [-2.0, -2.0]
    # h = 4 (even): offsets run -2 .. 1, the initial point is just past the centre.
    offsets, ref = scan_offsets(4)
    assert ref == 10 and offsets[0].tolist() == [-2.0, -2.0] and offsets[-1].tolist() == [1.0, 1.0]


def test_step_is_pixel_over_h_on_the_object_plane():
    assert step_mm(SYSTEM, 7) == pytest.approx(3.75e-3 / 7 * 50 / 12, rel=1e-12)


@pytest.mark.parametrize("h", [2, 4, 7])
@pytest.mark.parametrize("initial", [(5.0, 70.0), (45.0, 130.0), (80.0, 20.0), (300.0, 10.0)])
def test_exact_plan_lands_the_axis_within_1e_6_of_the_step(h, initial):
    plan = plan_scan(SYSTEM, h, initial, method="exact")
    ae = axis_alignment_error(SYSTEM, plan)
    assert ae.shape == (h * h,)
    assert float(ae.max()) < 1e-6
    assert plan.phases_deg[plan.reference_index].tolist() == list(initial)
    # Sub-pixel scans need only small rotations near the initial phases.
    assert float((plan.phases_deg - torch.tensor(initial)).abs().max()) < 1.0


def test_exact_plan_over_the_paper_ranges_of_figure_5():
    """Fig. 5 ranges: phi2 all round, wedge angle 1-10 deg, index 1.3-2.0 (h = 7)."""
    worst = 0.0
    # Aligned prisms (phi2 near phi1 = 5) put the axis on the rim: the scan would leave the disc.
    for phi2 in range(25, 360, 20):
        plan = plan_scan(SYSTEM, 7, (5.0, float(phi2) + 0.5))
        worst = max(worst, float(axis_alignment_error(SYSTEM, plan).max()))
    for alpha, n in [(1.0, 1.5), (10.0, 1.5), (4.0, 1.3), (4.0, 2.0)]:
        system = FoveaSystem(prisms=Prisms(wedge_angle_deg=alpha, refractive_index=n))
        plan = plan_scan(system, 7, (45.0, 130.0))
        worst = max(worst, float(axis_alignment_error(system, plan).max()))
    assert worst < 1e-6


def test_paper_plan_is_close_but_not_exact():
    plan = plan_scan(SYSTEM, 7, (5.0, 70.0), method="paper")
    ae = axis_alignment_error(SYSTEM, plan)
    assert 1e-3 < float(ae.max()) < 0.02


@pytest.mark.parametrize("bad", [0, -1, 2.5, "7", True])
def test_bad_h_is_rejected(bad):
    with pytest.raises(HbisInputError, match="h must be"):
        plan_scan(SYSTEM, bad)


def test_bad_method_and_phases_are_rejected():
    with pytest.raises(HbisInputError, match="method"):
        plan_scan(SYSTEM, 3, method="newton")
    with pytest.raises(HbisInputError, match="phases"):
        plan_scan(SYSTEM, 3, (float("nan"), 3.0))
    with pytest.raises(HbisInputError, match="phases"):
        plan_scan(SYSTEM, 3, (1.0, 2.0, 3.0))


@pytest.mark.parametrize("method", ["exact", "paper"])
def test_plan_at_opposed_prisms_scans_round_the_centre_without_nan(method):
    """Initial phases 180 deg apart put the axis at the centre, where the azimuth is undefined:
    the scan's targets surround it, so the phases swing widely (the paper's control
    singularity), but every number is finite and the exact plan still lands on target."""
    plan = plan_scan(SYSTEM, 3, (0.0, 180.0), method=method)
    assert torch.isfinite(plan.phases_deg).all()
    assert float(plan.targets_mm[plan.reference_index].norm()) < 1e-12
    ae = axis_alignment_error(SYSTEM, plan)
    assert torch.isfinite(ae).all()
    if method == "exact":
        assert float(ae.max()) < 1e-6
    assert float(plan.phase_range_deg().max()) > 30.0
