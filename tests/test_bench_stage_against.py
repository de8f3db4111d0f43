"""benchmarks/bench_stage_against.py: refuses bad input before any work; a stage against itself."""

import json
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def bench(load_script):
    return load_script("benchmarks/bench_stage_against.py")


@pytest.mark.parametrize("argv", [["--baseline", "/nonexistent"], ["--stages", "splat"], ["--repeats", "1"],
                                  ["--size", "32x32"], ["--frames", "1"], ["--cache", "/nonexistent/folder"]])
def test_bad_input_is_refused_before_any_work(bench, argv, tmp_path, capsys):
    out = tmp_path / "against.json"
    args = argv if argv[0] == "--baseline" else ["--baseline", str(REPO), *argv]
    assert bench.main(args + ["--json", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("bench_stage_against: ")
    assert not out.exists()


def test_each_stage_against_its_own_file_gives_the_same_bits(bench, tmp_path):
    out = tmp_path / "against.json"
    assert bench.main(["--baseline", str(REPO), "--size", "96x72", "--frames", "5", "--repeats", "2",
                       "--cache", str(tmp_path), "--json", str(out)]) == 0
    result = json.loads(out.read_text())
    assert {r["stage"] for r in result["rows"]} == {"brightness", "lattice_fit"}
    for row in result["rows"]:
        assert row["calls"] >= 1 and row["same_bits"] and row["this_s"] > 0 and row["baseline_s"] > 0
    assert (tmp_path / "handheld_all_96x72_S2_F5_seed0.npy").exists()  # the burst kept for the next run


def test_a_different_result_is_named(bench):
    calls = [((2.0,), {})]
    row = bench.compare(calls, lambda x: (x, 1.0), lambda x: (x, 1.0 + 1e-12), 2)
    assert row["calls"] == 1 and not row["same_bits"]
    assert bench.compare(calls, lambda x: (x, 1.0), lambda x: (x, 1.0), 2)["same_bits"]
