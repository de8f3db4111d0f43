"""training/eval_third_renderer.py: its renderer keeps the project's grid conventions (an LR pixel
is the mean of its S x S output pixels, pixel centres at integers, homographies frame px ->
reference px), so that its truth and frames line up as the package assumes."""

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


def test_bad_cells_are_refused_before_any_work(third, tmp_path, capsys):
    with pytest.raises(SystemExit) as stop:
        third.main(["--out", str(tmp_path / "r.json"), "--cells", "spin:2:8", "--no-vidsr"])
    assert stop.value.code == 2
    assert "--cells spin:2:8" in capsys.readouterr().err
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
