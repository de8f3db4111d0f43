"""The training-data pipeline's pools: shapes, determinism per seed and index, where on the sensor,
the scene and noise mix, the grid convention, edge cases and the pool cache on disk.

(The flips/transposes of crops and the natural scenes are tested in test_training_data.py.)
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from hbis_torch.config import FoveaSystem
from hbis_torch.errors import HbisInputError
from hbis_torch.reconstruct.learned.training_data import (
    FULL_WELL_E,
    NATURAL_SCENES,
    POOL_KEYS,
    SCENE_WEIGHTS,
    TRAIN_SCENES,
    build_pool,
    crop_example,
    draw_example,
    example_seed,
    load_pool,
    make_batch,
    save_pool,
    whole_example,
)
from hbis_torch.scan import plan_scan


@pytest.fixture(scope="module")
def pool():
    return build_pool(h=2, count=3, size=20, seed=3)  # example 0 is a words scene


def test_examples_have_the_documented_shapes_and_ranges(pool):
    cam = FoveaSystem().camera
    ref = plan_scan(FoveaSystem(), 2).reference_index
    for ex in pool:
        assert set(ex) == set(POOL_KEYS) and ex["scene"] in TRAIN_SCENES
        assert ex["frames"].shape == (4, 20, 20) and ex["frames"].dtype == np.float32
        assert ex["positions"].shape == (4, 20, 20, 2) and ex["positions"].dtype == np.float32
        assert ex["truth"].shape == (40, 40) and ex["truth"].dtype == np.float32
        assert 0 <= ex["frames"].min() and ex["frames"].max() <= 1
        assert 0 <= ex["truth"].min() and ex["truth"].max() <= 1 and ex["truth"].std() > 0.01
        u0, v0, w, h = ex["roi"].tolist()
        assert (w, h) == (20, 20) and 0 <= u0 <= cam.cols - 20 and 0 <= v0 <= cam.rows - 20
        # the reference frame defines the ROI-local grid; the others sit off it
        grid = np.stack(np.meshgrid(np.arange(20.0), np.arange(20.0), indexing="xy"), -1)
        assert np.abs(ex["positions"][ref] - grid).max() < 1e-5
        others = [k for k in range(4) if k != ref]
        assert min(np.abs(ex["positions"][k] - grid).max() for k in others) > 0.2
    frames, offsets, truth = whole_example(pool[0], 2)
    assert frames.shape == (1, 4, 20, 20) and offsets.shape == (1, 8, 20, 20) and truth.shape == (1, 1, 40, 40)
    frames, offsets, truth = make_batch(pool, 2, 8, 5, np.random.default_rng(0), noise_prob=1.0, noise_max=0.05)
    assert frames.shape == (5, 4, 8, 8) and offsets.shape == (5, 8, 8, 8) and truth.shape == (5, 1, 16, 16)
    assert all(a.dtype == np.float32 for a in (frames, offsets, truth))
    assert 0 <= frames.min() and frames.max() <= 1  # extra noise is clipped as a sensor would


def test_examples_depend_only_on_the_pool_seed_and_their_index(pool):
    # Example i is the same whichever share of the pool is built (the ranks of train_sr.py).
    (again,) = build_pool(h=2, count=3, size=20, seed=3, indices=[2])
    for key in POOL_KEYS:
        assert np.array_equal(again[key], pool[2][key]), key
    assert not np.array_equal(pool[0]["roi"], pool[1]["roi"])
    (other,) = build_pool(h=2, count=1, size=20, seed=4)
    assert not np.array_equal(other["frames"], pool[0]["frames"])
    assert len({example_seed(3, i) for i in range(100)} | {example_seed(4, i) for i in range(100)}) == 200
    # The draw says what was simulated.
    draw = draw_example(FoveaSystem(), 20, example_seed(3, 1))
    assert draw.roi == tuple(pool[1]["roi"].tolist()) and draw.scene == pool[1]["scene"]
    # The same generator state gives the same batch; another one another batch.
    a = make_batch(pool, 2, 8, 4, np.random.default_rng([0, 0, 7]), 0.5, 0.06)
    b = make_batch(pool, 2, 8, 4, np.random.default_rng([0, 0, 7]), 0.5, 0.06)
    c = make_batch(pool, 2, 8, 4, np.random.default_rng([0, 0, 8]), 0.5, 0.06)
    assert all(np.array_equal(x, y) for x, y in zip(a, b))
    assert not np.array_equal(a[2], c[2])


def test_rois_cover_the_whole_sensor_and_the_mix_follows_its_weights():
    system = FoveaSystem()
    cam = system.camera
    draws = [draw_example(system, 64, example_seed(0, i)) for i in range(3000)]
    u0 = np.array([d.roi[0] for d in draws])
    v0 = np.array([d.roi[1] for d in draws])
    assert u0.min() >= 0 and u0.max() <= cam.cols - 64 and v0.min() >= 0 and v0.max() <= cam.rows - 64
    assert all(d.roi[2:] == (64, 64) for d in draws)
    # Every corner of the sensor, where pixels move most unevenly, is visited.
    near_u = (u0 < 0.1 * (cam.cols - 64), u0 > 0.9 * (cam.cols - 64))
    near_v = (v0 < 0.1 * (cam.rows - 64), v0 > 0.9 * (cam.rows - 64))
    for at_u in near_u:
        for at_v in near_v:
            assert (at_u & at_v).sum() >= 10
    # Scenes in the proportions of the mix, exposures from dim to bright.
    names = [d.scene for d in draws]
    for name, weight in zip(TRAIN_SCENES, SCENE_WEIGHTS):
        assert abs(names.count(name) / len(draws) - weight) < 0.03, name
    natural = np.mean([d.scene in NATURAL_SCENES for d in draws_of_share(0.55)])
    assert abs(natural - 0.55) < 0.04
    wells = np.array([d.full_well_e for d in draws])
    assert FULL_WELL_E[0] <= wells.min() < 2500 and 25000 < wells.max() <= FULL_WELL_E[1]
    assert len({d.noise_seed for d in draws}) == len(draws) and len({d.scene_seed for d in draws}) == len(draws)


def draws_of_share(share: float, count: int = 1000):
    return [draw_example(FoveaSystem(), 64, example_seed(1, i), natural_share=share) for i in range(count)]


def test_reference_frame_is_the_truth_pooled_over_h_blocks_up_to_noise(pool):
    """The grid convention (docs/data.md): reference pixel (x, y) integrates output pixels
    h x .. h x + h - 1; a truth misplaced by one LR pixel would be far worse."""
    ex = pool[0]
    ref = plan_scan(FoveaSystem(), 2).reference_index
    pooled = torch.nn.functional.avg_pool2d(torch.from_numpy(ex["truth"])[None, None], 2)[0, 0].numpy()
    frame = ex["frames"][ref]
    error = np.abs(pooled - frame).mean()
    shifted = min(np.abs(pooled[:, 1:] - frame[:, :-1]).mean(), np.abs(pooled[1:] - frame[:-1]).mean())
    assert error < 0.02 and error < 0.3 * shifted


def test_sizes_that_do_not_fit_are_refused(pool):
    system = FoveaSystem()
    cam = system.camera
    for size in (0, cam.rows + 1):
        with pytest.raises(HbisInputError, match="does not fit"):
            draw_example(system, size, 0)
    full = draw_example(system, cam.rows, 0)  # the largest square that fits
    assert full.roi[1] == 0 and 0 <= full.roi[0] <= cam.cols - cam.rows
    rng = np.random.default_rng(0)
    for patch in (0, 21):
        with pytest.raises(HbisInputError, match="patch"):
            crop_example(pool[0], 2, patch, rng)
    # A crop of the whole example, unaugmented, is the whole example.
    frames, offsets, truth = crop_example(pool[0], 2, 20, rng, augment=False)
    whole = whole_example(pool[0], 2)
    assert np.array_equal(frames, whole[0][0]) and np.array_equal(offsets, whole[1][0])
    assert np.array_equal(truth, whole[2][0])
    with pytest.raises(ValueError, match="natural_share"):
        draw_example(system, 20, 0, natural_share=-0.1)


def test_pool_round_trips_through_its_npz_file(pool, tmp_path):
    path = tmp_path / "pool.npz"
    save_pool(path, pool)
    assert [p.name for p in tmp_path.iterdir()] == ["pool.npz"]  # written atomically, no leftovers
    loaded = load_pool(path)
    assert len(loaded) == len(pool)
    for a, b in zip(pool, loaded):
        for key in POOL_KEYS:
            assert np.asarray(a[key]).dtype == b[key].dtype and np.array_equal(a[key], b[key]), key
        assert str(b["scene"]) == a["scene"]
    assert all(np.array_equal(x, y) for x, y in zip(whole_example(pool[1], 2), whole_example(loaded[1], 2)))
