"""The training-data pipeline: pools of simulated stacks under randomised degradations, each with
its classical image; determinism per seed and index, the ranges drawn, crops and flips, the cache."""

from __future__ import annotations

import numpy as np
import pytest

from hbis_torch.config import Camera, FoveaSystem
from hbis_torch.errors import HbisInputError
from hbis_torch.metrics import psnr
from hbis_torch.training.data import (
    BIT_DEPTHS,
    F_NUMBER,
    FULL_WELL_E,
    HELD_OUT_PHOTOS,
    POOL_KEYS,
    SCENE_WEIGHTS,
    TRAIN_PHOTOS,
    TRAIN_SCENES,
    build_pool,
    crop_example,
    dead_leaves,
    dihedral,
    draw_example,
    example_seed,
    load_pool,
    make_batch,
    natural_image,
    save_pool,
    whole_example,
)


@pytest.fixture(scope="module")
def pool():
    return build_pool(h=2, count=3, size=20, seed=3)


def test_examples_hold_the_classical_image_the_truth_and_two_noise_models(pool):
    for ex in pool:
        assert set(ex) == set(POOL_KEYS) and ex["scene"] in TRAIN_SCENES
        assert ex["base"].shape == ex["truth"].shape == (40, 40)
        assert ex["base"].dtype == ex["truth"].dtype == np.float32
        assert 0 <= ex["base"].min() and ex["base"].max() <= 1
        # the classical image is a reconstruction of this truth, not of another
        assert psnr(ex["truth"], ex["base"]) > 20
        assert ex["noise"].shape == (2, 2) and (ex["noise"] >= 0).all()
        assert ex["noise"][0, 0] > 0  # the sensor model always has shot noise
    base, noise, truth = whole_example(pool[0], 2)
    assert base.shape == (1, 4, 20, 20) and noise.shape == (1, 1, 20, 20) and truth.shape == (1, 1, 40, 40)
    base, noise, truth = make_batch(pool, 2, 8, 5, np.random.default_rng(0))
    assert base.shape == (5, 4, 8, 8) and noise.shape == (5, 1, 8, 8) and truth.shape == (5, 1, 16, 16)
    assert all(a.dtype == np.float32 for a in (base, noise, truth))


def test_examples_depend_only_on_the_pool_seed_and_their_index(pool):
    # Example i is the same whichever share of the pool is built (the ranks of train_sr.py).
    (again,) = build_pool(h=2, count=3, size=20, seed=3, indices=[2])
    for key in POOL_KEYS:
        assert np.array_equal(again[key], pool[2][key]), key
    assert len({example_seed(3, i) for i in range(100)} | {example_seed(4, i) for i in range(100)}) == 200
    draw = draw_example(Camera(), 2, 20, example_seed(3, 1))
    assert draw.roi == tuple(pool[1]["roi"].tolist()) and draw.scene == pool[1]["scene"]
    # The same generator state gives the same batch; another one another batch.
    a = make_batch(pool, 2, 8, 4, np.random.default_rng([0, 0, 7]))
    b = make_batch(pool, 2, 8, 4, np.random.default_rng([0, 0, 7]))
    c = make_batch(pool, 2, 8, 4, np.random.default_rng([0, 0, 8]))
    assert all(np.array_equal(x, y) for x, y in zip(a, b))
    assert not np.array_equal(a[2], c[2])


def test_draws_cover_the_sensor_the_scan_the_optics_and_the_noise():
    cam = Camera()
    h = 4
    draws = [draw_example(cam, h, 64, example_seed(0, i)) for i in range(2000)]
    u0 = np.array([d.roi[0] for d in draws])
    v0 = np.array([d.roi[1] for d in draws])
    assert u0.min() >= 0 and u0.max() <= cam.cols - 64 and v0.min() >= 0 and v0.max() <= cam.rows - 64
    for at_u in (u0 < 0.1 * (cam.cols - 64), u0 > 0.9 * (cam.cols - 64)):  # every corner
        for at_v in (v0 < 0.1 * (cam.rows - 64), v0 > 0.9 * (cam.rows - 64)):
            assert (at_u & at_v).sum() >= 5
    names = [d.scene for d in draws]
    for name, weight in zip(TRAIN_SCENES, SCENE_WEIGHTS):
        assert abs(names.count(name) / len(draws) - weight) < 0.03, name
    # the reference frame anywhere in the scan; both scan solutions; phase errors in half
    assert {d.reference_index for d in draws} == set(range(h * h))
    assert {d.plan_method for d in draws} == {"paper", "exact"}
    assert 0.4 < np.mean([d.phase_error_deg > 0 for d in draws]) < 0.6
    # optics from F 1 to 8, defocus in half, fill factors from 0.5 to 1
    f = np.array([d.f_number for d in draws])
    assert F_NUMBER[0] <= f.min() < 1.2 and 6.5 < f.max() <= F_NUMBER[1]
    assert 0.4 < np.mean([d.sensor.defocus_um > 0 for d in draws]) < 0.6
    fill = np.array([d.sensor.fill_factor for d in draws])
    assert fill.min() < 0.55 and fill.max() > 0.95
    # noise over two decades of full well, every bit depth
    wells = np.array([d.sensor.full_well_e for d in draws])
    assert FULL_WELL_E[0] <= wells.min() < 1500 and 70_000 < wells.max() <= FULL_WELL_E[1]
    assert {d.sensor.bit_depth for d in draws} == set(BIT_DEPTHS)
    assert len({d.noise_seed for d in draws}) == len(draws)


def test_flips_and_transposes_move_the_classical_image_with_its_truth(pool):
    base, truth = pool[0]["base"], pool[0]["truth"]
    error = np.abs(base - truth)
    for k in range(8):
        b, t = dihedral(base, truth, k)
        e = np.abs(b - t)
        assert b.shape == t.shape and np.isclose(e.sum(), error.sum())  # the same pairs, moved
    assert np.array_equal(dihedral(base, truth, 1)[0], base[:, ::-1])
    assert np.array_equal(dihedral(base, truth, 4)[1], truth.T)


def test_crops_take_either_noise_model(pool):
    ex = pool[1]
    seen = set()
    for seed in range(40):
        base, noise, truth = crop_example(ex, 2, 6, np.random.default_rng(seed), augment=False)
        seen.add(round(float(noise.min()), 6))
        assert base.shape == (4, 6, 6) and truth.shape == (1, 12, 12)
    assert len(seen) >= 2  # the sensor model's map and the measured one both appear


def test_sizes_that_do_not_fit_are_refused(pool):
    cam = Camera()
    for size in (0, cam.rows + 1):
        with pytest.raises(HbisInputError, match="does not fit"):
            draw_example(cam, 2, size, 0)
    rng = np.random.default_rng(0)
    for patch in (0, 21):
        with pytest.raises(HbisInputError, match="patch"):
            crop_example(pool[0], 2, patch, rng)
    # A crop of the whole example, unaugmented, is the whole example with one of its noise models.
    wholes = [whole_example(pool[0], 2, measured_noise=m) for m in (False, True)]
    for seed in range(10):
        base, noise, truth = crop_example(pool[0], 2, 20, np.random.default_rng(seed), augment=False)
        assert np.array_equal(base, wholes[0][0][0]) and np.array_equal(truth, wholes[0][2][0])
        assert any(np.array_equal(noise, whole[1][0]) for whole in wholes)


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


def test_dead_leaves_covers_the_raster_with_flat_discs():
    image = dead_leaves((64, 48), np.random.default_rng(1))
    assert image.shape == (64, 48) and image.dtype == np.float32
    assert np.isfinite(image).all() and 0 <= image.min() and image.max() <= 1
    # opaque discs of one grey each: few distinct levels, most neighbours equal
    assert 5 < len(np.unique(image)) < 64 * 48 / 4
    assert np.mean(image[:, 1:] == image[:, :-1]) > 0.5


@pytest.mark.parametrize("name", ["dead-leaves", "natural-field", "photograph"])
def test_natural_images_fill_the_view_in_range_and_clip_when_overexposed(name):
    from hbis_torch.simulate import SceneSpec

    pixel = FoveaSystem().object_pixel_mm
    spec = SceneSpec(size_mm=(40 * pixel, 30 * pixel), pixel_mm=pixel, detail_mm=pixel / 16)
    for seed in range(3):
        scene = natural_image(name, spec, np.random.default_rng(seed))
        assert scene.size_mm == spec.size_mm
        image = scene.image.numpy()
        assert 0 <= image.min() and image.max() <= 1 and image.std() > 0.005
        # raster pixels of 1/8 to 4 sensor pixels
        assert 40 / 4 - 1 <= image.shape[1] <= 40 * 8 + 1
        bright = natural_image(name, spec, np.random.default_rng(seed), exposure=4.0).image.numpy()
        assert bright.max() == 1.0 and np.mean(bright == 1.0) > np.mean(image == 1.0)


def test_natural_rasters_are_read_bilinear_or_bicubic_and_bicubic_keeps_more_detail():
    """Pool version 5: half the natural scenes read their raster by bicubic interpolation, which
    attenuates detail near the raster's Nyquist frequency less than bilinear does."""
    import torch

    from hbis_torch.simulate import SceneSpec
    from hbis_torch.simulate.scenes import ImageScene

    pixel = FoveaSystem().object_pixel_mm
    spec = SceneSpec(size_mm=(40 * pixel, 30 * pixel), pixel_mm=pixel, detail_mm=pixel / 16)
    kinds = [natural_image("dead-leaves", spec, np.random.default_rng(seed)).interpolation for seed in range(16)]
    assert {"bilinear", "bicubic"} == set(kinds)
    raster = torch.from_numpy(np.random.default_rng(0).random((32, 32)).astype(np.float32))
    x = torch.linspace(-0.4, 0.4, 400)
    reads = {}
    for kind in ("bilinear", "bicubic"):
        scene = ImageScene(size_mm=(1.0, 1.0), image=raster, interpolation=kind)
        reads[kind] = scene.value(x[None, :], torch.zeros(1, 1)).numpy()[0]
        assert 0 <= reads[kind].min() and reads[kind].max() <= 1
    # the same raster; bicubic's samples vary more from one to the next (less smoothing)
    assert np.abs(np.diff(reads["bicubic"])).mean() > 1.05 * np.abs(np.diff(reads["bilinear"])).mean()
    with pytest.raises(HbisInputError, match="interpolation"):
        ImageScene(size_mm=(1.0, 1.0), image=raster, interpolation="nearest")


def test_no_held_out_photograph_reaches_a_training_scene(monkeypatch):
    from hbis_torch.training import data as training_data
    from hbis_torch.simulate import SceneSpec
    from hbis_torch.simulate.rasters import PHOTOS, photo

    assert set(HELD_OUT_PHOTOS) <= set(PHOTOS) and len(TRAIN_PHOTOS) >= 8
    assert not set(TRAIN_PHOTOS) & set(HELD_OUT_PHOTOS)
    read = []
    monkeypatch.setattr(training_data, "photo", lambda name: read.append(name) or photo(name))
    pixel = FoveaSystem().object_pixel_mm
    spec = SceneSpec(size_mm=(96 * pixel, 96 * pixel), pixel_mm=pixel, detail_mm=pixel / 16)
    for seed in range(40):
        image = natural_image("photograph", spec, np.random.default_rng(seed)).image.numpy()
        assert image.shape[0] >= 96 / 4 - 1 and image.shape[1] >= 96 / 4 - 1
    assert set(read) <= set(TRAIN_PHOTOS) and len(set(read)) >= 6  # many photographs, never a held-out one


def test_the_measured_noise_row_is_the_lattice_estimate_near_the_sensor_model():
    # What the learned method measures on a stack without a sensor model; a single frame's
    # estimate would be several times too high on detailed scenes.
    from hbis_torch.reconstruct.learned.domain import noise_at_mid_grey

    pool = build_pool(h=4, count=6, size=48, seed=0)
    ratios = [noise_at_mid_grey(ex["noise"][1]) / noise_at_mid_grey(ex["noise"][0]) for ex in pool]
    assert 0.9 < np.median(ratios) < 1.2 and max(ratios) < 2.0, ratios
