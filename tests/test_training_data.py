"""Training data: flips/transposes of a simulated crop are valid scans with a consistent truth."""

import numpy as np
import pytest

from hbis_torch.sr.learned import prepare_inputs
from training.sr_data import build_pool, crop_example, dihedral


@pytest.fixture(scope="module")
def example():
    return build_pool(h=2, count=1, size=20, seed=5)[0]


def nearest_splat(frames, positions, h):
    """Each sample dropped on the output pixel nearest to it, averaged: (hH, hW)."""
    rows, cols = frames.shape[1:]
    x = np.rint(h * (positions[..., 0] + 0.5) - 0.5).astype(int).clip(0, h * cols - 1)
    y = np.rint(h * (positions[..., 1] + 0.5) - 0.5).astype(int).clip(0, h * rows - 1)
    acc = np.zeros((h * rows, h * cols))
    cnt = np.zeros_like(acc)
    np.add.at(acc, (y, x), frames)
    np.add.at(cnt, (y, x), 1)
    return acc / np.maximum(cnt, 1), cnt > 0


def test_every_flip_and_transpose_keeps_samples_where_the_truth_says(example):
    frames, positions, truth = example["frames"], example["positions"], example["truth"]
    errors = []
    for k in range(8):
        f, p, t = dihedral(frames, positions, truth, k)
        splat, hit = nearest_splat(f, p, 2)
        errors.append(np.abs(splat - t)[hit].mean())
        # The reference frame stays the one whose samples are on the grid.
        frames_reg, offsets = prepare_inputs(f, p, 2)
        assert np.abs(offsets[:2, 2:-2, 2:-2]).max() < 1e-3
    # A wrong flip of the positions would put samples far from their truth; all 8 agree.
    assert max(errors) < 1.2 * min(errors) + 1e-3
    assert max(errors) < 0.1


def test_crops_are_shaped_for_the_network(example):
    rng = np.random.default_rng(0)
    frames_reg, offsets, truth = crop_example(example, 2, 8, rng)
    assert frames_reg.shape == (4, 8, 8) and offsets.shape == (8, 8, 8) and truth.shape == (1, 16, 16)
    assert np.isfinite(offsets).all() and np.abs(offsets).max() <= 2
