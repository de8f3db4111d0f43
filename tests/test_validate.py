"""Observation-space cross-validation (hbis_torch.validate, ``hbis validate``): frame subsets, the
forward model, and that its ranking of methods agrees with the ground truth's on simulated stacks."""

import json

import numpy as np
import pytest

from hbis_torch import FoveaSystem
from hbis_torch.cli import main
from hbis_torch.errors import HbisInputError
from hbis_torch.reconstruct import reconstruct
from hbis_torch.reconstruct.positions import stack_sample_positions
from hbis_torch.reconstruct.registry import METHODS, Method
from hbis_torch.simulate.cases import make_stack, roi_for
from hbis_torch.stack_io import Stack, make_burst_meta, write_stack
from hbis_torch.training.heldout import score as true_psnr
from hbis_torch.validate import (
    centre_offset,
    cross_validate,
    fit_and_score,
    holdout_frames,
    pixel_kernel,
    predict_frame,
    select_frames,
    single_frame,
)
from hbis_torch.validate.score import inside

pytestmark = pytest.mark.usefixtures("one_thread")
SYSTEM = FoveaSystem()


def _scan(h, scene="words", size=48, seed=1000):
    return make_stack(SYSTEM, h, roi_for(SYSTEM, size, 0), scene, seed)


# --- frame subsets --------------------------------------------------------------------------

def test_select_frames_cuts_every_per_frame_field_of_a_scan_and_keeps_the_reference():
    stack, _ = _scan(2, size=16)
    ref = stack.reference_index
    part = select_frames(stack, [0])
    kept = sorted({0, ref})
    assert len(part.frames) == len(kept) and part.reference_index == kept.index(ref)
    np.testing.assert_array_equal(part.frames, stack.frames[kept])
    np.testing.assert_array_equal(part.phases_deg, stack.phases_deg[kept])
    assert len(stack.frames) == 4 and stack.reference_index == ref  # the original is untouched
    # the subset's positions are the whole stack's, for the frames kept
    whole, _ = stack_sample_positions(stack, "optics")
    some, _ = stack_sample_positions(part, "optics")
    np.testing.assert_allclose(some.numpy(), whole.numpy()[kept], atol=1e-9)
    with pytest.raises(HbisInputError, match="not one of the stack's 4 frames"):
        select_frames(stack, [4])


def translation_burst(shifts, scale=2, size=40, seed=0, factor=8, reference=0):
    """A burst of a random smooth scene, frame k shifted by ``shifts[k]`` LR pixels (multiples of
    1 / factor), frame ``reference`` the reference (its shift (0, 0)): (stack, truth on the
    reference grid refined ``scale`` times, HR pixel (U, V) centred at LR ((U + 0.5) / S - 0.5, ...))."""
    from scipy.ndimage import gaussian_filter

    rng = np.random.default_rng(seed)
    pad = 4
    side = (size + 2 * pad) * factor
    scene = gaussian_filter(rng.random((side, side)), 0.4 * factor)
    scene = (scene - scene.min()) / (scene.max() - scene.min())
    frames = []
    for dx, dy in shifts:  # frame pixel (u, v) sees reference position (u + dx, v + dy)
        ox, oy = int(round((pad + dx) * factor)), int(round((pad + dy) * factor))
        crop = scene[oy:oy + size * factor, ox:ox + size * factor]
        frames.append(crop.reshape(size, factor, size, factor).mean(axis=(1, 3)))
    crop = scene[pad * factor:(pad + size) * factor, pad * factor:(pad + size) * factor]
    b = factor // scale
    truth = crop.reshape(size * scale, b, size * scale, b).mean(axis=(1, 3))
    noisy = np.clip(np.asarray(frames) + rng.normal(0, 0.004, (len(frames), size, size)), 0, 1)
    motions = np.repeat(np.eye(3)[None], len(shifts), 0)
    motions[:, :2, 2] = np.asarray(shifts) - np.asarray(shifts[reference])
    models = ["translation"] * len(shifts)
    models[reference] = "identity"
    meta = make_burst_meta(scale, (0, 0, size, size), motions, [1.0] * len(shifts), models,
                           [[1.0, 0.0]] * len(shifts), reference_index=reference)
    return Stack(noisy.astype(np.float32), meta).validate(), truth.astype(np.float32)


def test_select_frames_cuts_a_bursts_motions_and_the_rest():
    stack, _ = translation_burst([(0, 0), (0.5, 0), (0, 0.5), (0.5, 0.5)])
    stack.meta["reference_index"] = 2
    part = select_frames(stack, [0, 3])
    assert part.kind == "burst" and part.reference_index == 1 and len(part.frames) == 3
    np.testing.assert_array_equal(part.motions, stack.motions[[0, 2, 3]])
    assert part.meta["motion_models"] == [stack.meta["motion_models"][k] for k in (0, 2, 3)]
    assert len(part.confidence) == len(part.gain_offset) == 3


@pytest.mark.parametrize("cache_bytes", [None, 0])
def test_a_folds_samples_lie_where_the_whole_bursts_do(monkeypatch, cache_bytes):
    # a hand-held burst's local shifts are per frame too: a fold of frames 0, 2 and 3 reads frame
    # 2's shifts for its second frame (they had stayed the whole burst's, frame 1's read there, and
    # a burst too large to keep its positions failed on them)
    from hbis_torch.capture.burst import assemble_burst
    from hbis_torch.reconstruct import positions as burst_positions_module
    from hbis_torch.simulate.burst import random_motions, simulate_burst

    if cache_bytes is not None:  # each band computed when read, as for a 12 MP burst
        monkeypatch.setattr(burst_positions_module, "CACHE_BYTES", cache_bytes)
    rng = np.random.default_rng(4)
    truth = rng.random((256, 256))
    burst = simulate_burst(truth, 2, random_motions(4, (128, 128), rng, 1.5, 1.0), noise=0.005, seed=4)
    stack, _ = assemble_burst(burst.frames, 2, motion="homography")
    assert stack.meta.get("local_motion") is not None
    part = select_frames(stack, [0, 2, 3])
    assert len(part.meta["local_motion"]["offsets"]) == 3
    whole, _ = burst_positions_module.burst_positions(stack, lazy=True)
    fold, _ = burst_positions_module.burst_positions(part, lazy=True)
    for k, original in enumerate((0, 2, 3)):
        np.testing.assert_array_equal(fold[k, 10:20].numpy(), whole[original, 10:20].numpy())


def test_a_burst_is_validated_without_every_samples_position(monkeypatch):
    # only the held-out frames' positions are read (a 16-frame 12 MP burst's whole are 3 GB)
    from hbis_torch.capture.burst import assemble_burst
    from hbis_torch.reconstruct.positions import BurstPositions
    from hbis_torch.simulate.burst import random_motions, simulate_burst

    rng = np.random.default_rng(5)
    burst = simulate_burst(rng.random((96, 96)), 2, random_motions(5, (48, 48), rng, 1.5, 1.0), noise=0.005, seed=5)
    stack, _ = assemble_burst(burst.frames, 2)

    def whole(self):
        raise AssertionError("every sample's position was asked for")

    monkeypatch.setattr(BurstPositions, "whole", whole)
    result = cross_validate(stack, ("single-frame", "classical"), 2)
    assert all(np.isfinite(s.psnr).all() for s in result.methods.values())


def test_holdout_frames_are_spread_and_never_the_reference():
    assert holdout_frames(16, 10, 3) == [2, 7, 13]
    assert holdout_frames(30, 0, 3) == [5, 15, 25]
    assert holdout_frames(4, 3, 3) == [0, 1, 2]
    assert 5 not in holdout_frames(8, 5, 7)
    # untrusted frames only when the trusted ones are too few
    assert 2 not in holdout_frames(8, 0, 3, trusted=[True, True, False, True, True, True, True, True])
    for bad in (0, 16):
        with pytest.raises(HbisInputError, match="holdout must be from 1 to 15"):
            holdout_frames(16, 10, bad)


# --- the forward model ----------------------------------------------------------------------

@pytest.mark.parametrize("h, fill, weights", [
    (2, 1.0, [0.5, 0.5]),  # an even h's LR pixel centre lies between two HR pixels: it covers both
    (3, 1.0, [1 / 3, 1 / 3, 1 / 3]),
    (4, 1.0, [0.25, 0.25, 0.25, 0.25]),
    (4, 0.25, [0.5, 0.5]),  # a quarter of the area: half the side
    (3, 0.25, [1 / 6, 2 / 3, 1 / 6]),  # 1.5 HR px centred on one: a quarter of each neighbour
])
def test_pixel_kernel_is_the_pixels_box_integrated_over_hr_pixels(h, fill, weights):
    k = pixel_kernel(h, fill, 0.0)
    np.testing.assert_allclose(k[k > 0], weights, atol=1e-12)
    centre = centre_offset(h)
    m = np.arange(len(k)) - len(k) // 2
    assert (k * m).sum() == pytest.approx(centre, abs=1e-12)  # centred on the LR pixel's centre
    blurred = pixel_kernel(h, fill, 0.3)
    n = np.arange(len(blurred)) - len(blurred) // 2
    assert blurred.sum() == pytest.approx(1.0) and (blurred * n).sum() == pytest.approx(centre, abs=1e-9)
    # a Gaussian of 0.3 LR pixels adds its variance (0.3 h)^2 HR pixels^2 to the box's, and its
    # integration over HR pixels 1/12
    assert (blurred * (n - centre) ** 2).sum() == pytest.approx(
        (k * (m - centre) ** 2).sum() + (0.3 * h) ** 2 + 1 / 12, rel=0.01)


@pytest.mark.parametrize("h", [2, 3, 4])
def test_a_frame_of_the_hr_pixels_own_means_is_predicted_exactly(h):
    # each LR pixel records the mean of the h x h HR pixels it covers: at the reference's own
    # positions the prediction (no blur) must be that mean, for even h too (a box centred on an
    # HR pixel and read half a pixel on by the interpolation missed it by up to 0.14 at h = 2)
    estimate = np.random.default_rng(h).random((12 * h, 10 * h))
    frame = estimate.reshape(12, h, 10, h).mean(axis=(1, 3))
    v, u = np.mgrid[0:12, 0:10].astype(np.float64)
    predicted = predict_frame(estimate, np.stack((u, v), -1), h, blur_px=0.0)
    np.testing.assert_allclose(predicted[1:-1, 1:-1], frame[1:-1, 1:-1], atol=1e-6)


def test_the_truth_predicts_every_frame_and_a_wrong_motion_does_not():
    stack, truth = _scan(4)
    positions, _ = stack_sample_positions(stack, "optics")
    frames = stack.to_float().numpy()
    mask = inside(positions[0], 48, 48)
    for k in (0, 5, 10, 15):
        good = fit_and_score(predict_frame(truth, positions[k], 4), frames[k], mask)
        assert good.psnr > 32
        wrong = fit_and_score(predict_frame(truth, positions[k].numpy() + (0.5, 0.25), 4), frames[k], mask)
        assert wrong.psnr < good.psnr - 10
    # without blur, the truth predicts the noise-free frame up to noise: the model is the simulator's
    exact = fit_and_score(predict_frame(truth, positions[5], 4, blur_px=0.0), frames[5], mask)
    assert exact.psnr > 38 and exact.gain == pytest.approx(1.0, abs=0.02)


def test_the_prediction_in_float32_agrees_with_a_float64_block_mean():
    rng = np.random.default_rng(1)
    from scipy.ndimage import gaussian_filter

    hr = gaussian_filter(rng.random((64, 64)), 3.0)
    h = 4
    reference = hr.reshape(16, h, 16, h).mean(axis=(1, 3))  # what the reference pixels integrate
    v, u = np.mgrid[0:16, 0:16].astype(float)
    predicted = predict_frame(hr, np.stack((u, v), -1), h, blur_px=0.0)
    assert np.abs(predicted - reference)[2:-2, 2:-2].max() < 1e-2 * np.ptp(hr)


def test_gain_and_offset_are_fitted_and_too_few_samples_are_refused():
    x = np.linspace(0, 1, 100).reshape(10, 10)
    fit = fit_and_score(x, 0.5 * x + 0.2, np.ones_like(x, bool))
    assert (fit.gain, fit.offset) == pytest.approx((0.5, 0.2)) and fit.psnr > 200
    with pytest.raises(HbisInputError, match="too few to score"):
        fit_and_score(x, x, np.zeros_like(x, bool))


# --- the ranking agrees with the truth's ----------------------------------------------------

@pytest.mark.parametrize("h, scene", [(2, "words"), (2, "camera"), (4, "words"), (4, "camera")])
def test_validate_ranks_methods_as_the_ground_truth_does(h, scene):
    stack, truth = _scan(h, scene)
    result = cross_validate(stack, registration="optics")
    ref = stack.to_float().numpy()[stack.reference_index]
    truth_psnr = {"single-frame": true_psnr(single_frame(ref, h), truth, h)}
    for method in ("classical", "learned"):
        truth_psnr[method] = true_psnr(reconstruct(stack, method, registration="optics"), truth, h)
    by_validate = sorted(result.methods, key=lambda m: result.methods[m].mean_psnr)
    by_truth = sorted(truth_psnr, key=truth_psnr.get)
    assert by_truth == ["single-frame", "classical", "learned"]  # the cells are chosen where it is clear
    assert by_validate == by_truth, ({m: s.mean_psnr for m, s in result.methods.items()}, truth_psnr)
    assert len(result.held_out) == 3 and stack.reference_index not in result.held_out


# --- bursts -----------------------------------------------------------------------------------

def _splat(frames, positions, h: int, reference: int, weights=None) -> np.ndarray:
    """Every sample added to its nearest output pixel (with its weight), averaged; pixels no sample
    reached take the single-frame image's value."""
    frames, q = np.asarray(frames, dtype=np.float64), np.asarray(positions).reshape(-1, 2)
    rows, cols = frames.shape[1:3]
    w = np.ones(frames.size) if weights is None else np.asarray(weights, dtype=np.float64).reshape(-1)
    col = np.clip(np.round(h * (q[:, 0] + 0.5) - 0.5), 0, h * cols - 1).astype(int)
    row = np.clip(np.round(h * (q[:, 1] + 0.5) - 0.5), 0, h * rows - 1).astype(int)
    index = row * h * cols + col
    total = np.bincount(index, w * frames.reshape(-1), minlength=h * h * rows * cols)
    count = np.bincount(index, w, minlength=h * h * rows * cols)
    fill = single_frame(frames[reference], h).reshape(-1)
    return np.where(count > 0, total / np.maximum(count, 1e-12), fill).reshape(h * rows, h * cols).astype(np.float32)


def _shift_and_add(stack, registration="auto", messages=None):
    """A test method on a scan: nearest-pixel shift and add."""
    positions, _ = stack_sample_positions(stack, registration)
    return _splat(stack.to_float().numpy(), positions.numpy(), stack.h, stack.reference_index)


def _shift_and_add_burst(stack, frames, positions, weights, messages=None):
    """The same on a burst, with the burst path's positions and robustness weights."""
    return _splat(frames.numpy(), positions.numpy(), stack.h, stack.reference_index, weights.numpy())


@pytest.fixture
def shift_and_add(monkeypatch):
    monkeypatch.setitem(METHODS, "shift-and-add", Method("shift-and-add", _shift_and_add, "test: nearest-pixel shift and add",
                                                          burst=_shift_and_add_burst))
    return "shift-and-add"


def test_a_registered_method_is_validated_on_a_burst_and_beats_the_single_frame(shift_and_add):
    shifts = [(0, 0), (0.5, 0), (0, 0.5), (0.5, 0.5), (0.25, 0.75), (0.75, 0.25), (1.125, -0.5), (-0.375, 0.625)]
    stack, truth = translation_burst(shifts)
    result = cross_validate(stack, ("bicubic", shift_and_add), holdout=3)
    assert result.held_out == [2, 4, 6] and result.scored_on == "grey"
    assert result.gain(shift_and_add) > 1.0
    ref = stack.to_float().numpy()[0]
    assert true_psnr(reconstruct(stack, shift_and_add), truth, 2) > true_psnr(single_frame(ref, 2), truth, 2) + 1.0
    # the same frames with wrong motions: the held-out frames' predictions miss
    wrong = Stack(stack.frames, {**stack.meta, "motions": np.repeat(np.eye(3)[None], 8, 0).tolist()})
    assert cross_validate(wrong, (shift_and_add,), holdout=3).methods[shift_and_add].mean_psnr \
        < result.methods[shift_and_add].mean_psnr - 3


def test_colour_stacks_are_scored_on_luma(shift_and_add):
    stack, _ = translation_burst([(0, 0), (0.5, 0.25), (0.25, 0.5)], size=24)
    rgb = np.stack((stack.frames, 0.8 * stack.frames, 0.5 * stack.frames), axis=-1).astype(np.float32)
    result = cross_validate(Stack(rgb, stack.meta), ("single-frame",), holdout=2)
    grey = cross_validate(stack, ("single-frame",), holdout=2)
    assert result.scored_on == "luma" and np.isfinite(result.methods["single-frame"].mean_psnr)
    # luma is c = 0.299 + 0.8 x 0.587 + 0.5 x 0.114 times the grey frames here: the gain fit absorbs
    # c, and the residual shrinks by c, so the PSNR rises by -20 log10 c
    c = 0.299 + 0.8 * 0.587 + 0.5 * 0.114
    assert result.methods["single-frame"].mean_psnr == pytest.approx(
        grey.methods["single-frame"].mean_psnr - 20 * np.log10(c), abs=0.02)


# --- the command ------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def stack_file(tmp_path_factory):
    stack, _ = _scan(2, size=24)
    path = tmp_path_factory.mktemp("validate") / "s.tif"
    write_stack(path, stack)
    return path


def test_cli_prints_a_table_and_json(stack_file, capsys):
    assert main(["validate", str(stack_file), "--method", "bicubic,classical", "--registration", "optics"]) == 0
    out = capsys.readouterr().out
    assert "single-frame" in out and "classical" in out and "held out one at a time: 0, 1, 2" in out
    assert main(["validate", str(stack_file), "--method", "single-frame", "--method", "classical",
                 "--holdout", "2", "--json", "--registration", "optics"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["held_out"] == [0, 2] and list(report["methods"]) == ["single-frame", "classical"]
    assert all(np.isfinite(m["mean_psnr_db"]) and len(m["psnr_db"]) == 2 for m in report["methods"].values())


def test_cli_passes_a_methods_own_options_to_it(stack_file, capsys):
    runs = {}
    for extra in ([], ["--no-deblur"]):
        assert main(["validate", str(stack_file), "--method", "bicubic,classical", "--registration", "optics",
                     "--json", *extra]) == 0
        runs[bool(extra)] = json.loads(capsys.readouterr().out)["methods"]
    assert runs[False]["single-frame"]["psnr_db"] == runs[True]["single-frame"]["psnr_db"]  # it takes no options
    assert runs[False]["classical"]["psnr_db"] != runs[True]["classical"]["psnr_db"]


@pytest.mark.parametrize("argv, message", [
    (["--method", "classical", "--ensemble", "2"], "--ensemble is only for --method learned"),
    (["--method", "magic"], "unknown method 'magic'"),
    (["--method", "classical,"], "empty name"),
    (["--holdout", "4"], "holdout must be from 1 to 3"),
    (["--blur", "-1"], "--blur"),
])
def test_cli_refuses_bad_input_in_one_line_before_work(stack_file, capsys, argv, message):
    with pytest.raises(SystemExit) if argv[0] == "--blur" else _no_exit():
        code = main(["validate", str(stack_file), *argv])
        assert code == 2
    err = capsys.readouterr().err
    assert message in err and len(err.strip().splitlines()) == 1


def test_cli_refuses_a_missing_file(tmp_path, capsys):
    assert main(["validate", str(tmp_path / "none.tif")]) == 2
    assert len(capsys.readouterr().err.strip().splitlines()) == 1


class _no_exit:
    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False


def test_on_a_simulated_burst_both_methods_beat_the_single_frame_as_in_truth():
    import skimage.data

    from hbis_torch.simulate.burst import random_motions, simulate_burst

    truth = skimage.data.camera()[100:196, 150:246].astype(np.float64) / 255
    motions = random_motions(10, (48, 48), np.random.default_rng(0), max_shift=1.5, max_rotation_deg=1.0)
    burst = simulate_burst(truth, 2, motions, noise=0.01, seed=0)
    meta = make_burst_meta(2, (0, 0, 48, 48), motions, [1.0] * 10, ["identity"] + ["similarity"] * 9,
                           [[1.0, 0.0]] * 10, bit_depth=8)
    stack = Stack(burst.frames, meta).validate()
    result = cross_validate(stack)
    assert result.held_out == [2, 5, 8]
    reference = stack.to_float().numpy()[0]
    baseline = true_psnr(single_frame(reference, 2), burst.truth, 2)
    for method in ("classical", "learned"):
        assert true_psnr(reconstruct(stack, method), burst.truth, 2) > baseline + 1.0
        assert result.gain(method) > 1.0, {m: s.mean_psnr for m, s in result.methods.items()}


def test_raw_bayer_stacks_are_scored_on_the_mosaic_and_untrusted_frames_are_not_held_out():
    pytest.importorskip("cv2")  # demosaicking, for the registration's grey frames and the baseline
    from hbis_torch.sensor.cfa import mosaic

    stack, _ = translation_burst([(0, 0), (0.5, 0.25), (0.25, 0.5), (0.75, 0.75), (0.5, 0.5)], size=24)
    rgb = np.stack((stack.frames, 0.9 * stack.frames, 0.6 * stack.frames), axis=-1)
    meta = {**stack.meta, "cfa": "RGGB", "confidence": [1.0, 1.0, 0.0, 1.0, 1.0]}
    raw = Stack(mosaic(rgb, "RGGB").astype(np.float32), meta).validate()
    result = cross_validate(raw, ("single-frame",), holdout=2)
    assert result.scored_on == "mosaic" and 2 not in result.held_out
    assert np.isfinite(result.methods["single-frame"].mean_psnr) and result.methods["single-frame"].mean_psnr > 20


def test_a_held_out_frame_whose_motion_is_not_trusted_is_said_so():
    stack, _ = translation_burst([(0, 0), (0.5, 0.25), (0.25, 0.5)], size=24)
    stack.meta["confidence"] = [1.0, 0.0, 1.0]
    messages = []
    result = cross_validate(stack, ("single-frame",), holdout=2, messages=messages)
    assert result.held_out == [1, 2] and len(messages) == 1 and "held-out frame(s) [1]" in messages[0]
