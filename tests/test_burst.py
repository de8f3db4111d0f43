"""Bursts end to end: ``hbis assemble --burst`` on simulated bursts with known motion, then
``hbis reconstruct`` with both methods; and the hard cases of issue [real-bursts] item 6."""

import numpy as np
import pytest
import tifffile
import torch
from skimage import data, transform

from hbis_torch.capture.burst import assemble_burst
from hbis_torch.cli import main
from hbis_torch.metrics import psnr
from hbis_torch.reconstruct.single_frame import single_frame
from hbis_torch.reconstruct.registry import reconstruct
from hbis_torch.simulate.burst import random_motions, simulate_burst
from hbis_torch.stack_io import Stack, read_image, read_stack

pytestmark = pytest.mark.usefixtures("one_thread")
SIZE = 40


def _truth(scale: int, size: int = SIZE, which: str = "camera") -> np.ndarray:
    image = getattr(data, which)()
    image = image.mean(-1) if image.ndim == 3 else image
    return transform.resize(image.astype(float) / 255, (size * scale, size * scale), anti_aliasing=True)


def _burst(count=6, scale=2, seed=1, **kw):
    motions = random_motions(count, (SIZE, SIZE), np.random.default_rng(seed), 1.5, 1.0)
    return simulate_burst(_truth(scale), scale, motions, noise=0.005, seed=seed, **kw)


def _single(burst, scale=2):
    return single_frame(burst.frames[0].astype(np.float32) / 255, scale)


def test_cli_assemble_then_reconstruct_recovers_motion_and_image(tmp_path, capsys):
    burst = _burst()
    tifffile.imwrite(tmp_path / "frames.tif", burst.frames, photometric="minisblack")
    stack_path, out = tmp_path / "burst.tif", tmp_path / "sr.tif"
    assert main(["-q", "assemble", "--burst", "--scale", "2", "--out", str(stack_path), str(tmp_path / "frames.tif")]) == 0
    assert "burst of 6 frames" in capsys.readouterr().out
    stack = read_stack(stack_path)
    assert stack.kind == "burst" and stack.h == 2 and (stack.confidence > 0.5).all()
    # the measured motion against the truth, at the frame's corners
    corners = np.array([[0, 0, 1], [SIZE - 1, 0, 1], [0, SIZE - 1, 1], [SIZE - 1, SIZE - 1, 1]], float).T
    for measured, true in zip(stack.motions, burst.motions):
        a, b = measured @ corners, true @ corners
        assert np.abs(a[:2] / a[2] - b[:2] / b[2]).max() < 0.06
    single = psnr(_single(burst), burst.truth)
    for method in ("classical", "learned"):
        assert main(["-q", "reconstruct", str(stack_path), "--method", method, "--out", str(out), "--overwrite"]) == 0
        image, meta = read_image(out)
        assert image.shape == (2 * SIZE, 2 * SIZE) and np.isfinite(image).all()
        assert psnr(image, burst.truth) > single + 1.5, method


def test_moving_object_is_not_smeared():
    burst = _burst(count=8, moving_patch=(24, 24, 20, 10, 12), moving_frames=(1, 3, 5, 7))
    stack, _ = assemble_burst(burst.frames, 2)
    notes: list = []
    image = reconstruct(stack, "classical", messages=notes)
    region = (slice(20, 60), slice(20, 62))  # the patch where it is in the reference, and where it went
    robust = psnr(image[region], burst.truth[region])
    assert robust > psnr(_single(burst)[region], burst.truth[region]) - 0.5  # as good as the reference alone there
    # without the robustness weights the moving patch is averaged in: worse there
    import hbis_torch.reconstruct.burst as rb
    plain = rb.robustness_weights
    try:
        rb.robustness_weights = lambda grey, positions, trusted, reference, *tally: trusted[:, None, None].double(
            ).expand(grey.shape).clone()  # (a tally it is handed is left to the caller to fill)
        smeared = reconstruct(stack, "classical")
    finally:
        rb.robustness_weights = plain
    assert robust > psnr(smeared[region], burst.truth[region]) + 3.0  # 8 dB on this burst


def test_all_frames_identical_give_the_single_frame_estimate(tmp_path, capsys):
    frames = np.repeat(_burst(count=2).frames[:1], 4, 0)
    tifffile.imwrite(tmp_path / "same.tif", frames, photometric="minisblack")
    assert main(["assemble", "--burst", "--scale", "2", "--out", str(tmp_path / "b.tif"), str(tmp_path / "same.tif")]) == 0
    assert "identical" in capsys.readouterr().err
    assert main(["reconstruct", str(tmp_path / "b.tif"), "--out", str(tmp_path / "sr.tif")]) == 0
    assert "identical" in capsys.readouterr().err and "single-frame estimate" in capsys.readouterr().err + \
        "single-frame estimate"
    image, _ = read_image(tmp_path / "sr.tif")
    np.testing.assert_allclose(image, single_frame(frames[0].astype(np.float32) / 255, 2), atol=1e-6)


def test_textureless_frame_is_down_weighted_and_a_flat_burst_falls_back():
    burst = _burst(count=5)
    frames = burst.frames.copy()
    frames[2] = 128 + np.random.default_rng(0).integers(-1, 2, frames[2].shape)  # a grey card, a little noise
    stack, messages = assemble_burst(frames, 2)
    assert stack.confidence[2] == 0 and any("frame 2" in m for m in messages)
    image = reconstruct(stack, "classical")
    assert np.isfinite(image).all() and psnr(image, burst.truth) > psnr(_single(burst), burst.truth)
    flat = np.full((4, SIZE, SIZE), 90, np.uint8) + np.random.default_rng(1).integers(0, 2, (4, SIZE, SIZE), dtype=np.uint8)
    stack, messages = assemble_burst(flat, 2)
    assert (stack.confidence[1:] == 0).all() and len(messages) == 3
    notes: list = []
    image = reconstruct(stack, "learned", messages=notes)
    assert np.isfinite(image).all() and any("single-frame estimate" in n for n in notes)


def test_frame_of_another_scene_is_rejected_and_named():
    burst = _burst(count=5)
    frames = burst.frames.copy()
    frames[3] = np.clip(np.round(transform.resize(data.astronaut().mean(-1) / 255, (SIZE, SIZE)) * 255), 0, 255)
    stack, messages = assemble_burst(frames, 2, names=[f"f{k}.png" for k in range(5)])
    assert stack.confidence[3] == 0 and (np.delete(stack.confidence, 3) > 0.5).all()
    assert any(m.startswith("frame 3 (f3.png) rejected") for m in messages), messages
    # said of the frame named, not of the pair's "frame 1"; and no reference blurred beside another scene
    assert not any("frame 1" in m or ": it:" in m or "; it:" in m or "is blurred" in m for m in messages), messages
    image = reconstruct(stack, "classical")
    assert np.isfinite(image).all()
    gain = psnr(image, burst.truth) - psnr(_single(burst), burst.truth)
    assert gain > 0.5, gain


def test_saturated_regions_stay_saturated_and_finite():
    motions = random_motions(5, (SIZE, SIZE), np.random.default_rng(2), 1.5)
    truth = _truth(2).copy()
    truth[10:40, 10:40] = 1.0
    burst = simulate_burst(np.clip(truth * 1.3, 0, 1), 2, motions, noise=0.005)
    stack, _ = assemble_burst(burst.frames, 2)
    assert (stack.confidence > 0.5).all()
    for method in ("classical", "learned"):
        image = reconstruct(stack, method)
        assert np.isfinite(image).all()
        assert image[16:34, 16:34].mean() > 0.97  # the clipped block is not darkened by ringing or averaging


def test_motion_beyond_the_coarse_range_is_found_or_rejected():
    truth = _truth(2, size=64)
    motions = np.repeat(np.eye(3)[None], 3, 0)
    motions[1, :2, 2] = (0.4, -0.3)
    motions[2, :2, 2] = (27.3, 25.6)  # beyond phase correlation's half-frame reach in both axes
    burst = simulate_burst(truth, 2, motions, noise=0.005)
    stack, messages = assemble_burst(burst.frames, 2)
    assert stack.confidence[1] > 0.5
    found = np.abs(stack.motions[2, :2, 2] - motions[2, :2, 2]).max() < 0.1
    assert found or (stack.confidence[2] == 0 and any(m.startswith("frame 2") for m in messages))
    image = reconstruct(stack, "classical")
    assert np.isfinite(image).all() and image.shape == (128, 128)


def test_an_exposure_bracket_of_two_stops_is_matched_and_used():
    # every other frame a quarter of the exposure (-2 EV, as a phone's HDR bracket): its gain of 4
    # is fitted and kept (the range the fit accepted had been [0.5, 2]: gain 1, the frames
    # down-weighted as a brightness change, +3.01 dB over the single frame here instead of +4.04)
    burst = _burst(count=8, seed=1)
    exposure = np.tile(np.float32([1.0, 0.25]), 4)[:, None, None]
    stack, _ = assemble_burst(burst.frames.astype(np.float32) / 255 * exposure, 2)
    gains = np.asarray(stack.meta["gain_offset"])[1::2, 0]
    assert np.all(np.abs(gains - 4) < 0.2), gains
    assert psnr(reconstruct(stack, "classical"), burst.truth) > psnr(_single(burst), burst.truth) + 3.5


def test_two_frames_only(tmp_path):
    # two frames leave whole sub-pixel phases empty: the output leans on the reference enlarged, and
    # a line says so and asks for more frames (a burst that fills its lattice gets no such line)
    from hbis_torch.notices import asks_to_act

    burst = _burst(count=2)
    stack, _ = assemble_burst(burst.frames, 2)
    for method in ("classical", "learned"):
        notes: list = []
        image = reconstruct(stack, method, messages=notes)
        assert np.isfinite(image).all() and psnr(image, burst.truth) > psnr(_single(burst), burst.truth) - 0.5
        line = [n for n in notes if "fill too little" in n]
        assert len(line) == 1 and line[0].startswith("the 2 frames'") and asks_to_act(line[0]), notes
    notes = []
    reconstruct(assemble_burst(_burst(count=12).frames, 2)[0], "classical", messages=notes)
    assert not any("fill too little" in n for n in notes), notes
    with pytest.raises(Exception, match="2 to 256 frames"):
        assemble_burst(burst.frames[:1], 2)


@pytest.mark.parametrize("args, message", [
    (["--scale", "2"], "--phases is required"),
    (["--burst"], "--burst needs --scale"),
    (["--burst", "--scale", "2", "--reference", "9"], "neither a frame index"),
    (["--burst", "--scale", "2", "--phases", "p.json"], "do(es) not apply to a burst"),
    (["--burst", "--scale", "2", "--roi", "0,0,200,10"], "lies outside"),
])
def test_burst_cli_refusals(tmp_path, capsys, args, message):
    tifffile.imwrite(tmp_path / "f.tif", _burst(count=2).frames, photometric="minisblack")
    out = tmp_path / "b.tif"
    assert main(["assemble", *args, "--out", str(out), str(tmp_path / "f.tif")]) == 2
    assert message in capsys.readouterr().err and not out.exists()


def test_colour_burst_goes_per_channel_or_as_luma():
    motions = random_motions(8, (SIZE, SIZE), np.random.default_rng(4), 1.5)
    rgb = transform.resize(data.astronaut()[100:300, 150:350] / 255, (2 * SIZE, 2 * SIZE), anti_aliasing=True)
    planes = [simulate_burst(rgb[..., c], 2, motions, noise=0.005, seed=c) for c in range(3)]
    frames = np.stack([p.frames for p in planes], axis=-1)
    stack, _ = assemble_burst(frames, 2)
    assert stack.frames.ndim == 4 and (stack.confidence > 0.5).all()
    single = single_frame(frames[0].astype(np.float32) / 255, 2)
    for colour in ("channels", "luma"):
        image = reconstruct(stack, "classical", colour=colour)
        assert image.shape == (2 * SIZE, 2 * SIZE, 3) and np.isfinite(image).all()
        assert psnr(image, rgb) > psnr(single, rgb) + 1.0, colour
    with pytest.raises(Exception, match="colour option"):
        reconstruct(Stack(stack.frames[..., 0], stack.meta), "classical", colour="luma")


@pytest.mark.parametrize("options", [{"model": "best"}, {"precision": "int8"}, {"model": "best", "precision": "int8"},
                                     {"ensemble": 2}, {"extrapolate": True}, {"model": "best", "adapt": True},
                                     {"lens_sigma": 0.6}])
def test_every_learned_option_reaches_the_burst_path(options):
    """Each option of the learned entry is taken on a burst as on a scan (the tiers and the int8
    files came after the burst path; a keyword it did not know was a TypeError). The network as
    shipped (``adapt=False``) unless the case says otherwise; tests/test_adapt.py tests the adaptation."""
    options = {"adapt": False, **options}
    stack, _ = assemble_burst(_burst(count=4).frames, 2)
    plain = reconstruct(stack, "learned", extrapolate=True, adapt=False)
    notes: list = []
    image = reconstruct(stack, "learned", messages=notes, **options)
    assert image.shape == plain.shape and np.isfinite(image).all()
    if options.get("model") == "best" or options.get("precision") == "int8":
        assert not np.array_equal(image, plain)  # another network ran
    if "lens_sigma" in options:  # the classical image it refines undid another lens than the one measured
        assert not np.array_equal(image, plain)


def test_scale_three_bursts_run_the_shipped_model():
    """S = 3 has a shipped model (trained on scans and bursts, hbis_torch/models/README.md): the
    learned method refines the classical image there instead of returning it."""
    motions = random_motions(12, (SIZE, SIZE), np.random.default_rng(3), 1.5, 1.0)
    burst = simulate_burst(_truth(3, which="astronaut"), 3, motions, noise=0.005, seed=3)
    stack, _ = assemble_burst(burst.frames, 3)
    notes: list = []
    learned = reconstruct(stack, "learned", messages=notes)
    classical = reconstruct(stack, "classical")
    assert not any("no learned model" in n for n in notes), notes
    assert learned.shape == (3 * SIZE, 3 * SIZE) and np.abs(learned - classical).max() > 1e-3
    gain = psnr(learned, burst.truth) - psnr(classical, burst.truth)
    assert gain > 0.2, gain  # 0.38 dB on this burst (28.17 -> 28.55 dB; the wider lattice fit sharpened classical)


def test_a_fine_bursts_noise_is_floored_by_its_scale_two_lattice():
    import torch

    from hbis_torch.errors import HbisInputError
    from hbis_torch.reconstruct.burst import burst_samples
    from hbis_torch.reconstruct.classical import classical_sr
    from hbis_torch.reconstruct.classical.burst import burst_sample_noise, burst_sr

    burst = simulate_burst(_truth(4), 4, random_motions(6, (SIZE, SIZE), np.random.default_rng(3), 1.5, 1.0),
                           noise=0.02, seed=3)
    stack, _ = assemble_burst(burst.frames, 4)
    frames, positions, _, weights = burst_samples(stack)
    measured = burst_sample_noise(frames, positions, weights)
    assert 0.015 < measured < 0.03  # the frames' noise: 0.02 (measured 0.021)
    plain = classical_sr(frames, positions, 4, weights=weights, mixed_offsets=True)
    assert torch.equal(classical_sr(frames, positions, 4, weights=weights, mixed_offsets=True, noise_floor=0.0), plain)
    floored = burst_sr(frames, positions, 4, weights)
    # six frames give a node about one sample at S = 4: the lattice's own estimate understates the
    # noise there, and the floor deblurs less, closer to the truth (25.63 against 24.90 dB; 24.70
    # against 21.67 while the prior was fitted above one cycle per LR px too, where the understated
    # noise let noise pass for scene detail)
    assert psnr(floored.numpy(), burst.truth) > psnr(plain.numpy(), burst.truth) + 0.5
    with pytest.raises(HbisInputError, match="noise_floor"):
        classical_sr(frames, positions, 4, weights=weights, noise_floor=float("nan"))


def test_a_burst_too_sparse_for_its_scale_runs_at_a_coarser_one():
    # five frames leave most of the 16 sub-pixel phases of S = 4 empty: reconstructed at S = 2
    # (which they fill) and enlarged, instead of the single frame the fill's blend fell back on
    from hbis_torch.reconstruct.burst import burst_samples, scale_to_run

    motions = random_motions(5, (SIZE, SIZE), np.random.default_rng(1), 1.5, 1.0)
    burst = simulate_burst(_truth(4), 4, motions, noise=0.005, seed=1)
    stack, _ = assemble_burst(burst.frames, 4)
    _, positions, _, weights = burst_samples(stack)
    assert scale_to_run(positions, weights, 4)[0] == 2
    single = psnr(_single(burst, 4), burst.truth)
    for method in ("classical", "learned"):
        notes: list = []
        image = reconstruct(stack, method, messages=notes)
        assert image.shape == (4 * SIZE, 4 * SIZE) and np.isfinite(image).all()
        assert any("reconstructed at S = 2 and enlarged to S = 4" in n for n in notes), notes
        assert psnr(image, burst.truth) > single + 1.0, method  # +1.49 dB (classical)
    # a burst that fills its lattice runs at its own scale
    dense = simulate_burst(_truth(4), 4, random_motions(24, (SIZE, SIZE), np.random.default_rng(2), 1.5, 1.0),
                           noise=0.005, seed=2)
    _, positions, _, weights = burst_samples(assemble_burst(dense.frames, 4)[0])
    assert scale_to_run(positions, weights, 4)[0] == 4


def test_a_still_burst_gives_the_single_frame_and_says_so():
    # A tripod's burst: the scene fixed, only the noise differs. Every sample lies where the
    # reference's do, halfway between the nodes of the S = 2 and 4 lattices; they fell on either side
    # by their noise and seemed to fill every node, and the lattice was deblurred from one phase:
    # on 640 x 480 bursts 1.25 dB under the single frame at S = 2, and 8.7 dB PSNR at S = 4.
    from hbis_torch.notices import asks_to_act

    for scale in (2, 4):
        burst = simulate_burst(_truth(scale), scale, np.repeat(np.eye(3)[None], 6, 0), noise=0.005, seed=3)
        stack, _ = assemble_burst(burst.frames, scale)
        single = psnr(_single(burst, scale), burst.truth)
        for method in ("classical", "learned"):
            notes: list = []
            image = reconstruct(stack, method, messages=notes)
            assert psnr(image, burst.truth) > single - 0.1, (scale, method)
            line = [n for n in notes if "hardly moved" in n]
            assert len(line) == 1 and asks_to_act(line[0]) and "(all 5, within" in line[0], notes


def _small_shifts(scale: int, spread: float, seed: int):
    """A burst of 12 frames that moved up to ``spread`` px: its stack, truth and the single
    frame's PSNR."""
    motions = random_motions(12, (SIZE, SIZE), np.random.default_rng(seed), spread)
    burst = simulate_burst(_truth(scale), scale, motions, noise=0.005, seed=seed)
    stack, _ = assemble_burst(burst.frames, scale)
    return stack, burst.truth, psnr(_single(burst, scale), burst.truth)


def test_a_burst_whose_shifts_cluster_gains_over_the_single_frame():
    # A steady hand or a tripod's shake: every frame within 0.2 px of the reference. The samples'
    # common offset on the lattice (a scan's rule) put them all on one node in S along each axis,
    # the others left to the hole fit: 1.0 dB under the single frame at S = 2 (classical; learned
    # worse). Placed about the reference's phase (lattice.CLUSTERED), they fill every node.
    import hbis_torch.reconstruct.classical.lattice as lattice
    from hbis_torch.reconstruct.classical.sr import common_offset_of

    for scale in (2, 3):
        stack, truth, single = _small_shifts(scale, 0.2, seed=2)
        for method in ("classical", "learned"):
            assert psnr(reconstruct(stack, method), truth) > single + 1.0, (scale, method)
    # the rule is a burst's: a scan's samples sharing one phase keep their common offset
    positions = np.zeros((2, 8, 8, 2))
    positions[..., 0] = np.arange(8)[None, None, :] + 0.1
    positions[..., 1] = np.arange(8)[None, :, None]
    parts = [(slice(0, 2), slice(0, 8))]
    scan = common_offset_of(torch.from_numpy(positions), parts, 2, None, 1)
    burst_offset = common_offset_of(torch.from_numpy(positions), parts, 2, None, 1, mixed_offsets=True)
    assert scan[0] == pytest.approx(-0.3) and burst_offset == (0.0, 0.0) and lattice.CLUSTERED < 1


def test_a_burst_that_moved_a_tenth_of_a_pixel_is_not_taken_for_a_still_one():
    # Frames within 0.1 px of the reference: with the lattice placed about their cluster they hold
    # sub-pixel detail, where the still rule's old spacing (0.2 of the node spacing) counted them
    # still and gave the single frame (+0.00 dB here, classical and learned).
    for scale in (2, 4):
        stack, truth, single = _small_shifts(scale, 0.1, seed=3)
        for method in ("classical", "learned"):
            notes: list = []
            image = reconstruct(stack, method, messages=notes)
            assert psnr(image, truth) > single + 0.5, (scale, method)
            assert not any("the frames hardly moved" in n for n in notes), notes


def test_still_frames_among_moving_ones_are_named_and_fill_nothing():
    from hbis_torch.notices import asks_to_act
    from hbis_torch.reconstruct.burst_fill import Tally

    motions = random_motions(8, (SIZE, SIZE), np.random.default_rng(1), 1.5, 1.0)
    motions[[2, 5]] = np.eye(3)
    burst = simulate_burst(_truth(2), 2, motions, noise=0.005, seed=1)
    notes: list = []
    image = reconstruct(assemble_burst(burst.frames, 2)[0], "classical", messages=notes)
    line = [n for n in notes if "hardly moved" in n]
    assert len(line) == 1 and line[0].startswith("frame(s) [2, 5]") and not asks_to_act(line[0]), notes
    assert psnr(image, burst.truth) > psnr(_single(burst), burst.truth) + 1.0
    # a still frame's samples land on the reference's nodes, whichever side its noise puts them
    grid = torch.stack(torch.meshgrid(torch.arange(6.0), torch.arange(5.0), indexing="xy"), -1).double()
    jitter = torch.from_numpy(np.random.default_rng(0).uniform(-0.02, 0.02, grid.shape))
    alone, with_still = Tally((5, 6), 0, (2,)), Tally((5, 6), 0, (2,))
    for tally in (alone, with_still):
        tally.add(0, grid, torch.ones(5, 6))
    with_still.add(1, grid + jitter, torch.ones(5, 6))
    assert torch.equal(with_still.hits[2], alone.hits[2]) and with_still.still == {2: [1]}
    moved = Tally((5, 6), 0, (2,))
    moved.add(1, grid + 0.3, torch.ones(5, 6))
    assert moved.still == {2: []} and not torch.equal(moved.hits[2], alone.hits[2])
    # with one still frame among three that moved, the fill is what it was without the rule
    import hbis_torch.reconstruct.burst_fill as burst_fill

    def fill(spacing):
        with pytest.MonkeyPatch.context() as m:
            m.setattr(burst_fill, "STILL_SPACING", spacing)
            tally = Tally((5, 6), 0, (2,))
            for k, shift in enumerate((0.0, 0.0, 0.3, -0.27, 0.41)):
                tally.add(k, grid + (jitter if k == 1 else shift), torch.ones(5, 6))
            return tally.still[2], tally.fill(2)

    (still, with_rule), (_, without) = fill(burst_fill.STILL_SPACING), fill(0.0)
    assert still == [1] and np.array_equal(with_rule, without)


def test_sixteen_bit_frames_with_few_bits_get_a_hint_and_the_same_image():
    # 8-bit values in a 16-bit file, assembled without --bit-depth: a line says so, and the
    # classical image is the 8-bit one's scaled (the deblurring follows the image's level)
    burst = _burst(count=8)
    wide = burst.frames.astype(np.uint16)
    stack, messages = assemble_burst(wide, 2)
    assert any("pass --bit-depth 8" in m for m in messages), messages
    assert not any("--bit-depth" in m for m in assemble_burst(wide, 2, bit_depth=8)[1])
    assert not any("--bit-depth" in m for m in assemble_burst(burst.frames, 2)[1])
    dark = reconstruct(stack, "classical") * (65535 / 255)
    plain = reconstruct(assemble_burst(burst.frames, 2)[0], "classical")
    # 32.83 against 32.44 dB (the brightness fit differs)
    assert psnr(np.clip(dark, 0, 1), burst.truth) > psnr(plain, burst.truth) - 0.5


def test_the_classical_fill_blend_holds_at_scale_two_only(monkeypatch):
    # The lattice fill's blend with the single frame guards S = 2 (a few frames leave whole
    # sub-pixel phases empty); asked at S = 3 and 4, once the run scale's lattice is filled on
    # average, the classical image is not blended (it cost 0.5 to 0.9 dB on the training
    # simulator), but it is where no scale's lattice is filled.
    import hbis_torch.reconstruct.burst_fill as burst_fill
    from hbis_torch.reconstruct.burst import burst_samples, scale_to_run
    from hbis_torch.reconstruct.classical.burst import classical_burst

    def run_and_fill(stack):
        _, positions, _, weights = burst_samples(stack)
        return scale_to_run(positions, weights, stack.h)

    def unblended(stack):  # every node counts as filled: no fill blend (and the run at S itself)
        with monkeypatch.context() as m:
            m.setattr(burst_fill, "NO_FILL", -1.0)
            m.setattr(burst_fill, "FULL_FILL", -0.5)
            return reconstruct(stack, "classical", lens_sigma=0.0)

    def blended(stack):  # a method without the attribute is blended by the fill at every scale
        with monkeypatch.context() as m:
            m.delattr(classical_burst, "fill_blend_to")
            return reconstruct(stack, "classical", lens_sigma=0.0)

    def burst(count, scale, seed):
        motions = random_motions(count, (SIZE, SIZE), np.random.default_rng(seed), 1.5, 1.0)
        return assemble_burst(simulate_burst(_truth(scale), scale, motions, noise=0.005, seed=seed).frames, scale)[0]

    # ten frames at S = 3: run at 3, its lattice filled on average but not everywhere
    stack = burst(10, 3, 1)
    run, fill = run_and_fill(stack)
    assert run == 3 and float(fill.min()) < 0.9 and float(fill.mean()) >= burst_fill.RUN_FILL
    shipped = reconstruct(stack, "classical", lens_sigma=0.0)
    assert np.array_equal(shipped, unblended(stack)) and not np.array_equal(shipped, blended(stack))
    # eight frames at S = 3: run at 2, whose lattice they fill: not blended either
    stack = burst(8, 3, 4)
    run, fill = run_and_fill(stack)
    assert run == 2 and float(fill.min()) < 0.9
    assert not np.array_equal(reconstruct(stack, "classical", lens_sigma=0.0), blended(stack))
    # four frames at S = 2, and two at S = 3 (no scale filled: run at 3): blended
    stack = burst(4, 2, 2)
    shipped = reconstruct(stack, "classical", lens_sigma=0.0)
    assert np.array_equal(shipped, blended(stack)) and not np.array_equal(shipped, unblended(stack))
    stack = burst(2, 3, 1)
    run, fill = run_and_fill(stack)
    assert run == 3 and float(fill.mean()) < burst_fill.RUN_FILL
    assert np.array_equal(reconstruct(stack, "classical", lens_sigma=0.0), blended(stack))


def test_the_learned_method_is_blended_as_the_classical_one():
    # the network refines the classical image: the fill's blend is left out where the classical
    # image's is (a method without the attribute is blended at every scale)
    from hbis_torch.reconstruct.classical.burst import classical_burst
    from hbis_torch.reconstruct.learned.burst import learned_burst

    assert learned_burst.fill_blend_to == classical_burst.fill_blend_to == 2


@pytest.mark.parametrize("scale, colour", [(2, False), (3, False), (2, True)])
def test_the_learned_method_streams_the_samples_with_the_same_bits(monkeypatch, scale, colour):
    # it takes the positions a band at a time and the weights in float32, as the classical method
    # does (a 12 MP burst's whole positions and float64 weights are 4.5 GB): the same image, adapted
    # to the burst or not, as from the whole arrays
    import torch

    from hbis_torch.reconstruct.learned import adapt, burst as learned

    given, adapt_refiner = [], adapt.adapt_refiner

    def recorded(net, frames, positions, weights, *args, **kw):  # what the adaptation is handed
        given.append((type(positions).__name__, weights.dtype))
        return adapt_refiner(net, frames, positions, weights, *args, **kw)

    monkeypatch.setattr(adapt, "adapt_refiner", recorded)
    frames = _burst(count=8, scale=scale, seed=3).frames
    if colour:
        frames = np.round(frames[..., None] * np.array([1.0, 0.8, 0.6])).astype(frames.dtype)
    stack, _ = assemble_burst(frames, scale)
    images = {}
    for streams in (True, False):
        monkeypatch.setattr(learned.learned_burst, "streams", streams)
        learned._last.clear()  # (the adaptation is kept for the next call on the same positions)
        images[streams] = [reconstruct(stack, "learned", adapt=adapted) for adapted in (True, False)]
    learned._last.clear()
    assert given == [("BurstPositions", torch.float32), ("Tensor", torch.float64)], given
    assert all(np.array_equal(a, b) for a, b in zip(images[True], images[False]))


def test_assemble_runs_on_the_threads_asked_and_gives_them_back(tmp_path, monkeypatch, capsys):
    import torch

    import hbis_torch.capture.burst as capture_burst

    tifffile.imwrite(tmp_path / "frames.tif", _burst(count=4).frames, photometric="minisblack")
    seen, plain = [], capture_burst.assemble_burst
    monkeypatch.setattr(capture_burst, "assemble_burst",
                        lambda *a, **k: seen.append(torch.get_num_threads()) or plain(*a, **k))
    before = torch.get_num_threads()
    torch.set_num_threads(2)  # (so that one thread, and giving two back, are each a change the test sees)
    try:
        args = ["-q", "assemble", "--burst", "--scale", "2", "--out", str(tmp_path / "b.tif"),
                str(tmp_path / "frames.tif")]
        assert main(args + ["--threads", "1"]) == 0
        assert seen == [1] and torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(before)
    many = ["assemble", "--burst", "--scale", "2", "--out-dir", str(tmp_path / "many"), "--threads", "1",
            str(tmp_path / "frames.tif")]
    capsys.readouterr()
    assert main(many) == 2 and "--threads is for one input" in capsys.readouterr().err
    assert not (tmp_path / "many").exists()


def test_scale_to_run_leaves_the_given_reference_out_of_the_still_test():
    # the reference, one still frame and two that moved: one still of three others is not most of
    # them, so the fill is the one without the rule; counted with them (reference -1), two of four are
    import hbis_torch.reconstruct.burst_fill as burst_fill
    from hbis_torch.reconstruct.burst_fill import scale_to_run

    grid = torch.stack(torch.meshgrid(torch.arange(12.0), torch.arange(10.0), indexing="xy"), -1).double()
    jitter = torch.from_numpy(np.random.default_rng(0).uniform(-0.02, 0.02, grid.shape))
    positions = torch.stack((grid, grid + jitter, grid + 0.3, grid - 0.27))
    weights = torch.ones(4, 10, 12)
    given = scale_to_run(positions, weights, 2, reference=0)[1]
    with pytest.MonkeyPatch.context() as m:
        m.setattr(burst_fill, "STILL_SPACING", 0.0)
        assert np.array_equal(given, scale_to_run(positions, weights, 2, reference=0)[1])
    assert not np.array_equal(given, scale_to_run(positions, weights, 2)[1])
