"""Scan figures (Fig. 3, Fig. 5 and the pixel AE map): they draw, and their data are right."""

import pytest

from hbis_torch.config import FoveaSystem
from hbis_torch.figures import scan_figures


def test_figure_3_draws(tmp_path):
    path = scan_figures.figure_3(tmp_path / "fig3.png")
    assert path.exists() and path.stat().st_size > 10_000
    assert not list(tmp_path.glob(".*.tmp"))  # written atomically


def test_fig5_points_are_below_the_paper_bound_or_gaps():
    system = FoveaSystem()
    assert scan_figures.max_axis_ae(system, 7, (5.0, 5.5)) is None  # aligned: leaves the disc
    value = scan_figures.max_axis_ae(system, 7, (45.0, 130.0))
    assert 0.001 < value < 0.01  # "the maximum AE is below 0.01" (section 3.2)
    assert scan_figures.max_axis_ae(system, 7, (45.0, 130.0), "exact") < 1e-6


@pytest.mark.slow
def test_make_figures_writes_every_png(tmp_path):
    paths = scan_figures.make_figures(tmp_path, FoveaSystem(), progress=False)
    assert [p.name for p in paths] == ["fig3_scan_patterns.png", "fig5_max_ae.png",
                                       "scan_pixel_ae.png"]
    assert all(p.stat().st_size > 20_000 for p in paths)
