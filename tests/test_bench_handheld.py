"""benchmarks/bench_handheld.py: a baseline that is no checkout is refused before any work; the
baseline's runs are interleaved with this checkout's."""


def test_a_baseline_that_is_no_checkout_is_refused(load_script, tmp_path, capsys):
    bench = load_script("benchmarks/bench_handheld.py")
    assert bench.main(["--sizes", "64x64", "--baseline", str(tmp_path), "--cache", str(tmp_path)]) == 2
    assert "not a checkout of the project" in capsys.readouterr().err
    assert not list(tmp_path.iterdir())  # nothing rendered


def test_the_baseline_runs_right_after_each_run(load_script, tmp_path, monkeypatch):
    bench = load_script("benchmarks/bench_handheld.py")
    calls = []

    def fake_child(path, scale, mode, learned, vidsr, max_gb=0, allocator="hbis", root=bench.ROOT):
        calls.append((mode, root))
        seconds = {"start": 1.0, "full": 3.0 if root == bench.ROOT else 4.0}[mode]
        return {"to_classical_s": seconds, "floor_s": 0.1, "assemble_s": 1.0, "classical_s": 1.0, "peak_rss_mb": 1.0}

    monkeypatch.setattr(bench, "run_child", fake_child)
    monkeypatch.setattr(bench, "_commit", lambda root: "abc")
    row = {}
    args = bench.main.__globals__["argparse"].Namespace(repeats=2, scale=2, allocator="hbis", max_gb=0,
                                                        no_learned=True, no_vidsr=True, baseline=tmp_path)
    bench.measure(row, tmp_path / "b.npy", 64, 64, args)
    assert [mode for mode, _ in calls] == ["start"] * 4 + ["full"] * 4
    assert [root for _, root in calls] == [bench.ROOT, tmp_path] * 4
    assert row["own_s"] == 2.0 and row["baseline"]["own_s"] == 3.0
    assert abs(row["own_over_baseline"] - 2 / 3) < 1e-12
