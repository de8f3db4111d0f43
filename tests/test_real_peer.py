"""A peer beside the project's methods in the observation-space cross-validation
(``cross_validate``'s ``extra_methods``, benchmarks/bench_real_bursts.py's vidsr row): it is handed
the same folds (every frame but the held-out one, the reference re-indexed) and scored by the same
held-out frames and forward model; its image lies on the reference frame's grid."""

import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.ndimage import shift as subpixel_shift

from hbis_torch.errors import HbisInputError
from hbis_torch.reconstruct import reconstruct
from hbis_torch.validate import cross_validate, select_frames
from tests.test_validate import translation_burst

REPO = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.usefixtures("one_thread")

#: Frame k's shift (LR px, multiples of 1/8): frame pixel (u, v) sees reference position (u + dx, v + dy).
SHIFTS = [(0.25, 0.5), (0.5, 0.125), (0.0, 0.0), (0.75, 0.375), (0.375, 0.75), (0.625, 0.25)]
REFERENCE = 2  # not frame 0, so that a fold's reference index moves when an earlier frame is held out


def _burst(scale=2, size=32, factor=8, seed=0):
    """A burst of a smooth random scene with the reference at :data:`REFERENCE`: (stack, truth on
    the reference's grid refined ``scale`` times)."""
    return translation_burst(SHIFTS, scale, size, seed, factor, reference=REFERENCE)


@pytest.fixture(scope="module")
def burst():
    return _burst()


def test_a_peer_is_handed_each_fold_and_scored_as_a_registered_method_is(burst):
    stack, _ = burst
    seen = []

    def peer(fold):  # what the classical method makes of the fold, through the peer's door
        seen.append(fold)
        return reconstruct(fold, "classical")

    scored = cross_validate(stack, ("single-frame", "classical"), holdout=3, extra_methods={"peer": peer})
    assert list(scored.methods) == ["single-frame", "classical", "peer"]
    assert len(seen) == len(scored.held_out) == 3 and REFERENCE not in scored.held_out
    for fold, k in zip(seen, scored.held_out):
        kept = [i for i in range(len(stack.frames)) if i != k]
        np.testing.assert_array_equal(fold.frames, stack.frames[kept])  # the held-out frame, and only it, left out
        assert fold.reference_index == kept.index(REFERENCE)
        np.testing.assert_array_equal(fold.frames[fold.reference_index], stack.frames[REFERENCE])
        np.testing.assert_array_equal(fold.motions, select_frames(stack, kept).motions)
    assert any(fold.reference_index != REFERENCE for fold in seen)  # some fold re-indexed the reference
    # the same image in the same fold scores the same: same held-out frames, forward model, samples
    assert scored.methods["peer"].psnr == scored.methods["classical"].psnr
    assert scored.gain("classical", "peer") == 0.0


def test_a_peer_off_the_reference_grid_by_half_an_output_pixel_scores_worse(burst):
    stack, truth = burst
    on_grid = lambda fold: truth  # noqa: E731 - the scene itself, on the reference's output grid
    off_grid = lambda fold: subpixel_shift(truth, (0.5, 0.5), order=3, mode="nearest")  # noqa: E731
    scored = cross_validate(stack, ("single-frame",), holdout=3,
                            extra_methods={"truth": on_grid, "truth moved": off_grid})
    assert scored.gain("truth") > 3.0, scored.gain("truth")
    assert scored.gain("truth", "truth moved") > 3.0, scored.gain("truth", "truth moved")


@pytest.mark.parametrize("extra, message", [
    ({"classical": lambda fold: None}, "a name of its own"),
    ({"bicubic": lambda fold: None}, "a name of its own"),
    ({"peer": "not a function"}, "not callable"),
    ({"peer": lambda fold: np.zeros((5, 5))}, "not the output grid's"),
])
def test_a_bad_extra_method_is_refused_in_one_line(burst, extra, message):
    stack, _ = burst
    with pytest.raises(HbisInputError, match=message):
        cross_validate(stack, ("single-frame",), holdout=1, extra_methods=extra)


@pytest.fixture(scope="module")
def bench():
    """benchmarks/bench_real_bursts.py as a module (it imports benchutil from its folder)."""
    import importlib.util

    sys.path.insert(0, str(REPO / "benchmarks"))
    try:
        spec = importlib.util.spec_from_file_location("bench_real_bursts", REPO / "benchmarks" / "bench_real_bursts.py")
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
    finally:
        sys.path.remove(str(REPO / "benchmarks"))
    return module


def _row(sequence, scale, single, classical, learned, vidsr=None):
    row = {"sequence": sequence, "scale": scale, "frames": 6, "trusted": 6, "models": {"translation": 6},
           "assemble_cpu_s": 0.1, "learned_ran": "network", "classical_gain_db": classical - single,
           "learned_minus_classical_db": learned - classical}
    for name, value in (("single-frame", single), ("classical", classical), ("learned", learned), ("vidsr", vidsr)):
        if value is not None:
            row[name] = {"psnr_db": value, "per_frame_db": [value], "seconds": 0.5, "messages": []}
    if vidsr is not None:
        row["classical_minus_vidsr_db"], row["learned_minus_vidsr_db"] = classical - vidsr, learned - vidsr
    return row


def test_the_benchmarks_table_and_summary_carry_vidsr_where_the_rows_have_it(bench):
    rows = [_row("a", 2, 20.0, 23.0, 23.5, 22.0), _row("b", 2, 20.0, 22.0, 22.1, 22.5)]
    s = bench.summary(rows)["2"]
    assert s["classical_minus_vidsr_mean_db"] == pytest.approx(0.25)
    assert s["classical_minus_vidsr_worst_db"] == pytest.approx(-0.5)
    assert s["learned_minus_vidsr_mean_db"] == pytest.approx(0.55)
    assert s["learned_minus_vidsr_worst_db"] == pytest.approx(-0.4)
    table = bench.table(rows).splitlines()
    assert "| vidsr |" in table[0] and "classical - vidsr | learned - vidsr" in table[0]
    assert "| 22.00 |" in table[2] and "| +1.00 | +1.50 |" in table[2] and "| -0.50 | -0.40 |" in table[3]
    assert all(line.count("|") == table[0].count("|") for line in table)
    without = [_row("a", 2, 20.0, 23.0, 23.5)]
    assert "vidsr" not in bench.table(without) and "classical_minus_vidsr_mean_db" not in bench.summary(without)["2"]


def test_the_benchmark_hands_vidsr_the_folds_frames_and_reference(bench, burst, monkeypatch):
    stack, _ = burst
    calls = []

    class FakePeer:
        @staticmethod
        def vidsr_sr(frames, scale, reference=0):
            calls.append((frames, scale, reference))
            return np.zeros((scale * frames.shape[1], scale * frames.shape[2]), np.float32)

    monkeypatch.setattr(bench, "vidsr_peer", FakePeer)
    fold = select_frames(stack, [0, 3, 4, 5])  # frame 1 held out: the reference moves to index 1
    image = bench.peer_of(fold)
    frames, scale, reference = calls[0]
    assert image.shape == (64, 64) and scale == 2 and reference == 1 == fold.reference_index
    np.testing.assert_array_equal(frames, fold.to_float().numpy())


def test_vidsr_through_the_benchmark_scores_on_the_reference_grid(bench, burst):
    pytest.importorskip("vidsr")
    stack, truth = burst
    image = bench.peer_of(stack)
    assert image.shape == truth.shape
    moved = lambda fold: subpixel_shift(bench.peer_of(fold), (0.5, 0.5), order=3, mode="nearest")  # noqa: E731
    scored = cross_validate(stack, ("single-frame",), holdout=2, extra_methods={"vidsr": bench.peer_of,
                                                                                "vidsr moved": moved})
    assert scored.gain("vidsr") > 2.0 and scored.gain("vidsr", "vidsr moved") > 2.0, scored.to_dict()


@pytest.mark.parametrize("argv, message", [
    (["--bogus"], "unrecognized arguments: --bogus"),
    (["--scales", "0"], "--scales must lie in 1..8"),
    (["--data", "/nonexistent/real-bursts"], "is not at /nonexistent/real-bursts"),
])
def test_the_benchmark_refuses_bad_flags_in_one_line_before_any_work(bench, argv, message, tmp_path, monkeypatch,
                                                                     capsys):
    data = [] if "--data" in argv else ["--data", str(tmp_path)]
    if "--scales" in argv:  # a sequence that is there, so that the scale is what is refused
        (tmp_path / "text.tif").write_bytes(b"")
        data += ["--sequences", "text.tif"]
    out = tmp_path / "out.json"
    monkeypatch.setattr(sys, "argv", ["bench_real_bursts.py", *data, *argv, "--json", str(out), "--no-doc"])
    with pytest.raises(SystemExit) as exit_:
        bench.main()
    said = capsys.readouterr()
    assert exit_.value.code == 2 and said.out == ""
    assert len(said.err.strip().splitlines()) == 1 and message in said.err, said.err
    assert not out.exists()
