"""Each frame's sharpness, the sharpest frame as the reference, and a blurred reference named."""

import numpy as np
import pytest
import tifffile
import torch
from scipy.ndimage import gaussian_filter, uniform_filter1d

from hbis_torch.capture.burst import assemble_burst, luminance
from hbis_torch.capture.sharpness import BLURRED_SHARE, blur_to_reference, choose_reference, frame_sharpness
from hbis_torch.cli import main
from hbis_torch.notices import asks_to_act
from hbis_torch.stack_io import read_stack
from hbis_torch.training.handheld_render import render_burst

pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture(scope="module")
def burst():
    """A hand-held burst of 8 equally sharp frames of 160 x 120 px (every motion)."""
    return render_burst("all", 2, 8, 160, 120, seed=4).frames


def _blurred(frames: np.ndarray, k: int, sigma: float = 1.0) -> np.ndarray:
    out = frames.copy()
    out[k] = np.round(gaussian_filter(frames[k].astype(np.float64), sigma)).astype(frames.dtype)
    return out


def test_a_frames_gain_and_offset_leave_its_sharpness_alone(burst):
    grey = luminance(burst)
    changed = grey.clone()
    changed[2] = changed[2] * 0.8 + 0.05
    assert np.allclose(frame_sharpness(changed), frame_sharpness(grey), rtol=1e-4)


def test_a_blurred_or_smeared_frame_is_the_least_sharp(burst):
    smeared = burst.copy()
    smeared[5] = np.round(uniform_filter1d(burst[5].astype(np.float64), 3, axis=1)).astype(burst.dtype)  # 3 px of shake
    for frames, k in ((_blurred(burst, 3), 3), (smeared, 5)):
        sharpness = frame_sharpness(luminance(frames))
        assert int(np.argmin(sharpness)) == k
        assert sharpness[k] < BLURRED_SHARE * sharpness.max()


def test_equally_sharp_frames_name_no_blurred_reference_and_keep_the_first(burst):
    grey = luminance(burst)
    sharpness = frame_sharpness(grey)
    assert sharpness.min() > 0.8 * sharpness.max()
    assert choose_reference(grey, 0) == (0, [])
    assert choose_reference(grey, "sharpest")[0] == 0


def test_a_blurred_reference_is_named_and_sharpest_takes_another(burst):
    grey = luminance(_blurred(burst, 0))
    index, messages = choose_reference(grey, 0)
    assert index == 0 and len(messages) == 1 and asks_to_act(messages[0])
    assert "frame 0, is blurred" in messages[0] and "--reference sharpest" in messages[0]
    index, messages = choose_reference(grey, "sharpest")
    assert index != 0 and messages == [f"reference: frame {index}, the sharpest of the burst (--reference sharpest)"]


def test_a_reference_is_compared_with_the_frames_that_register_only(burst):
    """A frame of another, busier scene is sharper than every frame of the burst; registration
    rejects it, and the reference is not called blurred beside it."""
    other = burst.copy()
    other[3] = (np.random.default_rng(0).random(burst.shape[1:]) * 255).astype(burst.dtype)
    grey = luminance(other)
    assert len(choose_reference(grey, 0)[1]) == 1  # beside every frame: named
    trusted = np.ones(len(burst), dtype=bool)
    trusted[3] = False
    assert choose_reference(grey, 0, trusted) == (0, [])
    trusted[0] = False  # the reference itself is always compared
    assert choose_reference(grey, 0, trusted) == (0, [])
    stack, messages = assemble_burst(other, 2)
    assert stack.confidence[3] == 0 and not any("is blurred" in m for m in messages), messages
    assert not any(": it:" in m or "; it:" in m for m in messages), messages


def test_assemble_with_the_sharpest_reference(burst, tmp_path, capsys):
    frames = _blurred(burst, 0)
    stack, messages = assemble_burst(frames, 2, reference="sharpest")
    assert stack.reference_index != 0 and stack.confidence[stack.reference_index] == 1.0
    assert any("the sharpest of the burst" in m for m in messages)
    _, messages = assemble_burst(frames, 2)
    assert any("is blurred" in m for m in messages)
    tifffile.imwrite(tmp_path / "frames.tif", frames)
    out = tmp_path / "burst.tif"
    assert main(["assemble", "--burst", "--scale", "2", "--reference", "sharpest", "--out", str(out),
                 str(tmp_path / "frames.tif")]) == 0
    assert read_stack(out).reference_index == stack.reference_index
    capsys.readouterr()
    with pytest.raises(SystemExit) as exit_:  # argparse's own refusal
        main(["assemble", "--burst", "--scale", "2", "--reference", "sharp", "--out", str(tmp_path / "b.tif"),
              str(tmp_path / "frames.tif")])
    assert exit_.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "'sharpest'" in err[0] and not (tmp_path / "b.tif").exists()


def test_raw_frames_take_the_sharpest_reference(tmp_path):
    pytest.importorskip("rawpy")
    pytest.importorskip("pidng")
    from hbis_torch.capture.dng import write_mosaic_dng
    from hbis_torch.capture.raw import assemble_raw_burst
    from hbis_torch.training.heldout_burst import BurstCondition
    from hbis_torch.training.heldout_raw import BLACK, WHITE, make_raw_burst

    burst = make_raw_burst("chelsea", "GRBG", "indoor", 1, 96, 5, BurstCondition("raw", frames=4))
    mosaics = burst.mosaics.copy()
    for dy in (0, 1):  # frame 0 blurred plane by plane
        for dx in (0, 1):
            mosaics[0, dy::2, dx::2] = np.round(gaussian_filter(mosaics[0, dy::2, dx::2].astype(np.float64), 1.5))
    paths = [str(write_mosaic_dng(tmp_path / f"f{k}.dng", m, "GRBG", BLACK, WHITE, exposure_s=0.01 * (k + 1),
                                  iso=100)) for k, m in enumerate(mosaics)]
    stack, messages = assemble_raw_burst(paths, 1, reference="sharpest")
    k = stack.reference_index
    assert k != 0 and f"reference: frame {k}, the sharpest of the burst (--reference sharpest)" in messages
    assert stack.meta["raw"]["gain"][k] == pytest.approx(1.0)  # the exposures are scaled to the new reference's
    assert stack.meta["raw"]["gain"][0] == pytest.approx((k + 1) / 1.0)


def test_sharpness_is_zero_for_flat_frames():
    assert np.array_equal(frame_sharpness(torch.full((3, 40, 40), 0.5)), np.zeros(3))


@pytest.fixture(scope="module")
def larger():
    """A hand-held burst of 8 equally sharp frames of 192 x 128 px, and its truth."""
    return render_burst("all", 2, 8, 192, 128, seed=5)


def test_blurred_frames_are_named_the_reference_never_and_at_most_half(larger):
    from hbis_torch.capture.sharpness import blurred_frames

    frames = _blurred(_blurred(larger.frames, 3), 0)
    found, line = blurred_frames(luminance(frames), 0)
    assert found == [3] and "left out 1 blurred frame(s): [3]" in line
    assert blurred_frames(luminance(larger.frames), 0) == ([], None)
    trusted = np.ones(8, bool)
    trusted[3] = False  # an untrusted frame is not looked at
    assert blurred_frames(luminance(frames), 0, trusted) == ([], None)
    many = larger.frames
    for k in (1, 2, 4, 5, 6):
        many = _blurred(many, k, 0.5 + 0.1 * k)
    found, _ = blurred_frames(luminance(many), 0)
    assert found == [4, 5, 6]  # the blurriest three of the seven others
    small = np.ascontiguousarray(frames[:, :100, :100])  # under MIN_SIDE_TO_LEAVE_OUT: none
    assert blurred_frames(luminance(small), 0) == ([], None)


def test_reconstruct_leaves_blurred_frames_out_as_if_untrusted(larger):
    from hbis_torch.reconstruct import reconstruct
    from hbis_torch.stack_io import Stack

    frames = _blurred(_blurred(larger.frames, 3), 5, 1.2)
    stack, _ = assemble_burst(frames, 2)
    notes = []
    image = reconstruct(stack, "classical", messages=notes)
    assert any("left out 2 blurred frame(s): [3, 5]" in m for m in notes)
    assert not any("motion is not trusted" in m for m in notes)
    untrusted = Stack(stack.frames, {**stack.meta, "confidence": [0.0 if k in (3, 5) else c
                                                                  for k, c in enumerate(stack.confidence)]})
    assert np.array_equal(image, reconstruct(untrusted, "classical"))
    notes = []
    kept = reconstruct(stack, "classical", messages=notes, keep_blurred=True)
    assert not any("blurred frame" in m for m in notes) and not np.array_equal(kept, image)


def test_keep_blurred_is_refused_on_a_scan_in_one_line(tmp_path, capsys):
    scan = tmp_path / "scan.tif"
    assert main(["simulate", "--scene", "flat", "--h", "2", "--roi", "600,400,16,12", "--out", str(scan), "-q"]) == 0
    capsys.readouterr()
    assert main(["reconstruct", str(scan), "--keep-blurred", "--out", str(tmp_path / "sr.tif")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--keep-blurred is for burst stacks" in err[0] and not (tmp_path / "sr.tif").exists()


def test_rgb_frames_are_measured_on_their_centres_luma(larger):
    from hbis_torch.reconstruct.burst import _rgb_luma

    rgb = torch.from_numpy(larger.frames.astype(np.float32) / 65535)[..., None] * torch.tensor([1.0, 0.9, 0.75])
    assert np.allclose(frame_sharpness(rgb), frame_sharpness(_rgb_luma(rgb)), rtol=1e-5)


def test_raw_bursts_leave_out_their_blurred_frames_too():
    from hbis_torch.capture.raw import raw_burst_stack
    from hbis_torch.reconstruct import reconstruct
    from hbis_torch.training.heldout_burst import BurstCondition
    from hbis_torch.training.heldout_raw import make_raw_burst

    burst = make_raw_burst("chelsea", "RGGB", "indoor", 1, 288, 3, BurstCondition("raw", frames=6))
    mosaics = burst.mosaics.copy()
    for dy in (0, 1):  # frame 4 blurred plane by plane (each colour apart)
        for dx in (0, 1):
            mosaics[4, dy::2, dx::2] = np.round(gaussian_filter(mosaics[4, dy::2, dx::2].astype(np.float64), 1.0))
    stack, _ = raw_burst_stack(mosaics, "RGGB", burst.raw, 1)
    notes = []
    reconstruct(stack, "classical", messages=notes)
    assert any("left out 1 blurred frame(s): [4]" in m for m in notes)
    notes = []
    reconstruct(stack, "classical", messages=notes, keep_blurred=True)
    assert not any("blurred frame" in m for m in notes)


def test_validate_holds_out_no_blurred_frame_of_a_burst(larger):
    from hbis_torch.validate import cross_validate
    from hbis_torch.validate.frames import holdout_frames

    frames = _blurred(larger.frames, holdout_frames(8, 0, 3)[1])
    stack, _ = assemble_burst(frames, 2)
    notes = []
    result = cross_validate(stack, ("single-frame",), holdout=3, messages=notes)
    assert holdout_frames(8, 0, 3)[1] not in result.held_out and len(result.held_out) == 3
    assert any("are blurred" in m for m in notes)
    assert cross_validate(assemble_burst(larger.frames, 2)[0], ("single-frame",), holdout=3).held_out == \
        holdout_frames(8, 0, 3)


def test_a_raw_bursts_blurred_reference_is_named():
    from hbis_torch.capture.raw import raw_burst_stack
    from hbis_torch.training.heldout_burst import BurstCondition
    from hbis_torch.training.heldout_raw import make_raw_burst

    burst = make_raw_burst("chelsea", "RGGB", "indoor", 1, 160, 3, BurstCondition("raw", frames=4))
    mosaics = burst.mosaics.copy()
    for dy in (0, 1):  # the reference blurred plane by plane
        for dx in (0, 1):
            mosaics[0, dy::2, dx::2] = np.round(gaussian_filter(mosaics[0, dy::2, dx::2].astype(np.float64), 1.5))
    stack, messages = raw_burst_stack(mosaics, "RGGB", burst.raw, 1)
    named = [m for m in messages if "is blurred" in m]
    assert stack.reference_index == 0 and len(named) == 1 and asks_to_act(named[0])
    assert "--reference sharpest" in named[0]


def _out_of_focus_reference(seed: int = 5):
    """A hand-held burst (8 frames of 160 x 120, S = 2) whose reference is out of focus by a further
    Gaussian of 1 px, with the renderer's noise: (frames, truth)."""
    rendered = render_burst("similarity", 2, 8, 160, 120, seed=seed, keep_clean=True)
    rng = np.random.default_rng(seed)
    soft = gaussian_filter(rendered.clean[0].astype(np.float64), 1.0)
    electrons = rng.poisson(soft.clip(0, None) * 5000.0) + rng.normal(0, 3.0, soft.shape)
    frames = rendered.frames.copy()
    frames[0] = np.clip(np.round(electrons / 5000.0 * 65535), 0, 65535).astype(np.uint16)
    return frames, rendered.truth


def test_the_blur_that_matches_an_out_of_focus_reference_is_found(burst):
    assert blur_to_reference(luminance(burst), 0) == [0.0] * len(burst)  # equally sharp: none
    frames, _ = _out_of_focus_reference()
    sigmas = blur_to_reference(luminance(frames), 0)
    assert sigmas[0] == 0.0 and all(0.75 <= s <= 1.25 for s in sigmas[1:]), sigmas


def test_one_sharper_frame_does_not_make_the_reference_out_of_focus(burst):
    """Every frame but one as soft as the reference: the reference is as sharp as most, and the
    one sharp frame (on small frames, say, one an object moved out of) is compared as it is."""
    frames = burst.copy()
    for k in range(len(burst)):
        if k != 5:
            frames = _blurred(frames, k)
    grey = luminance(frames)
    sharpness = frame_sharpness(grey)
    assert sharpness[0] < BLURRED_SHARE * sharpness[5]
    assert blur_to_reference(grey, 0) == [0.0] * len(burst)
    trusted = np.zeros(len(burst), dtype=bool)
    trusted[5] = True  # the sharp frame alone looked at: the reference is blurred beside it
    assert blur_to_reference(grey, 0, trusted)[5] > 0 and blur_to_reference(grey, 0, trusted)[1] == 0.0


def test_sharper_frames_compared_through_the_references_blur_keep_their_detail(monkeypatch):
    """Compared as they are, the sharp frames' samples at every edge lose weight against an
    out-of-focus reference, and the image leans on its blur (the reference's own samples at full
    weight on both sides: the next test weighs them)."""
    import hbis_torch.capture.sharpness as sharpness
    import hbis_torch.reconstruct.burst as burst_path
    from hbis_torch.metrics import psnr
    from hbis_torch.reconstruct import reconstruct

    monkeypatch.setattr(burst_path, "BLURRED_REFERENCE_WEIGHT", 1.0)
    frames, truth = _out_of_focus_reference()
    stack, _ = assemble_burst(frames, 2)
    cut = slice(16, -16)
    matched = psnr(reconstruct(stack, "classical")[cut, cut], truth[cut, cut])
    monkeypatch.setattr(sharpness, "blur_to_reference", lambda grey, reference, trusted=None: [0.0] * len(grey))
    plain = psnr(reconstruct(stack, "classical")[cut, cut], truth[cut, cut])
    assert matched > plain + 0.15, (matched, plain)  # (measured: +0.29 dB)


def test_an_out_of_focus_references_own_samples_weigh_less(burst, monkeypatch):
    """Its samples weigh BLURRED_REFERENCE_WEIGHT (said so) and the image gains over fusing them
    at full weight; a reference as sharp as the others keeps weight 1."""
    import hbis_torch.reconstruct.burst as burst_path
    from hbis_torch.metrics import psnr
    from hbis_torch.reconstruct import reconstruct
    from hbis_torch.reconstruct.burst import BLURRED_REFERENCE_WEIGHT, burst_samples

    assert 0 < BLURRED_REFERENCE_WEIGHT < 1
    sharp, _ = assemble_burst(burst, 2)
    assert bool((burst_samples(sharp)[3][0] == 1).all())
    frames, truth = _out_of_focus_reference()
    stack, _ = assemble_burst(frames, 2)
    weights = burst_samples(stack)[3]
    assert bool((weights[0] == BLURRED_REFERENCE_WEIGHT).all()) and float(weights[1:].max()) > 0.99
    cut = slice(16, -16)
    notes: list = []
    lowered = psnr(reconstruct(stack, "classical", messages=notes)[cut, cut], truth[cut, cut])
    assert any("frame 0, is out of focus" in n and "weigh 0.25" in n for n in notes), notes
    monkeypatch.setattr(burst_path, "BLURRED_REFERENCE_WEIGHT", 1.0)
    notes = []
    full = psnr(reconstruct(stack, "classical", messages=notes)[cut, cut], truth[cut, cut])
    assert not any("is out of focus" in n for n in notes)
    assert lowered > full + 0.5, (lowered, full)  # (measured: +1.09 dB)
