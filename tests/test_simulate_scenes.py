"""Scenes: every built-in one loads, knows its size, and averages cells correctly."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from hbis_torch.errors import HbisInputError
from hbis_torch.simulate import (
    BUILTIN_SCENES,
    PHOTOS,
    ImageScene,
    SceneSpec,
    load_scene,
)
from hbis_torch.simulate.rasters import to_gray
from hbis_torch.simulate.scenes import (
    BarTarget,
    EdgesScene,
    GratingScene,
    SiemensStar,
    box_interval,
    square_edge_coverage,
)

SPEC = SceneSpec(size_mm=(1.2, 0.9), pixel_mm=0.015625, detail_mm=0.015625 / 8)


def _points(scene, n=96):
    w, h = scene.size_mm
    x = torch.linspace(-w / 2, w / 2, n, dtype=torch.float64)
    y = torch.linspace(-h / 2, h / 2, n, dtype=torch.float64)
    return torch.stack(torch.meshgrid(x, y, indexing="xy"), -1)


@pytest.mark.parametrize("name", sorted(BUILTIN_SCENES))
def test_every_builtin_scene_loads_with_a_size_and_values_in_range(name):
    scene = load_scene(name, SPEC, seed=4)
    w, h = scene.size_mm
    assert w >= SPEC.size_mm[0] - 1e-9 and h >= SPEC.size_mm[1] - 1e-9  # covers the view
    values = scene.placed_at((0.3, -0.2)).sample(_points(scene) + torch.tensor([0.3, -0.2]), SPEC.detail_mm)
    assert values.dtype == torch.float32 and values.shape == (96, 96)
    assert float(values.min()) >= 0.0 and float(values.max()) <= 1.0
    if name != "flat":
        assert float(values.std()) > 0.01, "a pattern should have some contrast"


def test_procedural_scenes_are_reproducible_and_seeded():
    a = load_scene("words", SPEC, seed=1).image
    b = load_scene("words", SPEC, seed=1).image
    c = load_scene("words", SPEC, seed=2).image
    assert torch.equal(a, b) and not torch.equal(a, c)


def _numeric_cell_average(scene, x, y, side, k=40):
    offsets = ((torch.arange(k, dtype=torch.float64) + 0.5) / k - 0.5) * side
    dy, dx = torch.meshgrid(offsets, offsets, indexing="ij")
    return scene.value(x[:, None] + dx.flatten(), y[:, None] + dy.flatten(), None).mean(1)


@pytest.mark.parametrize(
    "scene",
    [
        SiemensStar(size_mm=(1.0, 1.0), spokes=12),
        BarTarget(size_mm=(1.0, 1.0), bar_widths_mm=(0.03, 0.011, 0.007, 0.004), columns=2),
        EdgesScene(size_mm=(1.0, 1.0), normals_deg=(17.0, 100.0, 250.0), offsets_mm=(0.01, -0.05, 0.1),
                   levels=tuple(np.linspace(0.1, 0.9, 8))),
        GratingScene(size_mm=(1.0, 1.0), period_mm=0.013, angle_deg=33.0),
    ],
    ids=["star", "bars", "edges", "grating"],
)
def test_analytic_cell_averages_match_supersampling(scene):
    side = 0.004
    rng = np.random.default_rng(0)
    x = torch.from_numpy(rng.uniform(-0.45, 0.45, 1500))
    y = torch.from_numpy(rng.uniform(-0.45, 0.45, 1500))
    fast = scene.value(x, y, side)
    slow = _numeric_cell_average(scene, x, y, side)
    err = (fast - slow).abs()
    # exact except the star near its centre and cells where two edges cross
    assert float(torch.quantile(err, 0.99)) < 0.01
    assert float(err.mean()) < 2e-3


def test_box_helpers_are_exact():
    t = torch.linspace(-3, 3, 601, dtype=torch.float64)
    side = 1.3
    k = 4000
    offsets = ((torch.arange(k, dtype=torch.float64) + 0.5) / k - 0.5) * side
    numeric = ((t[:, None] + offsets).abs() <= 0.7).double().mean(1)
    assert float((box_interval(t, 0.7, side) - numeric).abs().max()) < 1e-3
    angle = math.radians(25.0)
    cells = torch.stack(torch.meshgrid(offsets[::40], offsets[::40], indexing="xy"), -1)
    for d in (-0.9, -0.5, -0.1, 0.0, 0.3, 0.8):
        inside = (cells[..., 0] * math.cos(angle) + cells[..., 1] * math.sin(angle) + d >= 0).double().mean()
        exact = square_edge_coverage(torch.tensor([d], dtype=torch.float64), angle, side)
        assert float(exact) == pytest.approx(float(inside), abs=0.02)


def test_image_scene_orientation_size_and_mipmap():
    image = torch.zeros(4, 8)
    image[0, :] = 1.0  # top row bright
    scene = ImageScene(size_mm=(8.0, 4.0), image=image)
    assert scene.pixel_mm == 1.0
    top = scene.sample(torch.tensor([[0.0, -1.5]], dtype=torch.float64))
    bottom = scene.sample(torch.tensor([[0.0, 1.5]], dtype=torch.float64))
    assert float(top) == pytest.approx(1.0) and float(bottom) == pytest.approx(0.0)  # y grows downward
    checker = torch.from_numpy((np.indices((64, 64)).sum(0) % 2).astype(np.float32))
    fine = ImageScene(size_mm=(1.0, 1.0), image=checker)
    pts = torch.rand(500, 2, dtype=torch.float64) - 0.5
    coarse = fine.sample(pts, spacing_mm=4 / 64)  # four raster pixels per sample: averaged
    assert float((coarse - 0.5).abs().max()) < 0.01


def test_photographs_and_image_files(tmp_path):
    import skimage.io

    for name in ("camera", "astronaut", "brick"):
        assert name in PHOTOS
    scene = load_scene("astronaut", SPEC)  # RGB photo -> gray, covering the view
    assert scene.image.ndim == 2 and scene.size_mm[0] >= 1.2 - 1e-9 and scene.size_mm[1] >= 0.9 - 1e-9
    path = tmp_path / "pic.png"
    skimage.io.imsave(path, (np.arange(300 * 200).reshape(200, 300) % 251).astype(np.uint8))
    from_file = load_scene(str(path), SPEC, size_mm=3.0)
    assert from_file.size_mm == (3.0, 2.0) and from_file.name == "pic.png"
    assert load_scene(str(path), SPEC, size_mm=(1.0, 5.0)).size_mm == (1.0, 5.0)
    with pytest.raises(HbisInputError, match="unknown scene 'nope'"):
        load_scene("nope", SPEC)
    with pytest.raises(HbisInputError, match="no such image file"):
        load_scene(str(tmp_path / "missing.png"), SPEC)
    bad = tmp_path / "bad.png"
    bad.write_bytes(b"not an image")
    with pytest.raises(HbisInputError, match="cannot read the image"):
        load_scene(str(bad), SPEC)
    with pytest.raises(HbisInputError, match="scene size"):
        load_scene("siemens-star", SPEC, size_mm=(-1.0, 1.0))


def test_to_gray_and_bad_images():
    assert to_gray(np.full((2, 2, 3), 255, np.uint8)).max() == pytest.approx(1.0, abs=1e-6)
    assert to_gray(np.ones((2, 2), bool)).dtype == np.float32
    with pytest.raises(HbisInputError, match="NaN"):
        ImageScene(size_mm=(1.0, 1.0), image=torch.tensor([[float("nan")]]))
    with pytest.raises(HbisInputError, match="2-D"):
        ImageScene(size_mm=(1.0, 1.0), image=torch.zeros(2, 2, 2))
