"""The deblurring's lens spread: the Wiener filter is the MMSE one over a lens blur whose variance
is known to a share (``transfer.LENS_SPREAD``), so a lens undone too large over-sharpens less."""

import math

import numpy as np
import pytest
import torch

import hbis_torch.reconstruct.classical.transfer as transfer
from hbis_torch.capture.burst import assemble_burst
from hbis_torch.reconstruct.registry import reconstruct
from hbis_torch.simulate.burst import random_motions, simulate_burst
from hbis_torch.training.burst_data import truth_raster


@pytest.mark.parametrize("spread", [0.0, 0.3, 0.6, 0.9])
def test_the_lens_transfer_s_moments_are_the_mean_over_the_spread(spread):
    r2 = torch.tensor([0.0, 1e-6, 0.01, 0.1, 0.5, 2.0], dtype=torch.float64)
    sigma = 0.8
    mean, square = transfer.lens_transfer(r2, sigma, spread)
    # sigma^2 uniform over (1 -+ spread) sigma^2: the midpoint rule on a fine grid
    t = (torch.arange(20000, dtype=torch.float64) + 0.5) / 20000
    variance = sigma**2 * (1 - spread + 2 * spread * t)
    g = torch.exp(-2 * math.pi**2 * variance[:, None] * r2[None, :])
    torch.testing.assert_close(mean, g.mean(0), rtol=1e-6, atol=1e-12)
    torch.testing.assert_close(square, (g * g).mean(0), rtol=1e-6, atol=1e-12)


def test_the_lens_transfer_in_float32_is_float64_s():
    r2 = torch.linspace(0, 3, 101, dtype=torch.float64)
    for got, want in zip(transfer.lens_transfer(r2.float(), 0.6, 0.5), transfer.lens_transfer(r2, 0.6, 0.5)):
        assert got.dtype == torch.float32
        torch.testing.assert_close(got.double(), want, rtol=2e-6, atol=1e-9)


@pytest.fixture(scope="module")
def burst():
    """A burst with a lens of 0.3 LR px (its stack, the truth)."""
    rng = np.random.default_rng(5)
    truth = truth_raster("dead-leaves", 2, 96, 5, 0.8)
    motions = random_motions(8, (96, 96), rng, max_shift=2.0, max_rotation_deg=0.2)
    simulated = simulate_burst(truth, 2, motions, noise=0.003, seed=5, blur_px=0.3)
    stack, _ = assemble_burst(simulated.frames, 2)
    return stack, np.asarray(simulated.truth)


def _error(image, truth) -> float:
    inner = (slice(16, -16), slice(16, -16))
    return float(np.sqrt(np.mean((np.asarray(image)[inner] - truth[inner]) ** 2)))


@pytest.mark.parametrize("lens, most", [
    (0.5, 0.95),  # undone too large (the truth is 0.3): the spread keeps it from over-sharpening
    (0.3, 1.02),  # the truth: the spread costs little
])
def test_the_spread_over_sharpens_less_and_costs_little_at_the_truth(monkeypatch, burst, lens, most):
    stack, truth = burst
    with_spread = _error(reconstruct(stack, "classical", lens_sigma=lens), truth)
    monkeypatch.setattr(transfer, "LENS_SPREAD", 0.0)
    without = _error(reconstruct(stack, "classical", lens_sigma=lens), truth)
    assert with_spread < most * without, (with_spread, without)
