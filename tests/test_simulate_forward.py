"""The forward model against closed forms, the tracer, and itself."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from hbis_torch.config import FoveaSystem
from hbis_torch.errors import HbisInputError
from hbis_torch.scan import plan_scan
from hbis_torch.simulate import (
    FlatScene,
    GratingScene,
    SceneSpec,
    SensorModel,
    load_scene,
    render_scan,
    sample_positions,
    simulate_stack,
)
from hbis_torch.simulate.forward import grid_factor
from hbis_torch.simulate.reference import grating_frame, grating_truth

SYSTEM = FoveaSystem()
PIXEL_MM = SYSTEM.object_pixel_mm
NOISELESS = SensorModel(noise=False, bit_depth=None)


def _pixels(roi):
    u0, v0, w, h = roi
    vv, uu = torch.meshgrid(torch.arange(h), torch.arange(w), indexing="ij")
    return torch.stack((uu.flatten() + u0, vv.flatten() + v0), -1).double()


@pytest.mark.parametrize(
    "h,roi,period_px,angle,fill,defocus_um",
    [
        (4, (1260, 940, 20, 20), 3.0, 0.0, 1.0, 0.0),  # bottom-right corner, coarse grating
        (4, (1260, 0, 20, 20), 0.6, 30.0, 0.7, 0.0),  # above the LR Nyquist frequency
        (3, (0, 0, 16, 16), 1.3, 70.0, 0.5, 2.0),  # top-left corner, defocus, small fill
        (2, (600, 470, 16, 16), 0.9, -20.0, 1.0, 0.0),  # centre
        (5, (0, 944, 12, 16), 0.5, 45.0, 1.0, 0.0),
    ],
)
def test_frames_and_truth_match_the_closed_form_for_gratings(h, roi, period_px, angle, fill, defocus_um):
    """Every pixel of every frame, and every truth pixel, against I = m + a H(J^T k) cos(...)
    with the landing traced exactly at each frame's own phases (docs/data.md)."""
    plan = plan_scan(SYSTEM, h)
    grating = GratingScene(size_mm=(1.0, 1.0), period_mm=period_px * PIXEL_MM, angle_deg=angle,
                           mean=0.5, amplitude=0.45)
    sensor = SensorModel(fill_factor=fill, defocus_um=defocus_um, noise=False, bit_depth=None)
    # margin 16: the PSF's tails beyond it hold < 0.3 % of its energy, so the mirrored
    # continuation of the grid cannot be told from the infinite grating at this tolerance
    out = render_scan(grating, SYSTEM, plan.phases_deg, plan.reference_index, h, roi, sensor, margin_px=16)
    spacing = PIXEL_MM / (h * grid_factor(h))
    pixels = _pixels(roi)
    worst = 0.0
    for k in range(plan.frames):
        expected = grating_frame(out.scene, SYSTEM, plan.phases_deg[k], pixels, sensor, spacing)
        worst = max(worst, float((out.irradiance[k].flatten().double() - expected).abs().max()))
    assert worst < 4e-4
    hr = _pixels((0, 0, h * roi[2], h * roi[3])).long()
    expected = grating_truth(out.scene, SYSTEM, plan.phases_deg[plan.reference_index], hr, roi, h, sensor, spacing)
    assert float((out.truth.flatten().double() - expected).abs().max()) < 1e-4


def test_blur_really_is_applied_to_the_truth():
    """Sanity of the closed form itself: a grating finer than the ideal sensor's pitch is
    attenuated in the truth, and the frames (pitch p) lose even more of it."""
    h = 4
    plan = plan_scan(SYSTEM, h)
    grating = GratingScene(size_mm=(1.0, 1.0), period_mm=0.5 * PIXEL_MM, mean=0.5, amplitude=0.4)
    out = render_scan(grating, SYSTEM, plan.phases_deg, plan.reference_index, h, (600, 400, 16, 16), NOISELESS)
    truth_amp = float(out.truth.max() - out.truth.min()) / 2
    frame_amp = float(out.irradiance.max() - out.irradiance.min()) / 2
    assert 0.05 < truth_amp < 0.35 and frame_amp < 0.01


def test_noise_free_flat_scene_is_flat():
    plan = plan_scan(SYSTEM, 3)
    scene = FlatScene(size_mm=(2.0, 2.0), level=0.37)
    out = render_scan(scene, SYSTEM, plan.phases_deg, plan.reference_index, 3, (1240, 920, 40, 40),
                      SensorModel(fill_factor=0.6, defocus_um=3.0))
    assert float((out.irradiance - 0.37).abs().max()) < 1e-6
    assert float((out.truth - 0.37).abs().max()) < 1e-6
    sensor = SensorModel(noise=False, bit_depth=12, black_level_dn=64)
    stack, truth = simulate_stack(scene, SYSTEM, plan, (0, 0, 30, 20), sensor)
    assert stack.frames.dtype == np.uint16
    assert np.unique(stack.frames).size == 1  # every pixel of every frame: one DN
    assert np.unique(stack.frames)[0] == round(64 + 0.37 * (4095 - 64))
    assert np.ptp(truth) < 1e-6


def test_truth_at_h1_is_the_reference_frame():
    """With h = 1 the ideal sensor is the sensor: the truth equals the reference frame."""
    scene = load_scene("words", SceneSpec((1.5, 1.5), PIXEL_MM, PIXEL_MM / 8), seed=2)
    phases = torch.tensor([[5.0, 70.0], [5.3, 70.2]], dtype=torch.float64)
    out = render_scan(scene, SYSTEM, phases, 0, 1, (300, 200, 24, 24), NOISELESS)
    assert out.truth.shape == (24, 24)
    assert float((out.truth - out.irradiance[0]).abs().max()) < 2e-6
    assert float((out.irradiance[1] - out.irradiance[0]).abs().max()) > 0.05  # the other frame moved


def _register(reference: np.ndarray, moving: np.ndarray, margin: int = 8) -> np.ndarray:
    """Translation d (du, dv) with moving(x) = reference(x + d), by Gauss-Newton on the interior
    with cubic-spline interpolation of the reference.

    (skimage's phase_cross_correlation, even upsampled, is biased toward zero shift by 0.03 px
    here: the frames are not periodic and it does not window them.)
    """
    from scipy import ndimage

    coeffs = ndimage.spline_filter(reference.astype(np.float64), order=3)
    vv, uu = np.mgrid[margin:reference.shape[0] - margin, margin:reference.shape[1] - margin].astype(float)
    target = moving[margin:-margin, margin:-margin].astype(np.float64)
    d = np.zeros(2)
    for _ in range(30):
        def warp(du, dv):
            return ndimage.map_coordinates(coeffs, [vv + d[1] + dv, uu + d[0] + du], order=3, prefilter=False)

        warped, e = warp(0, 0), 1e-3
        gu = (warp(e, 0) - warp(-e, 0)) / (2 * e)
        gv = (warp(0, e) - warp(0, -e)) / (2 * e)
        normal = np.array([[np.sum(gu * gu), np.sum(gu * gv)], [np.sum(gu * gv), np.sum(gv * gv)]])
        step = np.linalg.solve(normal, [np.sum(gu * (target - warped)), np.sum(gv * (target - warped))])
        d += step
        if np.abs(step).max() < 1e-7:
            break
    return d


def test_frames_move_as_the_tracer_says():
    """Register each frame of a textured scene against the reference and compare the measured
    translation with the mean sample position the tracer predicts (roi-local, contract)."""
    from hbis_torch.simulate import ImageScene
    from hbis_torch.simulate.rasters import texture_image

    h = 4
    plan = plan_scan(SYSTEM, h)
    roi = (1152, 832, 96, 96)  # near a corner, where pixels move most unevenly
    # correlation length 2 px: frames that do not alias much, so registration is unbiased
    image = texture_image((400, 400), 8.0, np.random.default_rng(5))
    scene = ImageScene(size_mm=(100 * PIXEL_MM, 100 * PIXEL_MM), image=torch.from_numpy(image))
    out = render_scan(scene, SYSTEM, plan.phases_deg, plan.reference_index, h, roi, NOISELESS)
    grid = _pixels((0, 0, roi[2], roi[3])).reshape(roi[3], roi[2], 2)
    reference = out.irradiance[plan.reference_index].numpy()
    errors = []
    for k in range(plan.frames):
        predicted = (out.positions[k] - grid)[8:-8, 8:-8].reshape(-1, 2).mean(0).numpy()
        measured = _register(reference, out.irradiance[k].numpy())
        errors.append(np.abs(measured - predicted).max())
        if k != plan.reference_index:
            assert np.abs(predicted).max() > 0.2  # a real sub-pixel step (SL = 0.25 px)
    assert max(errors) < 0.015, errors


def test_edge_pixels_move_differently_from_the_centre():
    """A global translation is not the model: across the full sensor the sample positions of one
    frame differ by a sizeable fraction of the scan step (the paper's per-pixel AE)."""
    h = 4
    plan = plan_scan(SYSTEM, h)
    phases = plan.phases_deg[[0, plan.reference_index]]  # frame 0 and the reference
    pos = sample_positions(SYSTEM, phases, 1, None, local=False)[0]
    grid = _pixels((0, 0, 1280, 960)).reshape(960, 1280, 2)
    shift = pos - grid
    spread = (shift - shift[480, 640]).norm(dim=-1).max()
    assert float(spread) > 0.2 / h  # more than a fifth of the scan step SL


def test_float32_path_agrees_with_float64():
    plan = plan_scan(SYSTEM, 4)
    scene = load_scene("edges", SceneSpec((1.5, 1.5), PIXEL_MM, PIXEL_MM / 8), seed=1)
    args = (scene, SYSTEM, plan.phases_deg, plan.reference_index, 4, (1200, 900, 24, 24), NOISELESS)
    single = render_scan(*args, dtype=torch.float32)
    double = render_scan(*args, dtype=torch.float64)
    # a fifth of a 12-bit step; the scene itself is evaluated in float32 in both
    assert float((single.irradiance - double.irradiance).abs().max()) < 5e-5
    assert float((single.truth - double.truth).abs().max()) < 5e-5


def test_tiles_join_seamlessly():
    """Tiles agree with one big grid up to what the Airy tails see beyond the margin (they hold
    about 2 lambda F / (pi^2 margin) of the light: 0.3 % at 16 pixels)."""
    plan = plan_scan(SYSTEM, 2)
    scene = load_scene("camera", SceneSpec((2.0, 2.0), PIXEL_MM, PIXEL_MM / 8), seed=0)
    args = (scene, SYSTEM, plan.phases_deg, plan.reference_index, 2, (500, 300, 60, 44), NOISELESS)
    whole = render_scan(*args, margin_px=16)
    tiled = render_scan(*args, margin_px=16, max_grid=400)  # 14-pixel tiles
    assert float((whole.irradiance - tiled.irradiance).abs().max()) < 5e-4
    assert float((whole.truth - tiled.truth).abs().max()) < 5e-4
    assert float((whole.positions - tiled.positions).abs().max()) < 1e-6


def test_simulate_stack_is_deterministic_and_records_itself():
    plan = plan_scan(SYSTEM, 2)
    scene = load_scene("siemens-star", SceneSpec((1.0, 1.0), PIXEL_MM, PIXEL_MM / 8), seed=0)
    a, ta = simulate_stack(scene, SYSTEM, plan, (10, 20, 16, 12), seed=7, phase_error_deg=0.01)
    b, tb = simulate_stack(scene, SYSTEM, plan, (10, 20, 16, 12), seed=7, phase_error_deg=0.01)
    c, _ = simulate_stack(scene, SYSTEM, plan, (10, 20, 16, 12), seed=8, phase_error_deg=0.01)
    assert np.array_equal(a.frames, b.frames) and np.array_equal(ta, tb)
    assert not np.array_equal(a.frames, c.frames)
    assert a.frames.shape == (4, 12, 16) and ta.shape == (24, 32) and ta.dtype == np.float32
    assert a.h == 2 and a.roi == (10, 20, 16, 12) and a.reference_index == plan.reference_index
    np.testing.assert_array_equal(a.phases_deg, plan.phases_deg.numpy())  # planned phases stored
    true = np.asarray(a.meta["simulation"]["true_phases_deg"])
    assert np.array_equal(true[plan.reference_index], a.phases_deg[plan.reference_index])
    assert 0 < np.abs(true - a.phases_deg).max() < 0.1
    assert a.meta["simulation"]["scene"] == "siemens-star" and a.system == SYSTEM


def test_int_plan_and_bad_input():
    scene = FlatScene(size_mm=(1.0, 1.0))
    stack, truth = simulate_stack(scene, SYSTEM, 2, (0, 0, 8, 8))
    assert stack.frames.shape == (4, 8, 8) and truth.shape == (16, 16)
    with pytest.raises(HbisInputError, match="roi"):
        simulate_stack(scene, SYSTEM, 2, (1275, 0, 8, 8))
    with pytest.raises(HbisInputError, match="plan must be"):
        simulate_stack(scene, SYSTEM, "four", (0, 0, 8, 8))
    with pytest.raises(HbisInputError, match="reference index"):
        render_scan(scene, SYSTEM, [[5.0, 70.0]], 3, 2, (0, 0, 8, 8))
    with pytest.raises(HbisInputError, match="non-finite|NaN"):
        render_scan(scene, SYSTEM, [[5.0, float("nan")]], 0, 2, (0, 0, 8, 8))
    with pytest.raises(HbisInputError, match="phase error"):
        simulate_stack(scene, SYSTEM, 2, (0, 0, 8, 8), phase_error_deg=-1)


@pytest.mark.parametrize("h", [2, 3, 4])
def test_truth_pooled_h_by_h_is_the_reference_frame(h):
    """With fill factor 1 a sensor pixel's aperture is exactly the union of the h x h apertures
    of the ideal pitch-p/h pixels on it (docs/data.md grid convention), and the PSF is the same,
    so the noise-free reference frame equals the truth averaged over h x h blocks."""
    plan = plan_scan(SYSTEM, h)
    scene = load_scene("words", SceneSpec((1.0, 1.0), PIXEL_MM, PIXEL_MM / 8), seed=h)
    out = render_scan(scene, SYSTEM, plan.phases_deg, plan.reference_index, h, (1250, 0, 30, 20),
                      SensorModel(fill_factor=1.0, defocus_um=1.0))
    pooled = torch.nn.functional.avg_pool2d(out.truth[None, None], h)[0, 0]
    reference = out.irradiance[plan.reference_index]
    assert float(reference.std()) > 0.05
    assert float((pooled - reference).abs().max()) < 2e-4


def test_simulate_stack_takes_a_scene_name():
    stack, truth = simulate_stack("bars", SYSTEM, 2, (100, 100, 20, 12), SensorModel(noise=False), seed=3)
    assert stack.meta["simulation"]["scene"] == "bars" and truth.shape == (24, 40)
    assert np.ptp(truth) > 0.3
    with pytest.raises(HbisInputError, match="scene must be"):
        simulate_stack(42, SYSTEM, 2, (100, 100, 20, 12))
