"""The shared real-bursts set (real captured sequences, not shipped): every sequence assembles
as a burst and reconstructs with both methods, finite, at the burst's scale, and gives the gains
docs/real-bursts.md quotes from benchmarks/results/bench_real_bursts.json. Skipped where the set
is absent."""

import json
from pathlib import Path

import numpy as np
import pytest

from hbis_torch.capture.burst import assemble_burst
from hbis_torch.capture.frames import read_frames
from hbis_torch.reconstruct.registry import reconstruct

REPO = Path(__file__).resolve().parents[1]
DATA = REPO.parent / "shared" / "data" / "real-bursts"
RESULTS = REPO / "benchmarks" / "results" / "bench_real_bursts.json"
SEQUENCES = ("text.tif", "disk.tif", "Emily_small.tif", "Book_case1_small.tif")
#: How far a re-measured gain may sit from the committed one: the docs' rounding and another CPU's
#: float sums in the burst adaptation (the same machine reproduces them within 1e-5 dB).
AGREE_DB = 0.1
pytestmark = [pytest.mark.skipif(not DATA.is_dir(), reason="the shared real-bursts set is absent"),
              pytest.mark.usefixtures("one_thread")]


def _check(name: str, scale: int, count: int | None = None):
    frames, names = read_frames([DATA / name])
    frames = frames[:count]
    stack, messages = assemble_burst(frames, scale, names=names[:len(frames)])
    assert stack.kind == "burst" and (stack.confidence >= 0.5).sum() >= len(frames) // 2
    # every rejection names its frame; disk's and text's first frames are named as blurred
    assert all(m.startswith(("frame ", "the reference, frame 0, is blurred")) for m in messages)
    for method in ("classical", "learned"):
        image = reconstruct(stack, method)
        assert image.shape[:2] == (scale * frames.shape[1], scale * frames.shape[2])
        assert np.isfinite(image).all() and 0 <= image.min() and image.max() <= 1


def test_text_first_frames_assemble_and_reconstruct():
    _check("text.tif", 2, count=6)


def test_the_avi_reads_as_the_tiff():
    video, _ = read_frames([DATA / "disk.avi"])
    pages, _ = read_frames([DATA / "disk.tif"])
    assert np.array_equal(video, pages)


@pytest.mark.slow
@pytest.mark.parametrize("name", ["text.tif", "disk.tif", "Emily_small.tif", "Book_case1_small.tif", "text.avi",
                                  "disk.avi"])
@pytest.mark.parametrize("scale", [2, 3, 4])
def test_every_shared_sequence(name, scale):
    _check(name, scale)


@pytest.mark.parametrize("name, scale, least", [("Emily_small.tif", 4, 1.0), ("Book_case1_small.tif", 2, 2.5)])
def test_classical_beats_the_single_frame_by_validate(name, scale, least):
    # the two cells that were weakest: Emily at S = 4 (+0.45 dB without the bursts' noise floor,
    # +1.48 with it) and Book_case at S = 2 (+2.29 dB with the pilot's gradient read at the node,
    # +2.75 where the pilot stands)
    from hbis_torch.validate import cross_validate

    frames, names = read_frames([DATA / name])
    stack, _ = assemble_burst(frames, scale, names=names)
    gain = cross_validate(stack, ("single-frame", "classical"), holdout=3).gain("classical")
    assert gain > least, gain


def _gains(name: str, scale: int) -> tuple[float, float]:
    """(classical - single frame, learned - classical) by validate, 3 frames held out, as
    benchmarks/bench_real_bursts.py measures them."""
    from hbis_torch.validate import cross_validate

    frames, names = read_frames([DATA / name])
    stack, _ = assemble_burst(frames, scale, names=names)
    scored = cross_validate(stack, ("single-frame", "classical", "learned"), holdout=3)
    return scored.gain("classical"), scored.gain("learned", "classical")


def _documented(name: str, scale: int) -> tuple[float, float]:
    rows = json.loads(RESULTS.read_text())["rows"]
    row = next(r for r in rows if r["sequence"] == name and r["scale"] == scale)
    return row["classical_gain_db"], row["learned_minus_classical_db"]


def test_text_gives_the_documented_gains():
    # docs/real-bursts.md: text at S = 2, classical +5.13 dB over the single frame, the adapted
    # network +0.17 dB over the classical image (+4.68 and +0.38 while the lattice fit took only
    # the holes; +4.58 and +0.60 while a burst kept some frames' starting motions; +3.82 and +0.65
    # with the forward model not yet centred at even S)
    classical, learned = _gains("text.tif", 2)
    want_classical, want_learned = _documented("text.tif", 2)
    assert abs(classical - want_classical) < AGREE_DB, (classical, want_classical)
    assert abs(learned - want_learned) < AGREE_DB, (learned, want_learned)
    assert learned > 0.1 and classical > 2.5


@pytest.mark.slow
@pytest.mark.parametrize("scale", [2, 3, 4])
def test_every_sequence_gives_the_documented_gains_and_meets_the_goals(scale):
    # classical +2.5 dB over the single frame on average, +0.5 on every sequence; learned ahead of
    # classical on average and no sequence below -0.3 (the hand-held issue's +0.2 on average holds
    # at every S since each frame keeps its own fit: docs/real-bursts.md. Before the forward model was centred at even S
    # the floors here were 0.2 below what the unbounded adaptation gave, +0.50 / +0.35 / +0.44,
    # which the old model's shared blur with the adaptation had inflated at S = 2 and 4)
    measured = {name: _gains(name, scale) for name in SEQUENCES}
    for name, (classical, learned) in measured.items():
        want_classical, want_learned = _documented(name, scale)
        assert abs(classical - want_classical) < AGREE_DB, (name, classical, want_classical)
        assert abs(learned - want_learned) < AGREE_DB, (name, learned, want_learned)
    classical, learned = np.array(list(measured.values())).T
    assert classical.mean() > 2.5 and classical.min() > 0.5, measured
    assert learned.mean() > 0.0 and learned.min() > -0.3, measured


@pytest.mark.parametrize("name, scale, least", [("Emily_small.tif", 2, -0.3)])
def test_the_adapted_network_holds_against_classical_by_validate(name, scale, least):
    # as shipped the network gave +0.17 (text) and +0.00 dB (Emily: its noise lies outside the
    # training range, so the classical image came back); adapted to each burst, scored with the
    # forward model centred at even S, +0.60 and -0.05 (+0.65 and +0.16 with the old model, which
    # the adaptation shared; +0.38 and -0.12 since each frame keeps its own fit): Emily must stay
    # within the hand-held issue's -0.3
    from hbis_torch.validate import cross_validate

    frames, names = read_frames([DATA / name])
    stack, _ = assemble_burst(frames, scale, names=names)
    gain = cross_validate(stack, ("classical", "learned"), holdout=3).gain("learned", "classical")
    assert gain > least, gain
