"""Bursts for training (hbis_torch.training.burst_data) and for the held-out matrix
(hbis_torch.training.heldout_burst), and the blur of the simulated bursts."""

from __future__ import annotations

import json

import numpy as np
import pytest

from hbis_torch.metrics import psnr
from hbis_torch.reconstruct.single_frame import single_frame
from hbis_torch.simulate.burst import random_motions, simulate_burst
from hbis_torch.training.burst_data import NOISE, build_burst_pool, simulate_burst_example, training_domain_with_bursts
from hbis_torch.training.data import POOL_KEYS, crop_example, training_domain
from hbis_torch.training.heldout_burst import BURST_CONDITIONS, BurstCondition, make_burst, motions_for
from test_training import history, run


def test_a_burst_example_is_a_pool_example_and_its_seed_fixes_it():
    example = simulate_burst_example(2, 24, seed=5)
    assert set(POOL_KEYS) <= set(example) and example["scene"].startswith("burst:")
    assert example["base"].shape == example["truth"].shape == (48, 48)
    assert np.isfinite(example["base"]).all() and example["noise"].shape == (2, 2)
    assert example["noise"][0, 0] == 0 and 0 < example["noise"][0, 1] <= NOISE[1] ** 2  # Gaussian: (0, sigma^2)
    again = simulate_burst_example(2, 24, seed=5)
    np.testing.assert_array_equal(example["base"], again["base"])
    base, noise, truth = crop_example(example, 2, 16, np.random.default_rng(0))  # the scans' crops take it
    assert base.shape == (4, 16, 16) and truth.shape == (1, 32, 32)


def test_the_burst_pool_follows_the_example_seeds():
    pool = build_burst_pool(3, 3, 24, seed=1, indices=[2, 0])
    alone = build_burst_pool(3, 3, 24, seed=1, indices=[0])
    np.testing.assert_array_equal(pool[1]["truth"], alone[0]["truth"])
    assert pool[0]["base"].shape == (72, 72)


def test_the_domain_with_bursts_widens_only_the_noise():
    scans, both = training_domain(), training_domain_with_bursts()
    assert both["cutoff_cycles_per_px"] == scans["cutoff_cycles_per_px"]
    assert both["noise_at_mid_grey"][0] <= scans["noise_at_mid_grey"][0]
    assert both["noise_at_mid_grey"][1] == pytest.approx(np.hypot(NOISE[1], 1 / (255 * 12**0.5)))


def test_a_lens_blur_softens_the_frames_and_not_the_truth():
    truth = np.zeros((48, 48))
    truth[:, 24:] = 1.0
    motions = random_motions(3, (24, 24), np.random.default_rng(0), 1.0)
    sharp = simulate_burst(truth, 2, motions, noise=0.0)
    soft = simulate_burst(truth, 2, motions, noise=0.0, blur_px=0.6)
    np.testing.assert_array_equal(sharp.truth, soft.truth)
    edge = lambda frames: np.abs(np.diff(frames.astype(float), axis=2)).max()  # noqa: E731
    assert edge(soft.frames) < 0.8 * edge(sharp.frames)


def test_a_held_out_burst_pixel_averages_its_footprint():
    """No noise to speak of, no motion: at S = 2 the (2S)^2 bilinear reads of a pixel weigh the
    output pixels 1, 7, 7, 1 / 16 per axis (its 2 x 2 block and half a pixel's softening)."""
    from scipy.ndimage import correlate1d

    still = BurstCondition("still", frames=2, max_shift_px=0.0, full_well_e=1e9, read_noise_e=0.0, bit_depth=16)
    frames, truth, bits = make_burst(still, "camera", 2, 16, seed=0)
    kernel = np.array([1, 7, 7, 1]) / 16  # output pixels 2u - 1 .. 2u + 2 for frame pixel u
    soft = correlate1d(correlate1d(truth.astype(np.float64), kernel, 0, mode="nearest", origin=-1), kernel, 1,
                       mode="nearest", origin=-1)
    np.testing.assert_allclose(frames[0] / (2**bits - 1), soft[::2, ::2], atol=1e-3)
    np.testing.assert_allclose(frames[0], frames[1], atol=8)  # the same pixels; the shot noise of 1e9 e-


def test_held_out_motions_and_the_moving_object():
    rng = np.random.default_rng(0)
    motions = motions_for(BURST_CONDITIONS[3], 32, rng)  # rotation and zoom
    assert np.allclose(motions[0], np.eye(3)) and not np.allclose(motions[1][:2, :2], np.eye(2))
    moving = next(c for c in BURST_CONDITIONS if c.moving_object)
    frames, truth, _ = make_burst(moving, "astronaut", 2, 24, seed=1)
    assert frames.shape == (moving.frames, 24, 24) and truth.shape == (48, 48)
    # frames 1, 3, ... show the object: they differ from the reference far more than noise does
    still = np.abs(frames[2].astype(float) - frames[0]).mean()
    assert np.abs(frames[1].astype(float) - frames[0]).mean() > 2 * still


def test_a_held_out_burst_super_resolves_past_its_reference():
    from hbis_torch.capture.burst import assemble_burst
    from hbis_torch.reconstruct import reconstruct

    from hbis_torch.training.heldout import score

    frames, truth, bits = make_burst(BURST_CONDITIONS[0], "camera", 2, 48, seed=3)
    stack, _ = assemble_burst(frames, 2, bit_depth=bits)
    one = single_frame(frames[0] / (2**bits - 1), 2)
    assert score(reconstruct(stack, "classical"), truth, 2) > score(one, truth, 2) + 2.0


def test_training_takes_bursts_into_its_pool(tmp_path):
    result = run(["max_steps=2", "eval_interval=2", "burst_pool_size=2", "burst_roi=24", "burst_val_size=1"],
                 tmp_path / "bursts")
    assert result.returncode == 0, result.stderr[-2000:]
    assert "simulated 2 burst stacks" in result.stdout and "simulated 1 burstval stacks" in result.stdout
    saved = json.loads((tmp_path / "bursts" / "history.json").read_text())["config"]
    assert saved["burst_pool_size"] == 2 and len(history(tmp_path / "bursts")) >= 1
