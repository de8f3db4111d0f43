"""The Wiener deblurring's wanted image: the scene averaged over each output pixel (the default,
the sensor h times finer) or the scene at the pixels' centres (``target_aperture=0``)."""

import numpy as np
import torch

from hbis_torch.capture.burst import assemble_burst
from hbis_torch.reconstruct.classical.wiener import wiener_deblur
from hbis_torch.reconstruct.registry import reconstruct
from hbis_torch.simulate.burst import random_motions, simulate_burst
from hbis_torch.training.burst_data import truth_raster


def test_the_default_target_is_the_sensor_s_own_pixel_area():
    image = torch.rand((48, 64), generator=torch.Generator().manual_seed(0))
    args = dict(h=2, offset=(0.1, -0.2), kernel_sigma=0.45, noise=0.01, aperture=0.9, lens_sigma=0.3)
    assert torch.equal(wiener_deblur(image, **args), wiener_deblur(image, target_aperture=0.9, **args))


def test_the_pixels_centres_are_a_sharper_target():
    # the same data: aiming at the scene without the output pixel's box keeps more of the fine detail
    image = torch.rand((64, 64), generator=torch.Generator().manual_seed(1))
    args = dict(h=2, offset=(0.0, 0.0), kernel_sigma=0.45, noise=0.002)

    def fine_energy(out):
        spectrum = torch.fft.rfft2(out - out.mean()).abs() ** 2
        return float(spectrum[16:48, 16:].sum() / spectrum.sum())

    assert fine_energy(wiener_deblur(image, target_aperture=0.0, **args)) > 1.05 * fine_energy(
        wiener_deblur(image, **args))


def test_a_truth_sampled_at_the_pixels_is_nearer_with_that_target():
    # the training simulator's frames integrate a box of S x S of the truth's pixels, each read as
    # the scene's value there: the truth is the scene at the output pixels, not averaged over them
    rng = np.random.default_rng(3)
    truth = truth_raster("dead-leaves", 2, 128, 13, 0.8)
    motions = random_motions(16, (128, 128), rng, max_shift=2.0, max_rotation_deg=0.3)
    burst = simulate_burst(truth, 2, motions, noise=0.005, seed=3, blur_px=0.3)
    stack, _ = assemble_burst(burst.frames, 2)

    def error(image) -> float:
        inner = (slice(16, -16), slice(16, -16))
        return float(np.sqrt(np.mean((np.asarray(image)[inner] - np.asarray(burst.truth)[inner]) ** 2)))

    point = error(reconstruct(stack, "classical", target_aperture=0.0))
    area = error(reconstruct(stack, "classical"))
    assert point < 0.97 * area, (point, area)
