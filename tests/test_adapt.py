"""Test-time adaptation of the refiner to a burst (hbis_torch.reconstruct.learned.adapt)."""

import shutil

import numpy as np
import pytest
import torch
from skimage import data, transform

from hbis_torch.capture.burst import assemble_burst
from hbis_torch.metrics import psnr
from hbis_torch.reconstruct.burst import burst_samples, corrected_frames
from hbis_torch.reconstruct.classical.burst import burst_sr
from hbis_torch.reconstruct.learned import adapt
from hbis_torch.reconstruct.learned import burst as learned
from hbis_torch.reconstruct.learned.runtime import shipped_model_path
from hbis_torch.reconstruct.registry import reconstruct
from hbis_torch.simulate.burst import random_motions, simulate_burst

pytestmark = pytest.mark.usefixtures("one_thread")
SIZE = 32


def _truth(scale: int, which: str = "camera", size: int = SIZE) -> np.ndarray:
    image = getattr(data, which)()
    image = image.mean(-1) if image.ndim == 3 else image
    return transform.resize(image.astype(float) / 255, (size * scale, size * scale), anti_aliasing=True)


def _stack(which="camera", blur_px=0.0, count=8, seed=5, size=SIZE):
    motions = random_motions(count, (size, size), np.random.default_rng(seed), 1.5, 1.0)
    burst = simulate_burst(_truth(2, which, size), 2, motions, noise=0.01, seed=seed, blur_px=blur_px)
    stack, _ = assemble_burst(burst.frames, 2)
    return stack, burst.truth


def test_folds_deal_the_other_frames_and_need_two():
    assert adapt.folds_of(9, 0, [True] * 9) == [[1, 5], [2, 6], [3, 7], [4, 8]]
    assert adapt.folds_of(3, 1, [True] * 3) == [[0], [2]]
    assert adapt.folds_of(4, 0, [True, True, False, True]) == [[1], [3]]
    assert adapt.folds_of(3, 0, [True, True, False]) == []  # one frame to fit and check on: no adaptation


def test_pytorch_weights_are_found_beside_the_onnx_file(tmp_path):
    onnx = shipped_model_path(2)
    assert adapt.pytorch_weights(onnx) == onnx.with_suffix(".pt")
    assert adapt.pytorch_weights(onnx.with_name("hbis_sr_h2.int8.onnx")) == onnx.with_suffix(".pt")
    shutil.copy(onnx, tmp_path / "mine.onnx")
    assert adapt.pytorch_weights(tmp_path / "mine.onnx") is None


def test_adaptation_is_deterministic_keeps_the_best_check_and_leaves_the_network_alone():
    stack, _ = _stack(size=24)
    frames, positions, _, weights = burst_samples(stack, corrected_frames(stack))
    net = adapt.load_refiner(shipped_model_path(2).with_suffix(".pt"))
    before = {k: v.clone() for k, v in net.state_dict().items()}
    runs = [adapt.adapt_refiner(net, frames, positions, weights, 2, (0.0, 1e-4), stack.reference_index, burst_sr,
                                steps=10) for _ in range(2)]
    assert all(torch.equal(before[k], v) for k, v in net.state_dict().items())
    one, two = (r.net.state_dict() for r in runs)
    assert all(torch.equal(one[k], two[k]) for k in one)
    assert runs[0].step in (0, 5, 10) and runs[0].error_after <= runs[0].error_before
    assert np.isfinite([runs[0].error_after, runs[0].error_classical]).all()


@pytest.mark.parametrize("which, blur_px", [("camera", 0.0), ("astronaut", 0.8)])
def test_adapting_does_not_lose_where_the_network_already_fits(which, blur_px):
    """On the simulator the network was trained on, adapting has little to gain; the anchor and
    the held-out check keep it from losing much (measured -0.06 and +0.20 dB against the shipped
    network)."""
    stack, truth = _stack(which, blur_px)
    notes: list = []
    adapted = reconstruct(stack, "learned", messages=notes)
    shipped = reconstruct(stack, "learned", adapt=False)
    assert any("adapted to the burst's own frames" in n for n in notes), notes
    assert psnr(adapted, truth) > psnr(shipped, truth) - 0.1


def test_the_forward_models_lens_moves_from_validates_towards_the_lens_undone(monkeypatch):
    assert adapt.forward_blur(0.6) == adapt.BLUR_PX  # the default weight, 0: validate's lens
    monkeypatch.setattr(adapt, "LENS_WEIGHT", 0.5)
    assert adapt.forward_blur(0.6) == pytest.approx((0.6 + adapt.BLUR_PX) / 2)
    monkeypatch.setattr(adapt, "LENS_WEIGHT", 1.0)
    assert adapt.forward_blur(0.6) == 0.6 and adapt.forward_blur(0.1) == adapt.BLUR_PX


def test_the_lens_estimates_doubt_moves_the_forward_model_towards_the_lens_undone():
    """Where the classical image kept some of the edges' blur (the estimate's doubt), the
    adaptation's forward model blurs by the lens undone, not validate's lens; no doubt changes
    nothing, to the bit."""
    assert adapt.forward_blur(0.45, 0.0) == adapt.forward_blur(0.45) == adapt.BLUR_PX
    assert adapt.forward_blur(0.45, 1.0) == 0.45 and adapt.forward_blur(0.1, 1.0) == adapt.BLUR_PX
    assert adapt.forward_blur(0.45, 0.5) == pytest.approx((0.45 + adapt.BLUR_PX) / 2)
    assert adapt.forward_blur(0.45, 3.0) == 0.45  # (a weight of at most 1)


@pytest.mark.parametrize("which", ["camera", "astronaut"])
def test_adapting_through_the_lens_undone_does_not_teach_the_network_to_blur(monkeypatch, which):
    """A lens of 0.6 LR px, undone by the classical image. Through validate's 0.2 LR px alone the
    frames read softer than predicted and the adaptation teaches the network to blur (measured
    -0.81 and -0.84 dB against the unadapted network here); through the lens undone (a weight of
    1) it does not (+0.00 and +0.04)."""
    stack, truth = _stack(which, blur_px=0.6)
    shipped = psnr(reconstruct(stack, "learned", lens_sigma=0.6, adapt=False), truth)
    scores = {}
    for weight in (0.0, 1.0):
        monkeypatch.setattr(adapt, "LENS_WEIGHT", weight)
        learned._last.clear()  # (the adaptation is kept for the next call on the same positions)
        scores[weight] = psnr(reconstruct(stack, "learned", lens_sigma=0.6), truth)
    learned._last.clear()
    assert scores[1.0] > shipped - 0.1 and scores[0.0] < shipped - 0.3, (scores, shipped)


def test_adaptation_gains_on_a_camera_the_network_never_saw():
    """The held-out renderer (its own pixel integration, Poisson noise, 8 bits) is not the
    training's: there the adapted network is closer to the truth than the shipped one."""
    from hbis_torch.training.heldout_burst import BURST_CONDITIONS, make_burst

    frames, truth, bits = make_burst(BURST_CONDITIONS[0], "camera", 2, 40, seed=2000)
    stack, _ = assemble_burst(frames, 2, bit_depth=bits)
    adapted = psnr(reconstruct(stack, "learned"), truth)
    shipped = psnr(reconstruct(stack, "learned", adapt=False), truth)
    assert adapted > shipped + 0.3, (adapted, shipped)


def test_a_colour_burst_is_adapted_once_for_its_three_channels():
    motions = random_motions(8, (SIZE, SIZE), np.random.default_rng(4), 1.5)
    rgb = transform.resize(data.astronaut()[100:300, 150:350] / 255, (2 * SIZE, 2 * SIZE), anti_aliasing=True)
    frames = np.stack([simulate_burst(rgb[..., c], 2, motions, noise=0.005, seed=c).frames for c in range(3)], -1)
    stack, _ = assemble_burst(frames, 2)
    notes: list = []
    image = reconstruct(stack, "learned", messages=notes)
    assert image.shape == (2 * SIZE, 2 * SIZE, 3) and np.isfinite(image).all()
    assert sum("adapted to the burst's own frames" in n for n in notes) == 1, notes


def test_without_adaptation_or_weights_the_network_runs_as_shipped(tmp_path):
    stack, _ = _stack(size=24)
    shutil.copy(shipped_model_path(2), tmp_path / "mine.onnx")
    notes: list = []
    foreign = reconstruct(stack, "learned", model=str(tmp_path / "mine.onnx"), messages=notes)
    assert any("no PyTorch weights beside mine.onnx" in n for n in notes), notes
    plain_notes: list = []
    plain = reconstruct(stack, "learned", adapt=False, messages=plain_notes)
    np.testing.assert_array_equal(foreign, plain)
    assert not any("adapted" in n for n in plain_notes)
    assert not np.array_equal(reconstruct(stack, "learned"), plain)


def test_outside_the_noise_range_the_adapted_network_must_beat_the_classical_image(monkeypatch):
    """A burst noisier than the training's gets the network only where the adapted one predicts
    the left-out frames better than the classical image; else the classical image, said so."""
    stack, _ = _stack(size=24)
    stack.meta["sensor"] = {"full_well_e": 20.0}  # 16 % noise at mid-grey: outside the range
    real = adapt.adapt_refiner

    def worse(*args, **kw):
        result = real(*args, **kw)
        result.error_after = result.error_classical * 1.01
        return result

    monkeypatch.setattr(adapt, "adapt_refiner", worse)
    notes: list = []
    image = reconstruct(stack, "learned", messages=notes)
    assert any("outside the model's training range" in n and "did not predict the left-out frames better" in n
               for n in notes), notes
    np.testing.assert_allclose(image, reconstruct(stack, "classical"), atol=1e-6)


def test_the_command_line_turns_it_off(tmp_path, capsys):
    from hbis_torch.cli import main
    from hbis_torch.stack_io import write_stack

    stack, _ = _stack(size=24)
    path = tmp_path / "burst.tif"
    write_stack(path, stack)
    assert main(["-q", "reconstruct", str(path), "--method", "learned", "--no-adapt", "--out",
                 str(tmp_path / "plain.tif")]) == 0
    assert main(["-q", "validate", str(path), "--method", "classical,learned", "--no-adapt", "--holdout", "1"]) == 0
    capsys.readouterr()
    assert main(["-q", "reconstruct", str(path), "--method", "classical", "--no-adapt", "--out",
                 str(tmp_path / "c.tif")]) == 2
    assert "--no-adapt is only for --method learned" in capsys.readouterr().err
    assert not (tmp_path / "c.tif").exists()


def test_an_int8_request_is_told_that_the_adapted_network_runs_in_float32():
    stack, _ = _stack(size=24)
    notes: list = []
    reconstruct(stack, "learned", precision="int8", messages=notes)
    assert sum("runs in float32" in n for n in notes) == 1, notes
    notes.clear()
    reconstruct(stack, "learned", precision="int8", adapt=False, messages=notes)
    assert not any("float32" in n for n in notes), notes


def test_the_forward_model_in_float32_agrees_with_float64():
    rng = np.random.default_rng(0)
    output = torch.from_numpy(rng.random((1, 1, 40, 48)))
    points = torch.from_numpy(rng.uniform(1, 18, (500, 2)))
    predict = adapt._Predictor(2)
    wide, narrow = predict(output, points), predict(output.float(), points.float())
    assert wide.dtype == torch.float64 and narrow.dtype == torch.float32
    assert float((wide - narrow.double()).abs().max()) < 1e-6


@pytest.mark.parametrize("scale", [2, 3, 4])
def test_the_adaptation_predicts_as_validation_does(scale):
    # the adaptation fits the network to what hbis validate scores: one forward model for both
    # (at even S both once read the pixel's box half an HR pixel off its centre)
    from hbis_torch.observation.forward import predict_frame

    rng = np.random.default_rng(scale)
    output = torch.from_numpy(rng.random((1, 1, 20 * scale, 24 * scale)).astype(np.float32))
    points = torch.from_numpy(rng.uniform(2, 17, (300, 2)).astype(np.float32))
    ours = adapt._Predictor(scale)(output, points).double().numpy()
    theirs = predict_frame(output[0, 0].numpy(), points.double().numpy().reshape(-1, 1, 2), scale)[:, 0]
    np.testing.assert_allclose(ours, theirs, atol=1e-5)


def test_the_written_out_adam_takes_torchs_steps():
    torch.manual_seed(0)
    layers = [torch.nn.Conv2d(4, 3, 3) for _ in range(2)]
    layers[1].load_state_dict(layers[0].state_dict())
    ours, theirs = adapt.Adam(layers[0].parameters(), lr=1e-2), torch.optim.Adam(layers[1].parameters(), lr=1e-2)
    x = torch.randn(2, 4, 9, 9)
    start = layers[0].weight.detach().clone()
    for _ in range(5):
        for layer, optimiser in zip(layers, (ours, theirs)):
            optimiser.zero_grad()
            (layer(x) ** 3).mean().backward()
            optimiser.step()
    for a, b in zip(layers[0].parameters(), layers[1].parameters()):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6)
    assert float((layers[0].weight.detach() - start).abs().max()) > 1e-3  # it moved


def test_the_adaptation_stops_when_its_time_is_spent():
    stack, _ = _stack(size=24)
    frames, positions, _, weights = burst_samples(stack, corrected_frames(stack))
    net = adapt.load_refiner(shipped_model_path(2).with_suffix(".pt"))
    args = (net, frames, positions, weights, 2, (0.0, 1e-4), stack.reference_index, burst_sr)
    spent = adapt.adapt_refiner(*args, steps=10, budget_s=0.0, min_steps=0)
    assert spent.steps_taken == 0 and spent.step == 0 and spent.error_after == spent.error_before and spent.out_of_time
    assert all(torch.equal(a, b) for a, b in zip(spent.net.state_dict().values(), net.state_dict().values()))
    full = adapt.adapt_refiner(*args, steps=10, budget_s=60.0)
    assert full.steps_taken == 10 and 0 < full.seconds < 60


def test_the_first_steps_are_made_whatever_the_clock_says():
    # a machine busy with other work can spend the budget before the first step: the first
    # MIN_STEPS are made all the same, then the spent budget stops the rest
    stack, _ = _stack(size=24)
    frames, positions, _, weights = burst_samples(stack, corrected_frames(stack))
    net = adapt.load_refiner(shipped_model_path(2).with_suffix(".pt"))
    args = (net, frames, positions, weights, 2, (0.0, 1e-4), stack.reference_index, burst_sr)
    late = adapt.adapt_refiner(*args, steps=3 * adapt.MIN_STEPS, budget_s=0.0, patience=None)
    assert late.steps_taken == adapt.MIN_STEPS and late.out_of_time


def test_the_adaptation_stops_once_its_checks_stop_finding_better_weights(monkeypatch):
    stack, _ = _stack(size=24)
    frames, positions, _, weights = burst_samples(stack, corrected_frames(stack))
    net = adapt.load_refiner(shipped_model_path(2).with_suffix(".pt"))
    args = (net, frames, positions, weights, 2, (0.0, 1e-4), stack.reference_index, burst_sr)
    monkeypatch.setattr(adapt, "LEARNING_RATE", 1.0)  # steps that ruin the network: no check is better
    patient = adapt.adapt_refiner(*args, steps=40, patience=2)
    assert patient.step == 0 and patient.steps_taken == 2 * adapt.CHECK_EVERY and not patient.out_of_time
    assert adapt.adapt_refiner(*args, steps=40, patience=None).steps_taken == 40
    monkeypatch.setattr(adapt, "LEARNING_RATE", 1e-3)
    usual = adapt.adapt_refiner(*args, steps=40, patience=2)
    assert usual.steps_taken == 40 or usual.steps_taken - usual.step == 2 * adapt.CHECK_EVERY


def test_the_learned_method_gives_the_adaptation_a_budget_from_the_classical_time(monkeypatch):
    stack, _ = _stack(size=24)
    monkeypatch.setattr(adapt, "BUDGET_MIN_S", 0.0)
    monkeypatch.setattr(adapt, "BUDGET_X_CLASSICAL", 0.0)
    monkeypatch.setattr(adapt, "MIN_STEPS", 0)  # (the steps no budget stops: the test above)
    notes: list = []
    image = reconstruct(stack, "learned", messages=notes)
    assert any(f"(0 of {adapt.STEPS} steps" in n and "spent" in n for n in notes), notes
    np.testing.assert_allclose(image, reconstruct(stack, "learned", adapt=False), atol=1e-5)


def test_the_window_is_the_most_textured():
    frame = torch.zeros(300, 400)
    frame[200:290, 20:110] = torch.rand(90, 90, generator=torch.Generator().manual_seed(0))
    y, x, h, w = adapt.crop_box(frame, 128)
    assert (h, w) == (128, 128) and y <= 200 and y + h >= 290 and x <= 20 and x + w >= 110
    assert adapt.crop_box(frame[:50, :60], 128) == (0, 0, 50, 60)


def test_the_crop_keeps_only_the_samples_that_land_in_it():
    frames = torch.rand(2, 10, 12)
    positions = torch.stack(torch.meshgrid(torch.arange(10.0), torch.arange(12.0), indexing="ij")[::-1], -1)
    positions = torch.stack((positions, positions + torch.tensor([3.0, 0.0])))  # frame 1 moved 3 px right
    f, p, w = adapt.crop_samples(frames, positions.double(), torch.ones(2, 10, 12, dtype=torch.float64), (2, 4, 5, 6))
    assert f.shape == (2, 5, 6) and torch.equal(f, frames[:, 2:7, 4:10])
    assert torch.equal(p[0, 0, 0], torch.tensor([0.0, 0.0], dtype=torch.float64))
    assert bool((w[0] == 1).all()) and bool((w[1, :, :3] == 1).all()) and bool((w[1, :, 3:] == 0).all())


@pytest.mark.parametrize("motion", ["similarity", "homography"])
def test_on_a_held_out_hand_held_burst_learned_is_not_behind_classical(motion):
    """The hand-held matrix's renderer (never trained or tuned on), one small burst per motion."""
    from hbis_torch.training.handheld_render import render_burst

    burst = render_burst(motion, 2, 8, 128, 96, seed=7)
    stack, _ = assemble_burst(burst.frames, 2)
    border = (slice(8, -8), slice(8, -8))
    classical = psnr(reconstruct(stack, "classical")[border], burst.truth[border])
    learned = psnr(reconstruct(stack, "learned")[border], burst.truth[border])
    assert learned > classical + 0.1, (learned, classical)


def test_the_folds_undo_the_lens_the_classical_image_undoes(monkeypatch):
    stack, _ = _stack(size=24)
    seen = []
    real = adapt.adapt_refiner

    def spy(*args, **kw):
        seen.append(args[7].keywords["lens_sigma"])  # the classical step the folds are made with
        return real(*args, **kw)

    monkeypatch.setattr(adapt, "adapt_refiner", spy)
    reconstruct(stack, "learned", lens_sigma=0.4)
    reconstruct(stack, "learned")  # 'auto': the burst's own estimate, a number, and a new adaptation
    assert seen[0] == 0.4 and len(seen) == 2 and isinstance(seen[1], float)


def test_the_adaptation_is_handed_the_lens_estimates_doubt(monkeypatch):
    """The estimate's doubt reaches the adaptation where the lens is measured (here made sure by
    an estimate whose sharpest edges lie above FULL_TRUST), none where it is given (--psf-sigma),
    and the learned method says what its forward model blurred by."""
    from hbis_torch.reconstruct import lens_blur

    stack, _ = _stack(size=24)
    seen = []
    real_adapt, real_estimate = adapt.adapt_refiner, lens_blur.burst_lens_estimate

    def spy(*args, **kw):
        seen.append(kw["lens_doubt"])
        return real_adapt(*args, **kw)

    def soft(*args):
        return real_estimate(*args)._replace(sharpest=lens_blur.FULL_TRUST + lens_blur.DOUBT_RAMP, sigma=0.45)

    monkeypatch.setattr(adapt, "adapt_refiner", spy)
    monkeypatch.setattr(lens_blur, "burst_lens_estimate", soft)
    learned._last.clear()
    reconstruct(stack, "learned", lens_sigma=0.45)
    notes: list = []
    reconstruct(stack, "learned", messages=notes)
    learned._last.clear()
    assert seen == [0.0, 1.0], seen
    assert any("forward model blurred by 0.45 LR px" in n for n in notes), notes
