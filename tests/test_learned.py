"""Learned SR inputs: the noise model (from the metadata or measured), the network's inputs, tiling."""

import numpy as np
import pytest
import torch

from hbis_torch.errors import HbisInputError
from hbis_torch.reconstruct.learned import (
    NOISE_SCALE,
    estimate_noise_params,
    network_inputs,
    noise_params_from_meta,
    run_tiled,
    super_resolve,
)
from hbis_torch.reconstruct.learned.inputs import space_to_depth
from hbis_torch.training.net import HbisSRNet
from hbis_torch.training.net import space_to_depth as torch_space_to_depth


def test_noise_params_come_from_the_sensor_model_with_the_adc_rounding():
    meta = {"bit_depth": 12, "simulation": {"sensor": {"full_well_e": 20000.0, "read_noise_e": 4.0}}}
    a, b = noise_params_from_meta(meta)
    assert a == pytest.approx(1 / 20000)
    assert b == pytest.approx((4 / 20000) ** 2 + 1 / (12 * 4095**2))
    # A captured stack's own sensor block wins over nothing; no sensor model gives None.
    assert noise_params_from_meta({"sensor": {"full_well_e": 1000}})[0] == pytest.approx(1e-3)
    assert noise_params_from_meta({"bit_depth": 12}) is None


@pytest.mark.parametrize("bad", [0.0, -5.0, float("nan"), "10000", True])
def test_a_sensor_model_with_a_bad_full_well_is_refused(bad):
    with pytest.raises(HbisInputError, match="full_well_e"):
        noise_params_from_meta({"sensor": {"full_well_e": bad}})


@pytest.mark.parametrize("a, b", [(1e-3, 1e-5), (1e-4, 4e-6), (0.0, 1e-4)])
def test_measured_noise_params_find_shot_and_read_noise(a, b):
    """Poisson-Gaussian noise on a smooth ramp: the measured level is within 20 % at every level."""
    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[0:96, 0:96] / 95.0
    clean = 0.05 + 0.9 * (0.5 * xx + 0.5 * yy)
    frames = clean + rng.standard_normal((4, 96, 96)) * np.sqrt(a * clean + b)
    ea, eb = estimate_noise_params(frames.astype(np.float32))
    for level in (0.1, 0.5, 0.9):
        assert np.sqrt(ea * level + eb) == pytest.approx(np.sqrt(a * level + b), rel=0.2)


def test_measured_noise_of_a_noise_free_stack_is_near_zero():
    yy, xx = np.mgrid[0:64, 0:64] / 63.0
    frames = np.broadcast_to(0.2 + 0.6 * xx * yy, (4, 64, 64)).astype(np.float32)
    a, b = estimate_noise_params(frames)
    assert np.sqrt(a + b) < 1e-3


def test_space_to_depth_is_the_networks_own():
    image = np.random.default_rng(1).random((12, 20)).astype(np.float32)
    want = torch_space_to_depth(torch.from_numpy(image)[None, None], 4)[0].numpy()
    np.testing.assert_array_equal(space_to_depth(image, 4), want)


def test_network_inputs_hold_the_image_and_the_noise_level_per_lr_pixel():
    h = 2
    image = np.zeros((8, 6), np.float32)
    image[:4] = 0.64  # top two LR rows bright
    base, noise = network_inputs(image, h, (1e-3, 1e-4))
    assert base.shape == (4, 4, 3) and noise.shape == (1, 4, 3)
    np.testing.assert_allclose(noise[0, :2], NOISE_SCALE * np.sqrt(1e-3 * 0.64 + 1e-4), rtol=1e-6)
    np.testing.assert_allclose(noise[0, 2:], NOISE_SCALE * np.sqrt(1e-4), rtol=1e-6)


@pytest.mark.parametrize("image, params", [(np.zeros((7, 8)), (0, 0)), (np.zeros((8, 8, 1)), (0, 0)),
                                           (np.zeros((8, 8)), (-1e-3, 0)), (np.zeros((8, 8)), (np.nan, 0))])
def test_bad_images_or_noise_params_are_refused(image, params):
    with pytest.raises(HbisInputError):
        network_inputs(image, 2, params)


def test_tiled_inference_equals_one_pass():
    """A halo wider than the receptive field makes the tiles' seams invisible."""
    torch.manual_seed(0)
    net = HbisSRNet(3).eval()
    for p in net.tail.parameters():  # an untrained tail is zero: give it something to show
        torch.nn.init.normal_(p, std=0.05)
    rng = np.random.default_rng(2)
    base, noise = network_inputs(rng.random((3 * 40, 3 * 37)).astype(np.float32), 3, (1e-3, 1e-5))

    def infer(b, n):
        with torch.no_grad():
            return net(torch.from_numpy(b), torch.from_numpy(n)).numpy()

    whole = run_tiled(infer, base, noise, 3, tile=64)
    tiled = run_tiled(infer, base, noise, 3, tile=16)
    np.testing.assert_allclose(tiled, whole, atol=1e-5)


def test_an_untrained_network_returns_the_classical_image():
    net = HbisSRNet(4).eval()
    image = np.random.default_rng(3).random((32, 24)).astype(np.float32)

    def run(b, n):
        with torch.no_grad():
            return net(torch.from_numpy(b)[None], torch.from_numpy(n)[None]).numpy()[0, 0]

    np.testing.assert_allclose(super_resolve(run, image, 4, (1e-3, 1e-5)), image, atol=1e-6)


def test_non_finite_network_output_is_named():
    with pytest.raises(HbisInputError, match="non-finite"):
        super_resolve(lambda b, n: np.full((8, 8), np.nan, np.float32), np.zeros((8, 8)), 2, (0, 0), "m.onnx")


def test_band_limit_removes_only_what_lies_beyond_the_lens_cutoff():
    from hbis_torch.reconstruct.learned.inputs import band_limit

    h, n = 4, 128
    x = np.arange(n)
    yy, xx = np.meshgrid(x, x, indexing="ij")
    low = np.cos(2 * np.pi * 8 / n * xx)  # 8 cycles over 32 LR px: 0.25 cycles per LR pixel
    high = np.cos(2 * np.pi * 48 / n * yy)  # 1.5 cycles per LR pixel
    correction = (low + high).astype(np.float32)
    limited = band_limit(correction, h, cutoff=0.62)  # F 11 at 3.75 um, 550 nm
    np.testing.assert_allclose(limited, low, atol=1e-5)
    # a lens that passes everything the output grid holds changes nothing
    assert band_limit(correction, h, cutoff=4.9) is correction
    assert band_limit(correction, h, cutoff=None) is correction


def test_band_limit_in_float32_bands_matches_a_float64_whole_transform():
    from hbis_torch.reconstruct.learned.inputs import band_limit

    h, cutoff = 7, 2.0
    correction = np.random.default_rng(5).normal(0, 0.01, (601, 133)).astype(np.float32)  # bands of 256 rows
    fy = np.fft.fftfreq(601)[:, None] * h
    fx = np.fft.rfftfreq(133)[None, :] * h
    t = np.clip((np.hypot(fx, fy) / cutoff - 0.85) / 0.15, 0.0, 1.0)
    expected = np.fft.irfft2(np.fft.rfft2(correction.astype(np.float64)) * (0.5 + 0.5 * np.cos(np.pi * t)), s=(601, 133))
    result = band_limit(correction, h, cutoff)
    assert result is correction  # in place
    np.testing.assert_allclose(result, expected, atol=3e-8)  # float32 is plenty next to corrections of 1e-2
