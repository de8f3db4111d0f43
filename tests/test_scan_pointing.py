"""Coarse ROI pointing (section 2.3): paraxial, exact refinement, shortest rotation."""

import pytest
import torch

from hbis_torch.config import FoveaSystem
from hbis_torch.errors import HbisInputError
from hbis_torch.scan import point_axis, point_sequence

SYSTEM = FoveaSystem()


def test_paraxial_pointing_is_coarse_and_the_refinement_exact():
    dev, az = [0.5, 2.0, 3.5, 3.95], [10.0, 135.0, -100.0, 300.0]
    coarse = point_axis(SYSTEM, dev, az, (0.0, 90.0))
    fine = point_axis(SYSTEM, dev, az, (0.0, 90.0), exact=True)
    assert 1e-4 < float(coarse.miss_deg.max()) < 0.05  # first order: within 1 % of 4 deg
    assert float(fine.miss_deg.max()) < 1e-9
    # The refinement stays on the coarse answer's branch: a small correction only.
    assert float((fine.phases_deg - coarse.phases_deg).abs().max()) < 5.0


def test_pointing_at_the_centre_keeps_the_common_rotation():
    for exact in (False, True):
        p = point_axis(SYSTEM, [0.0], [123.0], (30.0, 190.0), exact=exact)
        assert p.phases_deg[0].tolist() == pytest.approx([20.0, 200.0], abs=1e-9)
        assert float(p.deviation_deg[0]) < 1e-9


def test_a_sweep_through_the_centre_turns_smoothly():
    """Pointing from azimuth 0 to 180 through the centre: no 180 degree jump anywhere."""
    dev = torch.cat((torch.linspace(1.0, 0.0, 21), torch.linspace(0.05, 1.0, 20))).double()
    az = torch.cat((torch.zeros(21), torch.full((20,), 180.0))).double()
    for exact in (False, True):
        path = point_sequence(SYSTEM, dev, az, (-70.0, 70.0), exact=exact)
        assert float(path.phases_deg.diff(dim=0).abs().max()) < 5.0
        assert float(path.miss_deg.max()) < (0.05 if not exact else 1e-9)


def test_shortest_rotation_between_targets_counts_whole_turns():
    # Targets walking round the azimuth: the prisms keep turning one way, never unwinding.
    az = torch.arange(0.0, 1080.0, 30.0, dtype=torch.float64)
    path = point_sequence(SYSTEM, torch.full_like(az, 2.0), az, (0.0, 120.0), exact=True)
    steps = path.phases_deg.diff(dim=0)
    assert float(steps.abs().max()) < 31.0
    assert float(path.phases_deg[-1].mean() - path.phases_deg[0].mean()) > 1000.0


def test_beyond_the_maximum_is_an_error_naming_it():
    with pytest.raises(HbisInputError, match=r"maximum deviation 4\.008"):
        point_axis(SYSTEM, [4.2], [0.0])
    with pytest.raises(HbisInputError, match="90"):
        point_axis(SYSTEM, [-1.0], [0.0])
    with pytest.raises(HbisInputError, match="non-finite"):
        point_axis(SYSTEM, [float("nan")], [0.0])
    with pytest.raises(HbisInputError, match="as many"):
        point_axis(SYSTEM, [1.0, 2.0], [0.0])
