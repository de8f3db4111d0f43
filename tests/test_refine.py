"""hbis_torch.reconstruct.classical.refine: a burst's image made consistent with its samples."""

import numpy as np
import pytest
import torch
from scipy.ndimage import gaussian_filter

from hbis_torch.reconstruct.classical.refine import refine_on_samples
from hbis_torch.registration import apply_homography_to_grid
from hbis_torch.simulate.burst import random_motions, simulate_burst

S, H, W = 2, 48, 64


def _psnr(image, truth) -> float:
    b = 4 * S
    error = np.asarray(image, np.float64)[b:-b, b:-b] - truth[b:-b, b:-b]
    return float(-10 * np.log10(np.mean(error**2)))


@pytest.fixture(scope="module")
def burst():
    rng = np.random.default_rng(3)
    truth = np.clip(gaussian_filter(rng.random((S * H, S * W)), 1.2) * 4 - 1.5, 0, 1)
    motions = random_motions(8, (H, W), rng, max_shift=2.0, max_rotation_deg=0.3)
    b = simulate_burst(truth, S, motions, noise=0.005, seed=1, blur_px=0.3)
    frames = torch.from_numpy(np.asarray(b.frames, np.float32) / 255)  # 8-bit frames
    positions = apply_homography_to_grid(torch.from_numpy(motions), torch.arange(H, dtype=torch.float64),
                                         torch.arange(W, dtype=torch.float64))
    return b.truth.astype(np.float64), frames, positions, torch.ones(frames.shape)


def test_the_refined_image_is_nearer_the_truth_than_its_start(burst):
    truth, frames, positions, weights = burst
    start = gaussian_filter(truth, 2.0)  # a start without the scene's detail
    done = refine_on_samples(start, frames, positions, weights, S, 0.3)
    assert done.steps >= 3 and done.stopped_by in ("stall", "iterations")
    assert _psnr(done.image, truth) > _psnr(start, truth) + 3
    # its residual (before its last step) is far below the start's (before the first)
    first = refine_on_samples(start, frames, positions, weights, S, 0.3, max_iterations=1)
    assert done.residual < 0.5 * first.residual


def test_float32_is_enough(burst):
    truth, frames, positions, weights = burst
    start = gaussian_filter(truth, 2.0)
    single = refine_on_samples(start.astype(np.float32), frames, positions, weights, S, 0.3, max_iterations=6)
    double = refine_on_samples(torch.from_numpy(start), frames, positions, weights, S, 0.3, max_iterations=6)
    assert double.image.dtype == torch.float64 and single.image.dtype == torch.float32
    assert single.steps == double.steps
    assert float((single.image.double() - double.image).abs().max()) < 1e-4


def test_a_sample_of_weight_zero_changes_nothing(burst):
    truth, frames, positions, weights = burst
    start = gaussian_filter(truth, 2.0)
    garbage = frames.clone()
    garbage[3] = torch.rand(H, W)
    left_out = weights.clone()
    left_out[3] = 0
    a = refine_on_samples(start, frames[[0, 1, 2, 4, 5, 6, 7]], positions[[0, 1, 2, 4, 5, 6, 7]],
                          weights[[0, 1, 2, 4, 5, 6, 7]], S, 0.3)
    b = refine_on_samples(start, garbage, positions, left_out, S, 0.3)
    assert a.steps == b.steps
    assert float((a.image - b.image).abs().max()) < 1e-5


def test_an_image_of_the_wrong_size_is_refused(burst):
    _, frames, positions, weights = burst
    with pytest.raises(ValueError, match=r"\(S H, S W\)"):
        refine_on_samples(np.zeros((H, W)), frames, positions, weights, S, 0.3)


def test_the_development_script_refuses_a_bad_burst_before_any_work(load_script, tmp_path, capsys):
    dev = load_script("training/dev_refine.py")
    out = tmp_path / "dev.json"
    assert dev.main(["--out", str(out), "--bursts", "spin:2:8"]) == 2
    assert dev.main(["--out", str(out), "--bursts", "shift:5:8"]) == 2
    assert "KIND:S:F" in capsys.readouterr().err and not out.exists()
    rows = {"shift:2:8:1": {"classical_db": 30.0, "classical_unrefined_db": 29.0}}
    assert dev.summary(rows)["S=2"]["classical_refined_minus_unrefined"]["mean_db"] == 1.0
