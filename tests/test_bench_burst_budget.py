"""benchmarks/bench_burst_budget.py: refuses bad input before any work, and measures the hbis
program's peak and seconds beside the estimates."""

import importlib.util
import json
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SCRIPT = REPO / "benchmarks" / "bench_burst_budget.py"


@pytest.fixture(scope="module")
def bench():
    spec = importlib.util.spec_from_file_location("bench_burst_budget", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.parametrize("argv", [["--cases", "640x480"], ["--cases", "32x32:grey:2:classical"],
                                  ["--cases", "640x480:grey:5:classical"], ["--cases", "640x480:grey:2:best"],
                                  ["--threads", "0"], ["--cache", "/nonexistent/folder"],
                                  ["--json", "/nonexistent/folder/budget.json"]])
def test_bad_input_is_refused_before_any_work(bench, argv, capsys):
    assert bench.main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("bench_burst_budget: ")


@pytest.mark.parametrize("kind", ["rgb", "raw"])
def test_a_small_burst_is_measured_beside_its_estimates(tmp_path, kind):
    if kind == "raw":
        pytest.importorskip("rawpy")
        pytest.importorskip("pidng")
    out = tmp_path / "budget.json"
    subprocess.run([sys.executable, str(SCRIPT), "--cases", f"64x64:{kind}:2:classical", "--cache", str(tmp_path),
                    "--json", str(out)], check=True, capture_output=True, text=True)
    row = json.loads(out.read_text())["rows"][0]
    assert (row["channels"], row["raw"], row["scale"], row["method"]) == (3 if kind == "rgb" else 1, kind == "raw",
                                                                          2, "classical")
    for step in ("assemble", "reconstruct"):
        measured = row[step]
        assert measured["exit_code"] == 0 and 100 < measured["peak_rss_mib"] < 2000, measured
        assert 0.5 < measured["memory_estimated_over_measured"] < 3, measured
