"""The burst registration's fast paths against the plain computations they replace: the warp onto
the reference (registration/warp.py) against Kornia's warp_perspective, the local fit's tile sums
against an average pool, and the model evidence against a whole-frame blur and a least-squares
solver."""

from __future__ import annotations

import kornia
import numpy as np
import pytest
import torch

from hbis_torch.registration.evidence import SPLINE_NOISE_DROP, TRIM, model_evidence, trimmed_line_mse
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
    """model_evidence's definition, computed plainly: whole frames blurred, the reference read by
    SciPy's cubic spline, every model on the points all of them keep, a least-squares solver."""
    from scipy import ndimage

    F, H, W = grey.shape
    blur = kornia.filters.gaussian_blur2d(grey[:, None], (5, 5), (1.0, 1.0), border_type="reflect")[:, 0]
    step = max(1, int(np.sqrt(H * W / 32768)))
    v, u = np.meshgrid(np.arange(3, H - 3, step), np.arange(3, W - 3, step), indexing="ij")
    points = np.stack((u.ravel(), v.ravel(), np.ones(u.size)))
    independent = max(1.0, (H - 6) * (W - 6) / (4 * np.pi))
    out = {m: {} for m in motions}
    for k in frames:
        values = blur[k][v.ravel(), u.ravel()].double()
        places = {}
        for model, found in motions.items():
            q = found[k] @ points
            places[model] = (q[0] / q[2], q[1] / q[2])
        inside = np.logical_and.reduce([(qu >= 3) & (qu <= W - 4) & (qv >= 3) & (qv <= H - 4)
                                        for qu, qv in places.values()])
        for model, (qu, qv) in places.items():
            target = ndimage.map_coordinates(blur[reference].double().numpy(), [qv[inside], qu[inside]], order=3,
                                             mode="mirror")
            target = torch.from_numpy(target)
            x = values[torch.from_numpy(inside)]
            A = torch.stack((x, torch.ones_like(x)), -1)
            fit = A @ torch.linalg.lstsq(A, target[:, None], driver="gelsd").solution
            # the reference's noise at the spline's places brought to its level at whole pixels
            gain = np.prod([1 - SPLINE_NOISE_DROP * np.sin(np.pi * place[inside]) ** 2 for place in (qu, qv)], 0)
            squared = ((fit[:, 0] - target).pow(2) * torch.from_numpy(2 / (1 + gain))).sort().values
            mse = float(squared[:int(TRIM * len(squared))].mean()) + 1e-20
            n = min(float(len(target)), independent * float(inside.mean()))
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


def _flat_noisy_pair(H: int = 120, W: int = 160, sigma: float = 0.02) -> torch.Tensor:
    """Two frames of one flat grey scene, each with its own noise: nothing but noise to explain."""
    g = torch.Generator().manual_seed(5)
    return (0.5 + sigma * torch.randn((2, H, W), generator=g)).float()


def _spline_noise_gain(f: float, taps: np.ndarray, size: int = 64) -> float:
    """The variance of a cubic B-spline's value at fraction ``f`` of a pixel along one axis, of white
    noise blurred by ``taps``, over its variance at a pixel: the spline's value is a linear sum of
    the samples (the B-spline at the places, through the inverse of its sampled kernel [1, 4, 1] / 6,
    on a periodic line of ``size`` samples), its variance that sum's quadratic form in the blurred
    noise's covariance."""
    def at(place):
        x = np.abs(place)
        return np.where(x < 1, 2 / 3 - x ** 2 + x ** 3 / 2, np.where(x < 2, (2 - x) ** 3 / 6, 0.0))

    w = 2 * np.pi * np.fft.fftfreq(size)
    covariance = np.zeros(size)
    r = len(taps) // 2
    for d in range(-2 * r, 2 * r + 1):
        covariance[d % size] = sum(taps[i] * taps[i + d] for i in range(len(taps)) if 0 <= i + d < len(taps))
    matrix = covariance[(np.arange(size)[:, None] - np.arange(size)[None, :]) % size]

    def variance(fraction):
        beta = at(size // 2 + fraction - np.arange(size))
        weights = np.real(np.fft.ifft(np.fft.fft(beta) / ((4 + 2 * np.cos(w)) / 6)))
        return weights @ matrix @ weights

    return variance(f) / variance(0.0)


def test_the_splines_noise_drop_between_pixels_is_derived_from_the_evidences_blur():
    taps = kornia.filters.get_gaussian_kernel1d(5, 1.0)[0].double().numpy()
    assert 1 - _spline_noise_gain(0.5, taps) == pytest.approx(SPLINE_NOISE_DROP, abs=5e-5)
    for f in (0.1, 0.25, 0.4):  # the sine's shape in between
        assert _spline_noise_gain(f, taps) == pytest.approx(1 - SPLINE_NOISE_DROP * np.sin(np.pi * f) ** 2, abs=3e-4)
    # bilinear reading would drop the noise's variance by a ninth halfway (the old evidence's bias)
    bilinear = 0.5 + 0.5 * sum(taps[i] * taps[i + 1] for i in range(4)) / float(taps @ taps)
    assert bilinear < 0.9


def test_every_model_is_scored_on_the_same_points():
    # A shift of one pixel leaves the last column of points off the reference; an affine motion
    # that pulls the frame's right side in by 0.6 px keeps it. With each model on its own points,
    # the affine motion won by the column alone (n log mse grows more negative with n).
    grey = _flat_noisy_pair()
    H, W = grey.shape[1:]
    shift = np.array([[1, 0, 1.0], [0, 1, 0], [0, 0, 1]])
    squeeze = np.array([[1 - 0.6 / (W - 7), 0, 1 + 3 * 0.6 / (W - 7)], [0, 1, 0], [0, 0, 1.0]])
    motions = {"translation": np.stack((np.eye(3), shift)), "affine": np.stack((np.eye(3), squeeze))}
    evidence = model_evidence(grey, 0, motions, [1])
    assert evidence["translation"][1] < evidence["affine"][1]


def test_a_trimmed_line_fit_of_a_constant_leaves_the_mean():
    x = torch.full((100,), 0.5, dtype=torch.float64)
    y = torch.linspace(0, 1, 100, dtype=torch.float64)
    A = torch.stack((x, torch.ones_like(x)), -1)
    fit = A @ torch.linalg.lstsq(A, y[:, None], driver="gelsd").solution
    squared = (fit[:, 0] - y).pow(2).sort().values
    assert trimmed_line_mse(x, y) == pytest.approx(float(squared[:75].mean()), rel=1e-9)
