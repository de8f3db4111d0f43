"""Inverse solutions of the Risley pair: the paper's closed form, the exact inverse, and every
singular case (aligned prisms, opposed prisms at the centre, the rim, rounding past +-1)."""

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from hbis_torch.config import Prisms, FoveaSystem
from hbis_torch.errors import HbisInputError
from hbis_torch.optics.inverse import (
    axis_landing,
    exact_inverse,
    max_deviation_deg,
    max_landing_radius_mm,
    paper_inverse,
    paper_norms,
    paraxial_inverse,
)

SYSTEM = FoveaSystem()
R_MAX = max_landing_radius_mm(SYSTEM)


def _lands(phases, targets, tol_mm):
    landing = axis_landing(SYSTEM, phases[:, 0], phases[:, 1])
    assert torch.isfinite(phases).all()
    assert float((landing - targets).norm(dim=-1).max()) < tol_mm


def _polar(radius, azimuth_deg):
    a = math.radians(azimuth_deg)
    return torch.tensor([[radius * math.cos(a), radius * math.sin(a)]], dtype=torch.float64)


def test_frame_sign_aligned_prisms_deviate_toward_their_phase():
    # DV = k1 e(phi1) + k2 e(phi2): the paper's eq. 5 with the sign flipped.
    xy = axis_landing(SYSTEM, 30.0, 30.0)
    assert math.degrees(math.atan2(xy[1], xy[0])) == pytest.approx(30.0, abs=1e-9)
    assert float(xy.norm()) == pytest.approx(R_MAX, rel=1e-12)


def test_eq8_case_1_reproduces_the_initial_point():
    k1, k2 = paper_norms(SYSTEM, (5.0, 70.0))
    e = lambda d: torch.tensor([math.cos(math.radians(d)), math.sin(math.radians(d))])  # noqa: E731
    dv0 = axis_landing(SYSTEM, 5.0, 70.0)
    assert torch.allclose(k1 * e(5.0) + k2 * e(70.0), dv0.float(), atol=1e-6)
    # The non-paraxial pair is not symmetric: the two norms differ slightly.
    assert k1 != pytest.approx(k2, rel=1e-4)
    assert k1 + k2 == pytest.approx(R_MAX, rel=5e-3)


def test_eq8_case_2_equal_phases():
    k1, k2 = paper_norms(SYSTEM, (40.0, 40.0))
    assert k1 == k2 == pytest.approx(R_MAX / 2, rel=1e-12)
    # With equal norms the closed form still inverts interior targets (no NaN, on target).
    target = _polar(1.0, 70.0)
    phases = paper_inverse(target, k1, k2, torch.tensor([40.0, 40.0]))
    e = torch.stack((torch.cos(torch.deg2rad(phases)), torch.sin(torch.deg2rad(phases))), -1)
    assert torch.allclose((k1 * e[:, 0] + k2 * e[:, 1]), target, atol=1e-12)


def test_eq8_opposed_prisms_have_no_deviation_and_equal_norms():
    # Tilted faces parallel: a glass slab, the axis goes straight (this face layout).
    assert float(axis_landing(SYSTEM, 20.0, 200.0).norm()) < 1e-12
    k1, k2 = paper_norms(SYSTEM, (20.0, 200.0))
    assert k1 == k2 == pytest.approx(R_MAX / 2)


@pytest.mark.parametrize("solver", ["paper", "exact"])
def test_centre_keeps_the_common_rotation_of_the_current_phases(solver):
    centre = torch.zeros(1, 2, dtype=torch.float64)

    def solve(current):
        current = torch.tensor(current, dtype=torch.float64)
        if solver == "exact":
            return exact_inverse(SYSTEM, centre, current)[0]
        k = R_MAX / 2
        return paper_inverse(centre, k, k, current)[0]

    # Already opposed: nothing moves.
    assert solve([10.0, 190.0]).tolist() == pytest.approx([10.0, 190.0], abs=1e-9)
    # 10 deg past opposed: each prism turns back 5 deg; the common rotation (105) is kept.
    assert solve([10.0, 200.0]).tolist() == pytest.approx([15.0, 195.0], abs=1e-9)
    out = solve([100.0, 120.0])
    assert float(out[1] - out[0]) == pytest.approx(180.0, abs=1e-9)
    assert float(out.mean()) == pytest.approx(110.0, abs=1e-9)  # no 180 deg jump


def test_passing_through_the_centre_needs_no_180_degree_jump():
    """Targets on a line through the centre, each solved from the last phases."""
    xs = torch.linspace(-0.05, 0.05, 101, dtype=torch.float64)  # includes x = 0 exactly
    current = torch.tensor([-60.0, 115.0], dtype=torch.float64)
    path = []
    for x in xs:
        target = torch.tensor([[float(x), 0.0]], dtype=torch.float64)
        current = exact_inverse(SYSTEM, target, current)[0]
        path.append(current)
    path = torch.stack(path)
    _lands(path, torch.stack((xs, torch.zeros_like(xs)), -1), 1e-10)
    # 0.05 mm is about 0.8 deg of relative angle: every step is a fraction of a degree.
    assert float(path.diff(dim=0).abs().max()) < 0.5


def test_rim_targets_merge_the_branches_and_still_land():
    for az in (0.0, 33.0, 250.0):
        for scale in (1.0, 1.0 + 1e-12, 1.0 - 1e-12, 1.0 - 1e-6):
            target = _polar(R_MAX * scale, az)
            phases = exact_inverse(SYSTEM, target, torch.tensor([az + 5.0, az - 7.0]))
            _lands(phases, target, 1e-9 * R_MAX)
            if scale >= 1.0:
                # On the rim the prisms are aligned toward the target.
                assert float(phases[0, 1] - phases[0, 0]) == pytest.approx(0.0, abs=1e-4)


def test_beyond_the_maximum_deviation_names_it():
    target = _polar(R_MAX * 1.001, 10.0)
    with pytest.raises(HbisInputError, match=r"maximum deviation 4\.008\d* deg"):
        exact_inverse(SYSTEM, target, (0.0, 0.0))
    with pytest.raises(HbisInputError, match=r"maximum deviation 4\.008\d* deg"):
        paraxial_inverse(SYSTEM.prisms, [4.1], [0.0], (0.0, 0.0))
    k1, k2 = paper_norms(SYSTEM, (5.0, 70.0))
    with pytest.raises(HbisInputError, match="k1 \\+ k2"):
        paper_inverse(_polar((k1 + k2) * 1.01, 0.0), k1, k2, (5.0, 70.0))


def test_arccos_arguments_pushed_past_one_by_rounding_are_clamped():
    k1, k2 = 1.7, 1.3
    for radius in ((k1 + k2) * (1 + 1e-15), (k1 - k2) * (1 - 1e-15), (k1 + k2), (k1 - k2)):
        target = _polar(radius, 123.0)
        phases = paper_inverse(target, k1, k2, torch.tensor([100.0, 140.0]))
        assert torch.isfinite(phases).all()
        e = torch.stack((torch.cos(torch.deg2rad(phases)), torch.sin(torch.deg2rad(phases))), -1)
        assert torch.allclose(k1 * e[:, 0] + k2 * e[:, 1], target, atol=1e-7)
    # Inside the model's inner hole |k1 - k2|: a clear error, not NaN.
    with pytest.raises(HbisInputError, match="hole"):
        paper_inverse(_polar(0.1, 0.0), k1, k2, (0.0, 0.0))


def test_paraxial_pointing_between_first_order_and_exact_maximum_is_clamped():
    first_order = 2 * (1.5 - 1) * 4.0
    phases = paraxial_inverse(SYSTEM.prisms, [first_order + 0.005], [45.0], (0.0, 0.0))
    assert torch.isfinite(phases).all()
    assert phases[0].tolist() == pytest.approx([45.0, 45.0], abs=1e-9)
    assert max_deviation_deg(SYSTEM.prisms) > first_order + 0.005


def test_nearest_branch_is_chosen():
    target = _polar(2.0, 60.0)
    a = exact_inverse(SYSTEM, target, torch.tensor([0.0, 120.0]))
    b = exact_inverse(SYSTEM, target, torch.tensor([120.0, 0.0]))
    _lands(a, target, 1e-10)
    _lands(b, target, 1e-10)
    assert float(a[0, 1] - a[0, 0]) > 0 > float(b[0, 1] - b[0, 0])
    # Each phase within half a turn of the current one (shortest rotation).
    far = exact_inverse(SYSTEM, target, torch.tensor([720.0, 840.0]))
    assert far[0].tolist() == pytest.approx((a[0] + 720.0).tolist(), abs=1e-9)


@settings(max_examples=40, deadline=None)
@given(
    radius=st.floats(0.0, 1.0),
    azimuth=st.floats(-720.0, 720.0),
    current=st.tuples(st.floats(-400.0, 400.0), st.floats(-400.0, 400.0)),
)
def test_exact_inverse_lands_anywhere_in_the_disc(radius, azimuth, current):
    target = _polar(R_MAX * radius, azimuth)
    phases = exact_inverse(SYSTEM, target, torch.tensor(current, dtype=torch.float64))
    _lands(phases, target, 1e-10)
    assert float((phases[0] - torch.tensor(current)).abs().max()) <= 180.0 + 1e-9


@pytest.mark.parametrize("alpha,n", [(1.0, 1.3), (10.0, 1.5), (4.0, 2.0), (15.0, 1.8)])
def test_exact_inverse_for_other_prisms(alpha, n):
    system = FoveaSystem(prisms=Prisms(wedge_angle_deg=alpha, refractive_index=n))
    r_max = max_landing_radius_mm(system)
    targets = torch.stack(
        [_polar(r_max * f, az)[0] for f, az in [(0.0, 0), (0.3, 10), (0.9, 200), (1.0, 300)]]
    )
    phases = exact_inverse(system, targets, (0.0, 0.0))
    landing = axis_landing(system, phases[:, 0], phases[:, 1])
    assert float((landing - targets).norm(dim=-1).max()) < 1e-10 * r_max


@pytest.mark.parametrize(
    "targets,match",
    [
        (torch.tensor([[float("nan"), 0.0]]), "non-finite"),
        (torch.zeros(3), "shape"),
        (torch.zeros(0, 2), "no targets"),
    ],
)
def test_bad_targets(targets, match):
    with pytest.raises(HbisInputError, match=match):
        exact_inverse(SYSTEM, targets, (0.0, 0.0))


def test_bad_current_phases():
    with pytest.raises(HbisInputError, match="current phases"):
        exact_inverse(SYSTEM, torch.zeros(2, 2), torch.zeros(3, 2))
    with pytest.raises(HbisInputError, match="non-finite"):
        exact_inverse(SYSTEM, torch.zeros(1, 2), (float("inf"), 0.0))
