"""The design calculator against the paper's numbers (angles +-0.2 deg, ratios +-0.05)."""

import math

import pytest
from scipy.optimize import brentq

from hbis_torch import FoveaSystem
from hbis_torch.design import design, limit_sweep, phi_min_deg, with_prisms

ANGLE, RATIO = 0.2, 0.05


def test_table1_limits_and_fer_match_fig_10a():
    r = design()
    assert r.single_fov_h_deg == pytest.approx(22.6, abs=0.05)
    assert r.single_fov_v_deg == pytest.approx(17.1, abs=0.05)
    assert r.varphi_h_max_deg == pytest.approx(18.4, abs=ANGLE)
    assert r.varphi_v_max_deg == pytest.approx(12.9, abs=ANGLE)
    assert r.fer_h == pytest.approx(2.6, abs=RATIO)
    assert r.fer_v == pytest.approx(2.5, abs=RATIO)
    assert not r.inflection_h and not r.inflection_v


def test_prototype_numbers():
    r = design(varphi_h_deg=15.0, varphi_v_deg=10.0)
    assert r.varphi_c_deg == pytest.approx(17.8, abs=ANGLE)
    assert r.fer_h == pytest.approx(2.3, abs=RATIO)
    assert r.fer_v == pytest.approx(2.2, abs=RATIO)
    assert not r.blind_zone_h and not r.blind_zone_v
    assert design(varphi_h_deg=19.0).blind_zone_h


def test_small_wedge_gives_the_largest_extension():
    r = design(with_prisms(FoveaSystem(), wedge_angle_deg=1.0))
    assert r.fer_h == pytest.approx(2.9, abs=RATIO)
    assert r.fer_v == pytest.approx(2.88, abs=RATIO)


def _first_fer_two(parameter, values, direction):
    sweep = limit_sweep(FoveaSystem(), parameter, values)
    return next(v for v, fer in zip(values, sweep[f"fer_{direction}"]) if fer <= 2.0 + 1e-9)


def test_inflection_points_on_the_papers_sweep_grid():
    """On an integer wedge-angle grid and a 0.2-step index grid (as a figure sweep would use),
    the first point with FER = 2 is the paper's 11 / 9 deg and 2.4 / 2.2."""
    alphas = [float(a) for a in range(1, 16)]
    assert _first_fer_two("wedge_angle_deg", alphas, "h") == 11.0
    assert _first_fer_two("wedge_angle_deg", alphas, "v") == 9.0
    indices = [round(1.4 + 0.2 * i, 1) for i in range(9)]
    assert _first_fer_two("refractive_index", indices, "h") == 2.4
    assert _first_fer_two("refractive_index", indices, "v") == 2.2


def test_exact_inflections_and_fer_two_after_them():
    """Located by a root-find on Phi_min = 0, the crossings are 10.93 / 8.18 deg and n = 2.38 / 2.03."""
    system = FoveaSystem()

    def crossing(parameter, lo, hi, direction):
        return brentq(lambda x: phi_min_deg(with_prisms(system, **{parameter: x}), direction), lo, hi,
                      xtol=1e-6)

    assert crossing("wedge_angle_deg", 1.0, 20.0, "h") == pytest.approx(10.93, abs=0.01)
    assert crossing("wedge_angle_deg", 1.0, 20.0, "v") == pytest.approx(8.18, abs=0.01)
    assert crossing("refractive_index", 1.3, 3.0, "h") == pytest.approx(2.38, abs=0.01)
    assert crossing("refractive_index", 1.3, 3.0, "v") == pytest.approx(2.03, abs=0.01)
    sweep = limit_sweep(system, "wedge_angle_deg", [12.0, 20.0])
    assert sweep["fer_h"] == pytest.approx([2.0, 2.0]) and sweep["fer_v"] == pytest.approx([2.0, 2.0])


def test_diffraction_ratio_allows_h_up_to_7():
    r = design()
    assert 7 <= r.diffraction_ratio < 8 and r.h_max == 7


def test_bsr_over_80_percent_at_h7_and_grows_3_7_points_from_h4():
    r = design()
    assert r.bsr["7"] > 0.80
    assert r.bsr["7"] - r.bsr["4"] == pytest.approx(0.037, abs=0.005)
    assert r.bsr["1"] == 0.0
    fer = r.fer_h * r.fer_v
    assert r.bsr["4"] == pytest.approx((1 - 1 / 16) * (1 - 1 / fer))


def test_varphi_c_formula():
    r = design(varphi_h_deg=20.0, varphi_v_deg=0.0)
    assert r.varphi_c_deg == pytest.approx(20.0)
    r = design(varphi_h_deg=10.0, varphi_v_deg=10.0)
    t = math.tan(math.radians(10.0))
    assert r.varphi_c_deg == pytest.approx(math.degrees(math.atan(math.sqrt(2) * t)))
