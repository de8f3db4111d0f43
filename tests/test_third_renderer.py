"""training/eval_third_renderer.py: its renderer keeps the project's grid conventions (an LR pixel
is the mean of its S x S output pixels, pixel centres at integers, homographies frame px ->
reference px), so that its truth and frames line up as the package assumes."""

import json
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("cv2")
TRAINING = str(Path(__file__).resolve().parents[1] / "training")


@pytest.fixture(scope="module")
def third(load_script):
    sys.path.insert(0, TRAINING)  # the script imports its sibling eval_handheld.py
    try:
        return load_script("training/eval_third_renderer.py")
    finally:
        sys.path.remove(TRAINING)


def _box_mean(truth: np.ndarray, scale: int) -> np.ndarray:
    H, W = truth.shape[0] // scale, truth.shape[1] // scale
    return truth.reshape(H, scale, W, scale).mean(axis=(1, 3))


@pytest.mark.parametrize("scale", [2, 3])
def test_the_reference_frame_is_the_truths_pixel_means(third, scale):
    """Without lens and noise, frame 0 is the truth averaged over each LR pixel's S x S output
    pixels (away from the border, where the bicubic enlargement reads the reflection)."""
    frames, truth, motions = third.render("translation", scale, 2, 48, 40, seed=3, photos=("camera",), blur=0.0,
                                          noise=False)
    assert np.allclose(motions[0], np.eye(3))
    inner = (slice(3, -3), slice(3, -3))
    # the enlargement is bicubic, not the box: off by 3e-4 on the mean, 7e-3 at most (a grid off
    # by an eighth of an LR pixel is off by 1.2e-3 to 1.8e-3 on the mean, up to 0.05)
    error = np.abs(frames[0] - _box_mean(truth.astype(np.float64), scale))[inner]
    assert error.mean() < 6e-4 and error.max() < 0.015


def test_a_frame_shifted_by_whole_pixels_is_the_reference_moved(third):
    """A frame whose homography is a shift of (2, -1) LR px sees at pixel (x, y) what the
    reference sees at (x + 2, y - 1)."""
    third_homographies = third.homographies

    def shifted(motion, count, width, height, rng):
        out = third_homographies(motion, count, width, height, rng)
        out[1] = np.array([[1, 0, 2.0], [0, 1, -1.0], [0, 0, 1]])
        return out

    third.homographies = shifted
    try:
        frames, _, _ = third.render("translation", 2, 2, 48, 40, seed=5, photos=("camera",), blur=0.3, noise=False)
    finally:
        third.homographies = third_homographies
    assert np.allclose(frames[1][4:-4, 4:-6], frames[0][3:-5, 6:-4], atol=1e-6)


def test_the_noise_is_about_what_the_full_well_gives(third):
    """Poisson of FULL_WELL_E electrons: at the mean level m the frame's noise is sqrt(m / well)."""
    clean, _, _ = third.render("translation", 2, 2, 64, 48, seed=1, photos=("camera",), noise=False)
    noisy, _, _ = third.render("translation", 2, 2, 64, 48, seed=1, photos=("camera",))
    difference = noisy[0] / 65535.0 - clean[0]
    expected = np.sqrt(np.mean(clean[0]) / third.FULL_WELL_E)
    assert 0.8 * expected < difference.std() < 1.2 * expected
    # a dimmer light (--full-well 200): seven times the noise
    dim, _, _ = third.render("translation", 2, 2, 64, 48, seed=1, photos=("camera",), full_well=200.0)
    expected = np.sqrt(np.mean(clean[0]) / 200.0)
    assert 0.8 * expected < (dim[0] / 65535.0 - clean[0]).std() < 1.2 * expected


def test_a_dimmer_light_is_a_setting_of_its_own(third, tmp_path, capsys):
    out = tmp_path / "r.json"
    with pytest.raises(SystemExit) as stop:
        third.main(["--out", str(out), "--cells", "similarity:2:4", "--no-vidsr", "--full-well", "5"])
    assert stop.value.code == 2 and "--full-well 5" in capsys.readouterr().err
    args = third.parse_args(["--out", str(out), "--cells", "similarity:2:4", "--no-vidsr", "--full-well", "200"])
    assert third._settings(args)["full_well_e"] == 200
    default = third.parse_args(["--out", str(out), "--cells", "similarity:2:4", "--no-vidsr"])
    assert "full_well_e" not in third._settings(default)  # the files made before the setting resume


def test_bad_cells_are_refused_before_any_work(third, tmp_path, capsys):
    with pytest.raises(SystemExit) as stop:
        third.main(["--out", str(tmp_path / "r.json"), "--cells", "spin:2:8", "--no-vidsr"])
    assert stop.value.code == 2
    assert "--cells spin:2:8" in capsys.readouterr().err
    assert not (tmp_path / "r.json").exists()


def test_frames_too_small_for_the_moving_object_are_refused_before_any_work(third, tmp_path, capsys):
    with pytest.raises(SystemExit) as stop:
        third.main(["--out", str(tmp_path / "r.json"), "--cells", "object:2:8", "--size", "160x80", "--no-vidsr"])
    assert stop.value.code == 2 and "object cells need" in capsys.readouterr().err
    assert not (tmp_path / "r.json").exists()


def test_the_summary_names_the_cells_where_classical_trails_the_peer(third):
    cells = {"similarity:2:8": {r: {"psnr_db": v} for r, v in (("classical", 30.0), ("vidsr", 30.4), ("bicubic", 28.0))},
             "homography:3:16": {r: {"psnr_db": v} for r, v in (("classical", 29.0), ("vidsr", 28.0), ("bicubic", 27.5))}}
    out = third.summary(cells, ("bicubic", "classical", "vidsr"))
    assert out["classical_minus_vidsr"] == pytest.approx({"mean_db": 0.3, "worst_db": -0.4})
    assert out["classical_minus_bicubic"]["worst_db"] == pytest.approx(1.5)
    assert out["classical_behind_vidsr_by_more_than_gap"] == ["similarity:2:8"]
    assert "learned_minus_classical" not in out


def test_a_file_of_other_settings_is_refused_not_overwritten(third, tmp_path, capsys):
    out = tmp_path / "r.json"
    out.write_text('{"settings": {"seed": 7}, "cells": {}}')
    with pytest.raises(SystemExit) as stop:
        third.main(["--out", str(out), "--cells", "similarity:2:4", "--no-vidsr"])
    assert stop.value.code == 2 and "other settings" in capsys.readouterr().err
    assert out.read_text() == '{"settings": {"seed": 7}, "cells": {}}'


def test_a_rolling_shutter_moves_each_row_by_its_read_out_time(third, monkeypatch):
    """Frame 1 without a homography and a roll of (4, 0) LR px over the frame's height: its first
    row sees the reference 2 px to the left, its middle row the reference itself, its last row
    2 px to the right."""
    monkeypatch.setattr(third, "homographies", lambda motion, count, width, height, rng: np.stack([np.eye(3)] * count))
    real_effects = third.effects

    def fixed_roll(*args):
        out = real_effects(*args)
        out["roll"][1] = (4.0, 0.0)
        return out

    monkeypatch.setattr(third, "effects", fixed_roll)
    frames, _, _ = third.render("rolling", 2, 2, 48, 41, seed=2, photos=("camera",), blur=0.3, noise=False)
    inner = slice(6, -6)
    for row, shift in ((0, -2), (20, 0), (40, 2)):
        assert np.allclose(frames[1][row, inner], np.roll(frames[0][row], -shift)[inner], atol=1e-6)
    assert not np.allclose(frames[1][0, inner], frames[0][0, inner], atol=1e-3)


def test_brightness_scales_each_frame_and_keeps_the_reference(third):
    """The ``brightness`` burst is the ``similarity`` burst of the same seed (the same scene and
    homographies), each frame times its gain (within MAX_GAIN_CHANGE, frame 0 untouched)."""
    plain, truth, _ = third.render("similarity", 2, 4, 64, 48, seed=4, photos=("camera",), noise=False)
    lit, lit_truth, _ = third.render("brightness", 2, 4, 64, 48, seed=4, photos=("camera",), noise=False)
    assert np.array_equal(truth, lit_truth) and np.array_equal(plain[0], lit[0])
    unclipped = plain < 0.9
    gains = [np.median(lit[k][unclipped[k]] / plain[k][unclipped[k]]) for k in range(1, 4)]
    assert all(abs(g - 1) <= third.MAX_GAIN_CHANGE for g in gains)
    assert all(np.allclose(lit[k][unclipped[k]], gains[k - 1] * plain[k][unclipped[k]], rtol=1e-9) for k in range(1, 4))
    assert max(abs(g - 1) for g in gains) > 0.005


def test_the_moving_object_is_a_disc_that_the_truth_holds_where_the_reference_saw_it(third):
    """The ``object`` truth is the ``similarity`` scene but for a disc of OBJECT_RADIUS_LR LR px;
    frame 0 sees the disc there, and the last frame sees it moved (elsewhere it sees the scene)."""
    radius = third.OBJECT_RADIUS_LR
    size = (4 * radius, 3 * radius)  # LR px
    plain, truth, _ = third.render("similarity", 2, 6, *size, seed=6, photos=("camera", "astronaut"), noise=False)
    moving, object_truth, _ = third.render("object", 2, 6, *size, seed=6, photos=("camera", "astronaut"), noise=False)
    changed = np.abs(object_truth - truth) > 1e-6
    assert 0.9 * np.pi * (2 * radius) ** 2 < changed.sum() < 1.05 * np.pi * (2 * radius) ** 2
    lr_changed = changed.reshape(size[1], 2, size[0], 2).any(axis=(1, 3))
    near = np.zeros_like(lr_changed)
    ys, xs = np.nonzero(lr_changed)
    near[max(ys.min() - 3, 0):ys.max() + 4, max(xs.min() - 3, 0):xs.max() + 4] = True
    assert np.allclose(moving[0][~near], plain[0][~near], atol=1e-6)
    assert not np.allclose(moving[0][lr_changed], plain[0][lr_changed], atol=1e-2)
    # where the last frame sees the disc: about its travel (at least 1 LR px a frame) from frame 0's
    centroids = [np.argwhere(np.abs(moving[k] - plain[k]) > 1e-3).mean(axis=0) for k in (0, -1)]
    assert np.hypot(*(centroids[1] - centroids[0])) > 3


def test_a_colour_burst_renders_each_channel_as_the_grey_renderer_does(third):
    """``colour``: the same crops in RGB; without lens and noise each channel of frame 0 is that
    channel of the truth averaged over each LR pixel (as the grey reference, above), the channels
    differ (astronaut is a colour photograph), and the motions are the grey burst's."""
    frames, truth, motions = third.render("similarity", 2, 3, 48, 40, seed=3, photos=("astronaut",), blur=0.0,
                                          noise=False, colour=True)
    _, _, grey_motions = third.render("similarity", 2, 3, 48, 40, seed=3, photos=("astronaut",), blur=0.0,
                                      noise=False)
    assert frames.shape == (3, 40, 48, 3) and truth.shape == (80, 96, 3)
    assert np.array_equal(motions, grey_motions)
    inner = (slice(3, -3), slice(3, -3))
    for c in range(3):
        channel = truth[..., c].astype(np.float64)
        error = np.abs(frames[0][..., c] - _box_mean(channel, 2))[inner].mean()
        # (the bicubic enlargement's error, as the grey reference's; a grid off by one output
        # pixel, half an LR pixel, is off 13 to 19 times as much on this crop)
        shifted = np.abs(frames[0][..., c] - _box_mean(np.roll(channel, 1, 1), 2))[inner].mean()
        assert error < 1.5e-3 and error < shifted / 5
    assert np.abs(truth[..., 0] - truth[..., 2]).mean() > 0.02
    noisy, _, _ = third.render("similarity", 2, 3, 48, 40, seed=3, photos=("astronaut",), colour=True)
    assert noisy.shape == frames.shape and noisy.dtype == np.uint16


def test_redo_runs_the_named_rows_again_and_keeps_the_others(third, tmp_path, monkeypatch):
    out = tmp_path / "r.json"
    common = ["--out", str(out), "--cells", "translation:2:4", "--size", "96x64", "--no-vidsr", "--no-learned"]
    third.main(common)
    first = json.loads(out.read_text())
    real_run_cell = third.run_cell

    def marked(motion, scale, count, args, rows=None):
        cell = real_run_cell(motion, scale, count, args, rows)
        return {**cell, **{row: {**cell[row], "psnr_db": 99.0} for row in rows or ()}}

    monkeypatch.setattr(third, "run_cell", marked)
    third.main([*common, "--redo", "classical"])
    again = json.loads(out.read_text())
    cell, before = again["cells"]["translation:2:4"], first["cells"]["translation:2:4"]
    assert cell["classical"]["psnr_db"] == 99.0 and cell["classical"]["run"] == 1
    assert cell["bicubic"] == before["bicubic"] and cell["classical_lens"] == before["classical_lens"]
    assert [run["command"] for run in again["provenance"]] == [first["provenance"]["command"],
                                                               again["provenance"][1]["command"]]
    assert "--redo classical" in again["provenance"][1]["command"]
    third.main([*common, "--redo", "classical"])  # done: nothing run again, no run added
    assert json.loads(out.read_text())["provenance"] == again["provenance"]


def test_redo_of_a_row_the_file_lacks_is_refused(third, tmp_path, capsys):
    with pytest.raises(SystemExit) as stop:
        third.main(["--out", str(tmp_path / "r.json"), "--cells", "translation:2:4", "--no-vidsr", "--redo", "vidsr"])
    assert stop.value.code == 2 and "--redo vidsr" in capsys.readouterr().err
