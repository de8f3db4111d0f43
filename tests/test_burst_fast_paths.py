"""The burst registration's fast paths against the plain computations they replace: the warp onto
the reference (registration/warp.py) against Kornia's warp_perspective, the local fit's tile sums
against an average pool, and the model evidence against a whole-frame blur and a least-squares
solver."""

from __future__ import annotations

import kornia
import numpy as np
import pytest
import torch

from hbis_torch.registration.evidence import TRIM, model_evidence, trimmed_line_mse
from hbis_torch.registration.homography import N_PARAMS
from hbis_torch.registration.local import _tile_sums
from hbis_torch.registration.warp import warp_onto_reference


def _texture(H: int, W: int, seed: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    noise = torch.rand((1, 1, H, W), generator=g)
    return kornia.filters.gaussian_blur2d(noise, (9, 9), (2.0, 2.0), border_type="reflect")[0, 0]


def _motion(kind: str, W: int, rng) -> np.ndarray:
    m = np.eye(3)
    m[:2, :2] += rng.normal(0, 3e-3, (2, 2))
    m[:2, 2] = rng.normal(0, 3, 2)
    if kind == "homography":
        m[2, :2] = rng.normal(0, 1e-5, 2) * 640 / W
    return m


@pytest.mark.parametrize("kind", ["translation", "affine", "homography"])
@pytest.mark.parametrize("shape", [(48, 64), (150, 200)])
def test_the_warp_onto_the_reference_is_kornias(kind, shape):
    H, W = shape
    rng = np.random.default_rng(len(kind) + H)
    motion = _motion(kind, W, rng) if kind != "translation" else np.array([[1, 0, 2.3], [0, 1, -1.7], [0, 0, 1.0]])
    image = _texture(H, W, 3)[None, None]
    ones = torch.ones_like(image)
    theirs = kornia.geometry.transform.warp_perspective(torch.cat((image, ones), 1),
                                                         torch.as_tensor(motion, dtype=torch.float32)[None], (H, W),
                                                         mode="bilinear", padding_mode="zeros", align_corners=True)[0]
    ours, valid = warp_onto_reference(image, motion)
    # the same covered pixels but where a pixel maps within float32 rounding of the 1e-3 px margin
    assert int((valid != (theirs[1] > 0.999)).sum()) <= 2
    assert 0.5 * H * W < int(valid.sum()) < H * W  # the test covers an edge
    both = valid & (theirs[1] > 0.999)
    assert float((ours[0, 0] - theirs[0])[both].abs().max()) < 2e-5


def test_the_identity_warp_returns_the_frame():
    image = _texture(40, 50, 1)[None, None]
    ours, valid = warp_onto_reference(image, np.eye(3))
    assert bool(valid.all()) and float((ours - image).abs().max()) < 1e-6


def test_a_degenerate_motion_covers_nothing():
    _, valid = warp_onto_reference(_texture(40, 50, 1)[None, None], np.zeros((3, 3)))
    assert not bool(valid.any())


@pytest.mark.parametrize("shape", [(64, 96), (70, 101)])
def test_tile_sums_are_an_average_pool_times_each_tiles_pixel_count(shape):
    H, W = shape
    x = torch.rand((3, H, W), generator=torch.Generator().manual_seed(0))
    pooled = torch.nn.functional.avg_pool2d(x[None], 16, 16, ceil_mode=True, count_include_pad=False)[0]
    count = torch.nn.functional.avg_pool2d(torch.ones((1, 1, H, W)), 16, 16, ceil_mode=True,
                                           count_include_pad=False, divisor_override=1)[0]
    sums = _tile_sums(x, 16)
    assert sums.shape == pooled.shape
    assert torch.allclose(sums, pooled * count, rtol=1e-5, atol=1e-4)


def _evidence_as_written(grey, reference, motions, frames):
    """model_evidence's definition, computed plainly: whole frames blurred, a least-squares solver."""
    F, H, W = grey.shape
    blur = kornia.filters.gaussian_blur2d(grey[:, None], (5, 5), (1.0, 1.0), border_type="replicate")[:, 0]
    step = max(1, int(np.sqrt(H * W / 32768)))
    v, u = np.meshgrid(np.arange(3, H - 3, step), np.arange(3, W - 3, step), indexing="ij")
    points = np.stack((u.ravel(), v.ravel(), np.ones(u.size)))
    independent = max(1.0, (H - 6) * (W - 6) / (4 * np.pi))
    out = {m: {} for m in motions}
    for k in frames:
        values = blur[k][v.ravel(), u.ravel()].double()
        for model, found in motions.items():
            q = found[k] @ points
            qu, qv = q[0] / q[2], q[1] / q[2]
            inside = torch.from_numpy((qu >= 3) & (qu <= W - 4) & (qv >= 3) & (qv <= H - 4))
            grid = torch.from_numpy(np.stack((2 * qu / (W - 1) - 1, 2 * qv / (H - 1) - 1), -1)).float()
            target = torch.nn.functional.grid_sample(blur[reference][None, None], grid[None, None],
                                                     align_corners=True)[0, 0, 0].double()[inside]
            x = values[inside]
            A = torch.stack((x, torch.ones_like(x)), -1)
            fit = A @ torch.linalg.lstsq(A, target[:, None], driver="gelsd").solution
            squared = (fit[:, 0] - target).pow(2).sort().values
            mse = float(squared[:int(TRIM * len(squared))].mean()) + 1e-20
            n = min(float(len(target)), independent * float(inside.double().mean()))
            out[model][k] = n * np.log(mse) + N_PARAMS[model] * np.log(n)
    return out


def test_the_model_evidence_is_its_definition():
    H, W = 90, 120
    scene = _texture(H + 20, W + 20, 7)
    rng = np.random.default_rng(2)
    true = [np.eye(3)] + [_motion("affine", W, rng) for _ in range(3)]
    frames = [scene[10:10 + H, 10:10 + W]]
    for m in true[1:]:  # the frames: the scene seen through each motion, plus a little noise
        warped, _ = warp_onto_reference(scene[None, None], np.array([[1, 0, 10], [0, 1, 10], [0, 0, 1.0]])
                                        @ np.linalg.inv(m) @ np.array([[1, 0, -10], [0, 1, -10], [0, 0, 1.0]]))
        frames.append(warped[0, 0, 10:10 + H, 10:10 + W] + 0.003 * torch.randn(H, W, generator=torch.Generator()))
    grey = torch.stack(frames).float()
    translation = np.array(true)
    translation[:, :2, :2], translation[:, 2, :2] = np.eye(2), 0
    motions = {"translation": translation, "affine": np.array(true)}
    ours, plain = model_evidence(grey, 0, motions, [1, 2, 3]), _evidence_as_written(grey, 0, motions, [1, 2, 3])
    for model in motions:
        for k in (1, 2, 3):
            assert ours[model][k] == pytest.approx(plain[model][k], rel=1e-5)
    assert all(ours["affine"][k] < ours["translation"][k] for k in (1, 2, 3))  # the true model wins


def test_a_trimmed_line_fit_of_a_constant_leaves_the_mean():
    x = torch.full((100,), 0.5, dtype=torch.float64)
    y = torch.linspace(0, 1, 100, dtype=torch.float64)
    A = torch.stack((x, torch.ones_like(x)), -1)
    fit = A @ torch.linalg.lstsq(A, y[:, None], driver="gelsd").solution
    squared = (fit[:, 0] - y).pow(2).sort().values
    assert trimmed_line_mse(x, y) == pytest.approx(float(squared[:75].mean()), rel=1e-9)
