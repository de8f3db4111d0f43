"""Registration of shifted frames: known motions recovered, failures flagged, bad input refused."""

import numpy as np
import pytest
import torch
from scipy import ndimage
from skimage import data

from hbis_torch.errors import HbisInputError
from hbis_torch.registration import (
    apply_homography,
    bspline_sample,
    gaussian_kernel,
    homographies_from_grid,
    homographies_from_positions,
    prefilter,
    register_stack,
)
from hbis_torch.registration.bspline import _spline_fetch
from hbis_torch.sensor.noise import mean_and_spread

H_FACTOR = 4  # frames are box averages of h x h photo pixels

pytestmark = pytest.mark.usefixtures("one_thread")


def _photo() -> np.ndarray:
    return data.camera().astype(np.float64) / 255.0


def shifted_frames(shifts, snr_db=40.0, seed=0, image=None, crop=8):
    """Frames of a 512 px photo box-averaged 4 x 4, each with its content moved by shifts[k]
    (du, dv) in frame pixels (an exact Fourier shift of the photo, then the pixel's box), so
    that content at (u, v) of frame k sits at (u, v) - shifts[k] in frame 0 when shifts[0] = 0.
    """
    img = _photo() if image is None else image
    n = img.shape[0]
    spectrum = np.fft.fft2(img)
    k = np.fft.fftfreq(n)
    out = []
    for du, dv in shifts:
        moved = np.real(np.fft.ifft2(spectrum * np.exp(-2j * np.pi * (k[None, :] * du + k[:, None] * dv) * H_FACTOR)))
        m = n // H_FACTOR
        out.append(moved.reshape(m, H_FACTOR, m, H_FACTOR).mean(axis=(1, 3))[crop:-crop, crop:-crop])
    out = np.stack(out)
    rng = np.random.default_rng(seed)
    return out + rng.normal(0, out[0].std() * 10 ** (-snr_db / 20), out.shape)


@pytest.fixture(scope="module")
def shifts():
    rng = np.random.default_rng(3)
    s = rng.uniform(-1, 1, (9, 2))
    s[0] = 0
    return s


@pytest.fixture(scope="module")
def frames(shifts):
    return torch.tensor(shifted_frames(shifts))


def _centre_error(reg, shifts, frames):
    H, W = frames.shape[-2:]
    d = reg.displacement((W - 1) / 2, (H - 1) / 2).numpy()
    return np.abs(d + shifts).max(axis=1)


def test_known_translations_are_recovered(frames, shifts):
    reg = register_stack(frames, 0)
    assert reg.model == "translation"  # the data needs nothing richer
    err = _centre_error(reg, shifts, frames)
    assert err.max() < 0.01, err
    assert bool(reg.ok.all()) and float(reg.confidence.min()) > 0.8
    assert reg.messages == []
    assert torch.equal(reg.homographies[0], torch.eye(3, dtype=torch.float64))


def test_float32_agrees_with_float64(frames):
    a = register_stack(frames[:4], 0, model="translation", dtype=torch.float32).homographies
    b = register_stack(frames[:4], 0, model="translation", dtype=torch.float64).homographies
    pts = torch.tensor([[0.0, 0.0], [95.0, 95.0]], dtype=torch.float64)
    assert (apply_homography(a, pts) - apply_homography(b, pts)).abs().max() < 1e-3


def test_similarity_motion_is_chosen_and_recovered():
    """A small rotation and zoom about the centre: auto must pick a richer model and map the
    frame's corners to within 0.02 px."""
    img = _photo()
    motions = [(0.0, 0.0, 0.0, 1.0), (0.3, -0.2, 0.2, 1.0015), (-0.4, 0.5, -0.25, 0.998), (0.1, 0.7, 0.15, 1.001)]
    frames, truths = [], []
    c = (img.shape[0] - 1) / 2
    for tx, ty, angle_deg, zoom in motions:
        a = np.deg2rad(angle_deg)
        rot = zoom * np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
        # photo px -> frame content: out(x) = img(R^-1 (x - c - t h) + c), (row, col) order for ndimage
        t = np.array([tx, ty]) * H_FACTOR
        inv = np.linalg.inv(rot)
        matrix = inv[::-1, ::-1]
        offset = (np.array([c, c]) - inv @ (np.array([c, c]) + t))[::-1]
        moved = ndimage.affine_transform(img, matrix, offset=offset, order=3, mode="reflect")
        m = img.shape[0] // H_FACTOR
        frames.append(moved.reshape(m, H_FACTOR, m, H_FACTOR).mean(axis=(1, 3))[8:-8, 8:-8])
        # frame px (u, v) -> reference px: undo the motion in photo px, then back to frame px
        truths.append((rot, t))
    frames = np.stack(frames)
    frames += np.random.default_rng(1).normal(0, 0.01 * frames[0].std(), frames.shape)
    reg = register_stack(torch.tensor(frames), 0)
    assert reg.model in ("similarity", "homography")
    corners = np.array([[0.0, 0.0], [95.0, 0.0], [0.0, 95.0], [95.0, 95.0]])
    for k, (rot, t) in enumerate(truths):
        photo_pts = (corners + 8 + 0.5) * H_FACTOR - 0.5  # frame px centre -> photo px
        ref_photo = np.linalg.inv(rot) @ (photo_pts - c - t).T
        expected = (ref_photo.T + c + 0.5) / H_FACTOR - 0.5 - 8
        got = apply_homography(reg.homographies[k:k + 1], torch.tensor(corners))[0].numpy()
        assert np.abs(got - expected).max() < 0.02, (k, got - expected)


def test_occlusion_is_flagged_and_left_out(shifts):
    frames = shifted_frames(shifts)
    frames[4, 20:60, 30:70] = 0.5  # a flat occluder over a sixth of the frame
    reg = register_stack(torch.tensor(frames), 0)
    assert any("frame 4" in m and "do not match" in m for m in reg.messages)
    # The rest of the frame still registers, to the 0.02 px accuracy goal of the registration.
    assert _centre_error(reg, shifts, frames)[4] < 0.02
    assert float(reg.confidence[4]) < float(reg.confidence[3])


def test_a_frame_of_another_scene_is_not_ok(shifts):
    frames = shifted_frames(shifts)
    other = data.astronaut().mean(-1)[:512, :512] / 255.0
    frames[3] = shifted_frames([(0.0, 0.0)], image=other)[0]
    reg = register_stack(torch.tensor(frames), 0)
    assert not bool(reg.ok[3]) and bool(reg.ok[[0, 1, 2, 4]].all())
    assert any(m.startswith("frame 3 does not match") for m in reg.messages)


def test_low_texture_is_flagged(shifts):
    faint = np.full((512, 512), 0.5) + 0.001 * _photo()
    frames = shifted_frames(shifts, image=faint, snr_db=200)
    frames += np.random.default_rng(2).normal(0, 0.002, frames.shape)  # noise swamps the texture
    reg = register_stack(torch.tensor(frames), 0)
    assert not bool(reg.ok[1:].any())
    assert any("too little texture" in m for m in reg.messages)


def test_a_motion_the_model_cannot_hold_is_not_called_too_little_texture():
    from hbis_torch.training.handheld_render import render_burst

    burst = render_burst("similarity", 2, 2, 320, 240, seed=0)
    turned = burst.frames.astype(np.float32) / 65535
    turned[1] = ndimage.rotate(turned[0], 2.0, reshape=False, order=3, mode="reflect")  # 2 deg: 7 px at the corners
    reg = register_stack(torch.tensor(turned), 0, model="translation")
    assert not bool(reg.ok[1])
    assert any("its motion does not fit it" in m for m in reg.messages), reg.messages
    assert not any("too little texture" in m for m in reg.messages)


def test_flat_frame_is_not_ok(frames):
    bad = frames.clone()
    bad[2] = 0.3
    reg = register_stack(bad, 0)
    assert not bool(reg.ok[2]) and float(reg.confidence[2]) == 0.0
    assert "frame 2 is flat (no image)" in reg.messages


def test_prediction_is_refined_and_frames_out_of_order_are_detected(frames, shifts):
    predicted = torch.eye(3, dtype=torch.float64).repeat(len(shifts), 1, 1)
    predicted[:, :2, 2] = -torch.tensor(shifts) + 0.05  # the optics are a little off
    reg = register_stack(frames, 0, prediction=predicted)
    assert _centre_error(reg, shifts, frames).max() < 0.01
    assert not bool(reg.out_of_order.any())

    swapped = frames.clone()
    swapped[[3, 5]] = frames[[5, 3]]
    reg = register_stack(swapped, 0, prediction=predicted)
    assert reg.out_of_order.nonzero()[:, 0].tolist() == [3, 5]
    assert any("frame 3 sits where frame 5 was planned" in m for m in reg.messages)
    # The measured motions are still right (they follow the data, not the plan).
    assert _centre_error(reg, shifts[[0, 1, 2, 5, 4, 3, 6, 7, 8]], swapped).max() < 0.01


def test_homographies_from_positions_recovers_a_homography():
    true = torch.tensor([[1.001, 0.002, 0.3], [-0.001, 0.999, -0.2], [1e-5, -2e-5, 1.0]], dtype=torch.float64)
    vv, uu = torch.meshgrid(torch.arange(40.0), torch.arange(50.0), indexing="ij")
    grid = torch.stack((uu, vv), -1).double()
    pos = apply_homography(true[None], grid.reshape(-1, 2)).reshape(1, 40, 50, 2)
    est = homographies_from_positions(pos)
    assert torch.allclose(apply_homography(est, grid.reshape(-1, 2)), pos.reshape(1, -1, 2), atol=1e-8)


def test_a_full_frame_is_fitted_on_a_capped_grid_to_the_same_homography():
    """At most 64 grid lines per axis (fit_grid's cap): on a full frame's smooth map (a homography
    plus a gentle distortion of up to 0.3 px) the fit lands within 3 % of that distortion of the
    fit on every 4th line (5.8e-3 px measured); on the homography alone, on it."""
    from hbis_torch.registration import fit_grid

    H, W = 960, 1280
    rows, cols = fit_grid(H, W)
    assert len(rows) <= 66 and len(cols) <= 66 and rows[-1] == H - 1 and cols[-1] == W - 1
    assert len(fit_grid(40, 50)[0]) == 11  # small frames keep every 4th line
    true = torch.tensor([[1.001, 0.002, 0.3], [-0.001, 0.999, -0.2], [1e-6, -2e-6, 1.0]], dtype=torch.float64)
    vv, uu = torch.meshgrid(torch.arange(float(H)), torch.arange(float(W)), indexing="ij")
    grid = torch.stack((uu, vv), -1).reshape(-1, 2).double()
    exact = apply_homography(true[None], grid).reshape(1, H, W, 2)
    corners = torch.tensor([[0, 0], [W - 1, 0], [0, H - 1], [W - 1, H - 1], [W / 2, H / 2]], dtype=torch.float64)
    fitted = homographies_from_positions(exact)
    assert (apply_homography(fitted, corners) - apply_homography(true, corners)).abs().max() < 1e-8
    pos = exact + 0.3 * torch.stack((torch.sin(uu / 400), torch.cos(vv / 300)), -1).double()
    dense_rows, dense_cols = torch.arange(0, H, 4), torch.arange(0, W, 4)
    dense = homographies_from_grid(pos[:, dense_rows][:, :, dense_cols], dense_rows, dense_cols, H, W)
    capped = homographies_from_positions(pos)
    assert (apply_homography(capped, corners) - apply_homography(dense, corners)).abs().max() < 0.03 * 0.3


def test_bspline_interpolation_is_exact_at_nodes_and_matches_scipy():
    rng = np.random.default_rng(0)
    img = torch.tensor(rng.normal(size=(1, 30, 40)))
    _, coef = prefilter(img)
    vv, uu = torch.meshgrid(torch.arange(30.0), torch.arange(40.0), indexing="ij")
    nodes = torch.stack((uu, vv), -1).reshape(1, -1, 2).double()
    assert (bspline_sample(coef, nodes).reshape(30, 40) - img[0]).abs().max() < 1e-4
    pts = torch.tensor(rng.uniform(3, 26, (1, 50, 2)))
    ref = ndimage.map_coordinates(img[0].numpy(), [pts[0, :, 1].numpy(), pts[0, :, 0].numpy()], order=3, mode="mirror")
    assert np.abs(bspline_sample(coef, pts)[0].numpy() - ref).max() < 1e-4


def test_prefilter_with_a_sampled_kernel_is_mirrored_convolution():
    rng = np.random.default_rng(1)
    img = torch.tensor(rng.normal(size=(2, 31, 44)))
    kernel = gaussian_kernel(0.7)
    blurred, coef = prefilter(img, kernel=kernel)
    k2 = np.outer(kernel.numpy(), kernel.numpy())
    for k in range(2):
        ref = ndimage.convolve(img[k].numpy(), k2, mode="mirror")
        assert np.abs(blurred[k].numpy() - ref).max() < 1e-9
    # The fit's sampler (one image shared by every frame) agrees with the per-frame one on
    # every frame's points, at least 2 px inside the image.
    pts = torch.tensor(rng.uniform(2, 28, (3, 40, 2)))
    shared = _spline_fetch(coef[:1], pts)[0]
    single = bspline_sample(coef[:1].expand(3, -1, -1), pts)
    assert (shared - single).abs().max() < 1e-9


def test_mean_and_spread_survive_a_nearly_flat_frame():
    x = torch.rand(3, 40, 50)
    x[1] = 0.6 + 1e-5 * torch.randn(40, 50)  # spread far below the mean: the one-pass form cancels
    mean, spread = mean_and_spread(x)
    torch.testing.assert_close(mean, x.double().mean((-2, -1)).float())
    torch.testing.assert_close(spread, x.double().std((-2, -1), correction=0).float(), rtol=1e-3, atol=0)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(frames=np.zeros((4, 32))), "shape"),
        (dict(frames=np.full((2, 32, 32), np.nan)), "non-finite"),
        (dict(frames=np.zeros((2, 8, 8))), "16 x 16"),
        (dict(reference_index=5), "reference_index"),
        (dict(reference_index=1.5), "integer"),
        (dict(prediction=np.zeros((3, 3))), "prediction must have shape"),
        (dict(prediction=np.zeros((2, 3, 3))), "singular"),
        (dict(model="spline"), "model must be"),
        (dict(blur_sigma=-1.0), "blur_sigma"),
        (dict(keep_fraction=0.0), "keep_fraction"),
        (dict(max_points=10), "max_points"),
    ],
)
def test_bad_input_is_rejected_with_a_clear_message(kwargs, match):
    args = dict(frames=np.random.default_rng(0).random((2, 32, 32)), reference_index=0)
    args.update(kwargs)
    with pytest.raises(HbisInputError, match=match):
        register_stack(args.pop("frames"), args.pop("reference_index"), **args)


def test_results_are_ordinary_tensors_callers_may_modify(frames):
    """The registration runs under torch.inference_mode; what it returns must not be inference
    tensors, or a caller's in-place edit would fail."""
    reg = register_stack(frames[:3], 0)
    for t in (reg.homographies, reg.confidence, reg.ok, reg.precision_px, reg.residual, reg.out_of_order):
        assert not t.is_inference()
    reg.homographies[1, 0, 2] += 1.0  # an in-place edit outside inference mode
    assert torch.isfinite(reg.homographies).all()


def test_several_models_share_one_preparation_and_register_as_one_at_a_time(monkeypatch):
    """register_models: the same registrations as register_stack model by model, bit for bit, with
    the reference's splines and the compared points prepared once."""
    from hbis_torch.registration import register_models, stack

    frames = shifted_frames([(0.0, 0.0), (0.4, -0.3), (-1.2, 0.7)])
    prediction = np.repeat(np.eye(3)[None], 3, 0)
    models = ("translation", "similarity", "homography")
    alone = {m: register_stack(frames, 0, prediction=prediction, model=m) for m in models}
    calls = []
    original = stack._compared_points
    monkeypatch.setattr(stack, "_compared_points", lambda *a, **k: calls.append(1) or original(*a, **k))
    done = []
    together = register_models(frames, 0, {m: prediction for m in models}, done.append)
    assert len(calls) == 1 and done == list(models)
    for m in models:
        for name in ("homographies", "confidence", "precision_px", "residual"):
            assert torch.equal(getattr(alone[m], name), getattr(together[m], name)), (m, name)
        assert alone[m].model == together[m].model and alone[m].messages == together[m].messages
    register_stack(frames, 0, model="translation")  # and nothing is kept after
    assert len(calls) == 2
