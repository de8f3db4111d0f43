"""The Wiener filter's prior fit (hbis_torch.reconstruct.classical.wiener.fit_spectrum) on a burst's
lattice: power that repeats with the LR lattice (the errors of nodes filled where the samples leave
sub-pixel phases empty) must not set the scene's slope."""

import math
from functools import partial

import numpy as np
import torch

from hbis_torch.reconstruct.classical import wiener
from hbis_torch.reconstruct.classical.wiener import _alias_kernel, fit_spectrum

SHIFTS = [(kx, ky) for ky in (-1, 0, 1) for kx in (-1, 0, 1)]


def _spectrum(h: int, beta: float, s2: float, noise2: float, lens_sigma: float, side: int = 384,
              lr_power: float = 0.0):
    """A lattice's expected power on the half spectrum of a side x side image at h: the model
    s2 sum_k abs(K(f + k))^2 / abs(f + k)^beta + noise2 of :func:`fit_spectrum`, plus
    ``lr_power`` in a ring about one cycle per LR px (1 / h cycles per HR px, 0.04 wide), as
    the filled nodes' errors of a lattice with whole sub-pixel phases empty put there; and the
    kernel (fx, fy, kernel)."""
    fy = torch.fft.fftfreq(side, dtype=torch.float64)[:, None]
    fx = torch.fft.rfftfreq(side, dtype=torch.float64)[None, :]
    eps2 = (0.5 / side) ** 2
    kernel = partial(_alias_kernel, fx, fy, h, 1.0, None, (0.0, 0.0), eps2, lens_sigma=lens_sigma)
    power = torch.full((side, side // 2 + 1), noise2, dtype=torch.float64)
    for kx, ky in SHIFTS:
        k_mag, _, _, r2 = kernel(kx, ky)
        power += s2 * k_mag * k_mag * r2 ** (-beta / 2)
    radius = torch.sqrt(fx * fx + fy * fy)
    power += lr_power * torch.exp(-0.5 * ((radius - 1 / h) / 0.02) ** 2)
    return power, fx, fy, kernel


def test_the_fit_below_one_cycle_per_lr_pixel_keeps_the_scenes_slope():
    h, beta, s2, noise2, lens = 3, 2.75, 1e-4, 4e-5, 0.3
    power, fx, fy, kernel = _spectrum(h, beta, s2, noise2, lens, lr_power=20 * noise2)
    clean, *_ = _spectrum(h, beta, s2, noise2, lens)
    # without the LR lattice's power every fit finds the scene's slope
    assert fit_spectrum(clean, fx, fy, kernel, SHIFTS, noise2)[1] == beta
    assert fit_spectrum(clean, fx, fy, kernel, SHIFTS, noise2, highest=1 / h)[1] == beta
    # with it, the fit over every ring takes it for scene detail (a flatter slope: the filter
    # would sharpen the errors) ...
    assert fit_spectrum(power, fx, fy, kernel, SHIFTS, noise2)[1] < beta
    # ... and the fit below one cycle per LR px does not
    level, slope = fit_spectrum(power, fx, fy, kernel, SHIFTS, noise2, highest=1 / h)
    assert slope == beta and abs(math.log(level / s2)) < 0.1


def test_a_bursts_lattice_fits_its_prior_below_one_cycle_per_lr_pixel(monkeypatch):
    from hbis_torch.reconstruct.classical import classical_sr
    from hbis_torch.reconstruct.classical.burst import burst_sr

    seen = []
    fit = wiener.fit_spectrum

    def recording(*args, highest=None):
        seen.append(highest)
        return fit(*args, highest=highest)

    monkeypatch.setattr(wiener, "fit_spectrum", recording)
    rng = np.random.default_rng(0)
    frames = torch.from_numpy(rng.random((4, 24, 24)).astype(np.float32))
    v, u = np.mgrid[0:24, 0:24].astype(np.float64)
    shifts = rng.uniform(-1, 1, (4, 2))
    shifts[0] = 0
    positions = torch.from_numpy(np.stack([np.stack((u + dx, v + dy), -1) for dx, dy in shifts]))
    weights = torch.ones((4, 24, 24), dtype=torch.float64)
    burst_sr(frames, positions, 3, weights)
    classical_sr(frames.double(), positions, 3)  # a scan's lattice: every ring
    assert seen == [1 / 3, None]


def test_the_development_harness_reproduces_the_committed_fit(load_script):
    """training/dev_wiener_fit.py refits the prior on fit_spectrum's own rings (a copy of their
    set-up): its 0.25-step least-scatter variant must give fit_spectrum's answer, with and without
    the LR lattice's power and the cut at 1 / h, or its development matrix compares against
    something the package does not do."""
    dev = load_script("training/dev_wiener_fit.py")
    h, noise2, lens = 3, 4e-5, 0.3
    for beta, lr_power, highest in ((2.75, 20 * noise2, None), (2.75, 20 * noise2, 1 / h), (2.25, 0.0, None)):
        power, fx, fy, kernel = _spectrum(h, beta, 1e-4, noise2, lens, lr_power=lr_power)
        committed = fit_spectrum(power, fx, fy, kernel, SHIFTS, noise2, highest=highest)
        harness = dev.variant_fit(dev.VARIANTS["grid25"])(power, fx, fy, kernel, SHIFTS, noise2, highest=highest)
        assert harness[1] == committed[1] and math.isclose(harness[0], committed[0], rel_tol=1e-9)
    # and its finer grid finds a slope between the coarse grid's steps
    power, fx, fy, kernel = _spectrum(h, 2.6, 1e-4, noise2, lens)
    assert fit_spectrum(power, fx, fy, kernel, SHIFTS, noise2)[1] in (2.5, 2.75)
    assert dev.variant_fit(dev.VARIANTS["grid05"])(power, fx, fy, kernel, SHIFTS, noise2)[1] == 2.6
