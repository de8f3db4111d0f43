"""Every script in examples/ runs (``--out`` a temporary folder, exit code 0) and prints numbers
that say it worked: the Table 1 FER, an exact scan plan, super-resolution above bicubic, motors
that reach their targets, a stack's noise measured near its sensor's."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
SCRIPTS = sorted(EXAMPLES.glob("*.py"))


def numbers(pattern: str, text: str) -> list[tuple[float, ...]]:
    """Every match of ``pattern`` in ``text``, its groups as floats."""
    return [tuple(float(g) for g in m.groups()) for m in re.finditer(pattern, text)]


def check_plot_design_sensor(out: str, folder: Path) -> None:
    [(fer_h, fer_v)] = numbers(r"FER\s+h (\S+), v (\S+)", out)
    assert fer_h == pytest.approx(2.63, abs=0.01) and fer_v == pytest.approx(2.51, abs=0.01)
    assert "h_max              7" in out
    [(inflection,)] = numbers(r"reaches 2 \(the inflection\) at a wedge angle of (\S+) deg", out)
    assert inflection == pytest.approx(11.0, abs=0.5)  # the paper's Fig. 4b
    assert (folder / "fer_vs_wedge_angle.png").stat().st_size > 1000


def check_plan_scan(out: str, folder: Path) -> None:
    assert len(numbers(r"frame +(\d+) +offset", out)) == 16
    ae = {m: float(a) for m, a in re.findall(r"(paper|exact) inverse: .*axis AE max (\S+),", out)}
    assert ae["exact"] < 1e-9 < ae["paper"] < 0.02  # the paper reports about 0.01 for its inverse
    [(pixel_max, _)] = numbers(r"exact inverse: .*pixel AE max (\S+) mean (\S+)", out)
    assert 0.1 < pixel_max < 0.6
    assert (folder / "scan_h4.json").is_file()


def check_simulate_and_reconstruct(out: str, folder: Path) -> None:
    scores = {m: float(v) for m, v in re.findall(r"PSNR (\w+) +(\S+) dB", out)}
    assert set(scores) == {"bicubic", "classical", "learned"}
    assert scores["classical"] > scores["bicubic"] + 3
    assert scores["learned"] > scores["bicubic"] + 3
    assert {p.name for p in folder.glob("*.tif")} == {"stack.tif", "truth.tif", "sr_classical.tif",
                                                     "sr_learned.tif"}


def check_measure_noise(out: str, folder: Path) -> None:
    ratio = {name.strip(): float(r) for name, r in re.findall(r"^  (.+?) +a .*\((\S+) x the sensor's\)", out, re.M)}
    assert set(ratio) == {"sensor", "single frames", "lattice"}
    assert ratio["lattice"] == pytest.approx(1.0, abs=0.2)  # the lattice measures the sensor's noise
    assert ratio["single frames"] > 2  # a frame's aliased detail passes for noise
    assert set(json.loads((folder / "noise.json").read_text())) == set(ratio)


def check_drive_simulated_motors(out: str, folder: Path) -> None:
    [(step,)] = numbers(r"one step = (\S+) deg", out)
    tolerance = step + 1.5e-3  # read-back within a step (MPos is printed to 0.001 deg)
    [(g1, g2)] = numbers(r"goto \(5\.0, 70\.0\): read back \((\S+), (\S+)\)", out)
    assert abs(g1 - 5.0) <= tolerance and abs(g2 - 70.0) <= tolerance
    frames = numbers(r"planned \( *(\S+), +(\S+)\) +read back \( *(\S+), +(\S+)\)", out)
    assert len(frames) == 9
    for p1, p2, r1, r2 in frames:
        assert abs(p1 - r1) <= tolerance and abs(p2 - r2) <= tolerance
    assert (folder / "scan-journal.json").is_file()


def check_handheld_burst(out: str, folder: Path) -> None:
    scores = {m.strip(): float(v) for m, v in re.findall(r"PSNR (.+?) +(\S+) dB", out)}
    assert set(scores) == {"bicubic", "classical", "classical, lens given"}
    assert scores["classical"] > scores["bicubic"] + 1.5
    assert scores["classical, lens given"] > scores["classical"]
    assert "translation" not in re.search(r"models: (.*)", out).group(1)  # the burst turns
    assert (folder / "handheld_burst.png").stat().st_size > 1000 and (folder / "burst.tif").is_file()


CHECKS = {name[len("check_"):]: f for name, f in globals().items() if name.startswith("check_")}


def test_every_example_has_a_check():
    assert {p.stem for p in SCRIPTS} == set(CHECKS)


@pytest.fixture(scope="module")
def started(tmp_path_factory):
    """Start every example at once (separate processes, so the file takes about as long as the
    slowest one); each test then waits for its own. Output goes to files, not pipes."""
    runs = {}
    for script in SCRIPTS:
        folder = tmp_path_factory.mktemp(script.stem)
        out, err = open(folder / "stdout.txt", "w"), open(folder / "stderr.txt", "w")
        proc = subprocess.Popen([sys.executable, str(script), "--out", str(folder / "out")],
                                stdout=out, stderr=err, cwd=folder, text=True)
        runs[script.stem] = (proc, folder, out, err)
    yield runs
    for proc, _, out, err in runs.values():
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        out.close()
        err.close()


@pytest.mark.parametrize("script", SCRIPTS, ids=[p.stem for p in SCRIPTS])
def test_example_runs(script: Path, started):
    text = script.read_text()
    assert text.startswith('"""') and "sys.path" not in text  # a docstring first; no path hacks
    proc, folder, _, _ = started[script.stem]
    returncode = proc.wait(timeout=180)
    stdout, stderr = ((folder / name).read_text() for name in ("stdout.txt", "stderr.txt"))
    assert returncode == 0, stderr[-3000:]
    CHECKS[script.stem](stdout, folder / "out")
