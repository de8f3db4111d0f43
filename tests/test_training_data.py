"""Training data: flips/transposes of a simulated crop are valid scans with a consistent truth."""

import numpy as np
import pytest

from hbis_torch.reconstruct.learned import prepare_inputs
from hbis_torch.reconstruct.learned.training_data import (NATURAL_SCENES, NATURAL_SHARE, SCENE_WEIGHTS, TRAIN_SCENES,
                                                        build_pool, crop_example, dead_leaves, dihedral, natural_image,
                                                        scene_weights)


@pytest.fixture(scope="module")
def example():
    return build_pool(h=2, count=1, size=20, seed=7)[0]  # a words scene


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
    # A wrong flip of the positions would put samples far from their truth; all 8 agree ...
    assert max(errors) < 1.2 * min(errors) + 1e-3
    # ... and they are well below the error of frames flipped without their positions.
    wrong, hit = nearest_splat(frames[..., ::-1], positions, 2)
    assert max(errors) < 0.7 * np.abs(wrong - truth)[hit].mean()
    assert max(errors) < 0.1


def test_crops_are_shaped_for_the_network(example):
    rng = np.random.default_rng(0)
    frames_reg, offsets, truth = crop_example(example, 2, 8, rng)
    assert frames_reg.shape == (4, 8, 8) and offsets.shape == (8, 8, 8) and truth.shape == (1, 16, 16)
    assert np.isfinite(offsets).all() and np.abs(offsets).max() <= 2


def test_dead_leaves_covers_the_raster_with_flat_discs():
    image = dead_leaves((64, 48), np.random.default_rng(1))
    assert image.shape == (64, 48) and image.dtype == np.float32
    assert np.isfinite(image).all() and 0 <= image.min() and image.max() <= 1
    # opaque discs of one grey each: few distinct levels, most neighbours equal
    assert 5 < len(np.unique(image)) < 64 * 48 / 4
    assert np.mean(image[:, 1:] == image[:, :-1]) > 0.5


@pytest.mark.parametrize("name", ["dead-leaves", "natural-field"])
def test_natural_images_fill_the_view_in_range(name):
    from hbis_torch.config import FoveaSystem
    from hbis_torch.simulate import SceneSpec

    pixel = FoveaSystem().object_pixel_mm
    spec = SceneSpec(size_mm=(40 * pixel, 30 * pixel), pixel_mm=pixel, detail_mm=pixel / 16)
    for seed in range(3):
        scene = natural_image(name, spec, np.random.default_rng(seed))
        assert scene.size_mm == spec.size_mm
        image = scene.image.numpy()
        assert 0 <= image.min() and image.max() <= 1 and image.std() > 0.005
        # raster pixels of 1/4 to 4 sensor pixels
        assert 40 / 4 - 1 <= image.shape[1] <= 40 * 4 + 1


def test_natural_share_rescales_the_mix_and_keeps_the_standard_one():
    assert scene_weights() is SCENE_WEIGHTS  # the standard pools stay bit for bit
    assert np.isclose(sum(SCENE_WEIGHTS[-len(NATURAL_SCENES):]), NATURAL_SHARE)
    w = np.array(scene_weights(0.55))
    natural = np.isin(TRAIN_SCENES, NATURAL_SCENES)
    assert np.isclose(w.sum(), 1.0) and np.isclose(w[natural].sum(), 0.55)
    # Proportions within each group are kept.
    base = np.array(SCENE_WEIGHTS)
    assert np.allclose(w[~natural] / w[~natural].sum(), base[~natural] / base[~natural].sum())
    assert np.allclose(w[natural] / w[natural].sum(), base[natural] / base[natural].sum())
    with pytest.raises(ValueError, match="natural_share"):
        scene_weights(1.5)
