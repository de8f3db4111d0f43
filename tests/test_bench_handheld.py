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


def test_the_medians_leave_the_imports_out(load_script, tmp_path, monkeypatch):
    """On a busy machine one quiet import makes the fastest run: the medians of assemble + classical
    compare the steps themselves."""
    bench = load_script("benchmarks/bench_handheld.py")
    steps = {("start", bench.ROOT): [0.5, 0.7, 0.6], ("start", tmp_path): [0.6, 0.5, 0.7],
             ("full", bench.ROOT): [2.0, 2.6, 2.2], ("full", tmp_path): [3.0, 2.8, 2.9]}
    imports = iter([0.5, 3.0] * 6)  # this checkout's imports always the quicker: its fastest runs win by them

    def fake_child(path, scale, mode, learned, vidsr, max_gb=0, allocator="hbis", root=bench.ROOT):
        seconds = steps[(mode, root)].pop(0)
        return {"to_classical_s": next(imports) + seconds, "floor_s": 0.1, "assemble_s": seconds / 2,
                "classical_s": seconds / 2, "peak_rss_mb": 1.0}

    monkeypatch.setattr(bench, "run_child", fake_child)
    monkeypatch.setattr(bench, "_commit", lambda root: "abc")
    row = {"size": "64x64", "frames": 3, "scale": 2}
    args = bench.main.__globals__["argparse"].Namespace(repeats=3, scale=2, allocator="hbis", max_gb=0,
                                                        no_learned=True, no_vidsr=True, baseline=tmp_path)
    bench.measure(row, tmp_path / "b.npy", 64, 64, args)
    assert abs(row["own_median_s"] - (2.2 - 0.6)) < 1e-12
    assert abs(row["baseline"]["own_median_s"] - (2.9 - 0.6)) < 1e-12
    assert abs(row["own_median_over_baseline"] - 1.6 / 2.3) < 1e-12
    assert "medians, imports left out: 1.60 s against 2.30 s" in bench.summary(row)
