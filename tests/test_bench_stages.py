"""benchmarks/bench_handheld_stages.py: refuses bad input before any work; its stages add up."""

import importlib.util
import json
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def bench():
    spec = importlib.util.spec_from_file_location("bench_handheld_stages",
                                                  REPO / "benchmarks" / "bench_handheld_stages.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.parametrize("argv", [["--size", "64"], ["--size", "32x32"], ["--frames", "1"], ["--scale", "5"],
                                  ["--cache", "/nonexistent/folder"]])
def test_bad_input_is_refused_before_any_work(bench, argv, tmp_path, capsys):
    out = tmp_path / "stages.json"
    assert bench.main(argv + ["--json", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("bench_handheld_stages: ")
    assert not out.exists()


def test_the_stages_add_up_to_each_step(bench, tmp_path, capsys):
    out = tmp_path / "stages.json"
    assert bench.main(["--size", "160x128", "--frames", "4", "--repeats", "1", "--cache", str(tmp_path),
                       "--json", str(out)]) == 0
    result = json.loads(out.read_text())
    assert "--size 160x128" in result["provenance"]["command"] and result["provenance"]["commit"]
    for step in ("assemble", "classical"):
        rows = [r for r in result["stages"] if r["step"] == step]
        named = [r["seconds"] for r in rows if r["stage"] != "rest"]
        assert all(t > 0 for t in named)  # every stage's function was found in the profile
        # the stages do not overlap: together they are no more than the step's own time
        assert sum(named) <= result["profiled_s"][step] + 1e-6
    assert (tmp_path / "handheld_all_160x128_S2_F4_seed0.npy").exists()  # the burst kept for the next run
