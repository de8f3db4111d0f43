"""The demo's outputs and its one-page HTML report (checked in a real browser when one exists)."""

import json
import os
import re
import shutil
import subprocess
import sys
import tempfile

import numpy as np
import pytest
import torch
from PIL import Image

from hbis_torch.system.pipeline import ChainConfig, run_chain
from hbis_torch.system.array.scenario import default_path
from hbis_torch.cli import main
from hbis_torch.config import FoveaSystem
from hbis_torch.design import design
from hbis_torch.figures.design_figures import make_figures
from hbis_torch.system.report.report import image_links, write_report

BROWSER = shutil.which("chromium") or shutil.which("chromium-browser")


@pytest.fixture(scope="module")
def demo_dir(tmp_path_factory):
    """A reduced chain (binned 4 panorama, h = 2, a quick object) and its report."""
    out = tmp_path_factory.mktemp("demo")
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        path = default_path(stop_mm=(3.0, 2.0), speed_mm_s=12.0, start_x_mm=-15.0, end_x_mm=18.0, stop_s=1.0)
        config = ChainConfig(h=2, roi_size=96, panorama_binning=4, duration_s=4.6, path=path)
        summary = run_chain(out, FoveaSystem(), config, log=lambda *_: None)
    finally:
        torch.set_num_threads(threads)
    figures = [str(p.relative_to(out)) for p in make_figures(out / "figures", FoveaSystem(), progress=False)]
    page = write_report(out, summary, design(FoveaSystem()).to_dict(), figures)
    return out, page, summary


def test_report_is_written_and_every_image_it_names_exists(demo_dir):
    out, page, summary = demo_dir
    text = page.read_text()
    links = image_links(text)
    assert len(links) >= 13
    for link in links:
        path = out / link
        assert path.is_file(), link
        with Image.open(path) as im:
            assert im.format == "PNG" and min(im.size) > 16
    for key in ("panorama", "composite", "composite_zoom", "sr_fovea", "sub_image", "sr_pairs", "timeline"):
        assert summary["images"][key] in links
    assert "<table>" in text and "FER_h" in text and "Event log" in text


def test_demo_numbers_are_consistent(demo_dir):
    _, _, summary = demo_dir
    fer = summary["fer"]
    # the design-angle stitch of the (misassembled) array measures the design itself
    assert fer["measured_design_stitch"]["central"]["fer_h"] == pytest.approx(fer["theory"]["fer_h"], abs=0.01)
    # the refined stitch measures the real assembly: near the design, not equal to it
    assert abs(fer["measured_refined"]["central"]["fer_h"] - fer["theory"]["fer_h"]) < 0.15
    assert summary["refinement"]["refined_error_px"] < summary["refinement"]["design_error_px"] / 5
    assert summary["foveal_ratio"]["measured"] == pytest.approx(2.0, rel=0.02)
    assert summary["sr"]["psnr_sr_db"] > summary["sr"]["psnr_bicubic_db"]
    assert 0.0 < summary["bandwidth"]["bsr_from_coverage"] < 1.0
    json.dumps(summary)  # everything in it can go into report.json
    sr = np.asarray(Image.open(demo_dir[0] / summary["images"]["sr_fovea"]))
    assert sr.shape == tuple(summary["sr"]["shape"])


def test_report_opens_on_its_headline_numbers_with_real_captions(demo_dir):
    import hbis_torch
    from hbis_torch.system.report.report import FIGURE_CAPTIONS

    out, page, summary = demo_dir
    text = page.read_text()
    top = text[:text.index("<img")]  # everything above the first picture
    assert "<h2>Summary</h2>" in top and f"hbis-torch {hbis_torch.__version__}" in top and " UTC" in top
    sr = summary["sr"]
    for number in (f"{summary['fer']['measured_refined']['rectangle']['fer_h']:.2f}",
                   f"{summary['foveal_ratio']['measured']:.2f}", f"{summary['bandwidth']['bsr_from_coverage']:.3f}",
                   f"{sr['psnr_sr_db']:.2f} dB", f"bicubic {sr['psnr_bicubic_db']:.2f} dB", "time of the chain"):
        assert number in top, number
    # the fixture's chain runs the classical method, so its PSNR is the SR's own (another method
    # would be compared with it in the summary: test_summary_compares_another_method_with_classical)
    assert summary["config"]["method"] == "classical" and sr["psnr_classical_db"] == sr["psnr_sr_db"]
    assert "varphi" not in text and "φ" in text
    for name in ("fig4_fov_fer.png", "fig6_bsr.png", "fig10_fov_layout.png"):
        assert f"<figcaption>{FIGURE_CAPTIONS[name]}</figcaption>".replace("'", "&#x27;") in text
    assert set(summary["timings_s"]) == set(__import__("hbis_torch.system.pipeline", fromlist=["x"]).STAGES)


def test_summary_compares_another_method_with_classical(demo_dir):
    from hbis_torch.system.report.report import render_report

    _, _, summary = demo_dir
    learned = {**summary, "config": {**summary["config"], "method": "learned"},
               "sr": {**summary["sr"], "psnr_sr_db": 40.0, "psnr_classical_db": 35.5}}
    text = render_report(learned, design(FoveaSystem()).to_dict(), [], {"version": "9", "date": "d", "command": "c"})
    assert "SR PSNR, learned" in text and "40.00 dB" in text and "classical 35.50 dB" in text


@pytest.mark.skipif(BROWSER is None and not os.environ.get("HBIS_REQUIRE_BROWSER"), reason="no chromium installed")
def test_report_renders_in_a_headless_browser(demo_dir):
    # .ci/run installs Debian's chromium and sets HBIS_REQUIRE_BROWSER: there, a missing browser fails
    assert BROWSER is not None, "HBIS_REQUIRE_BROWSER is set, but no chromium or chromium-browser is on PATH"
    out, page, _ = demo_dir
    shot = out / "screenshot.png"
    with tempfile.TemporaryDirectory() as profile:
        subprocess.run(
            [BROWSER, "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
             "--disable-background-networking", "--disable-component-update", "--disable-sync",
             f"--user-data-dir={profile}", "--window-size=1280,4000", f"--screenshot={shot}",
             page.resolve().as_uri()],
            check=True, capture_output=True, timeout=120,
        )
    with Image.open(shot) as im:
        assert im.size == (1280, 4000)
        grey = np.asarray(im.convert("L"), dtype=np.float32)
    # the page shows pictures, not a blank or an error page: much of it is neither white nor flat
    assert float(grey.std()) > 40.0
    assert float((grey < 200).mean()) > 0.25
    # the browser's first heading after the title is the summary, with its table
    with tempfile.TemporaryDirectory() as profile:
        dom = subprocess.run(
            [BROWSER, "--headless", "--no-sandbox", "--disable-gpu", "--no-first-run", "--disable-sync",
             "--disable-background-networking", "--disable-component-update", f"--user-data-dir={profile}",
             "--dump-dom", page.resolve().as_uri()],
            check=True, capture_output=True, text=True, timeout=120,
        ).stdout
    headings = re.findall(r"<h2>([^<]+)</h2>", dom)
    assert headings[0] == "Summary" and dom.index("<table>") < dom.index("<img")


def test_demo_cli_design_only_and_bad_arguments(tmp_path, capsys):
    assert main(["demo", "--design-only", "--out", str(tmp_path / "d")]) == 0
    report = json.loads((tmp_path / "d" / "report.json").read_text())
    assert "design_at_limits" in report and "system" not in report
    capsys.readouterr()
    for bad in (["--method", "nonsense"], ["--threads", "0"], ["--model", str(tmp_path / "missing.onnx")]):
        try:
            rc = main(["demo", *bad, "--out", str(tmp_path / "x")])
        except SystemExit as exc:  # --threads 0: argparse's own range check
            rc = exc.code
        assert rc == 2, bad
        err = capsys.readouterr().err
        assert len(err.strip().splitlines()) == 1 and "Traceback" not in err


@pytest.mark.slow
def test_full_default_demo(tmp_path):
    result = subprocess.run([sys.executable, "-m", "hbis_torch", "demo", "--out", str(tmp_path)],
                            capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr
    page = (tmp_path / "report.html").read_text()
    assert all((tmp_path / link).is_file() for link in image_links(page))
    report = json.loads((tmp_path / "report.json").read_text())
    assert report["system"]["loop"]["kept"] >= 1
