"""benchmarks/bench_busy_machine.py: refuses bad input before any work."""

import importlib.util
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def bench():
    spec = importlib.util.spec_from_file_location("bench_busy_machine", REPO / "benchmarks" / "bench_busy_machine.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.parametrize("argv", [["--size", "640"], ["--size", "32x32"], ["--size", "axb"], ["--repeats", "0"],
                                  ["--cache", "/nonexistent/folder"], ["--json", "/nonexistent/folder/busy.json"]])
def test_bad_input_is_refused_before_any_work(bench, argv, capsys):
    assert bench.main(argv) == 2  # (before bench_handheld, which runs the bursts, is imported)
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("bench_busy_machine: ")
