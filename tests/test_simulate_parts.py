"""PSF, sensor noise and geometry of the simulator, each on its own."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from hbis_torch.config import Camera, FoveaSystem
from hbis_torch.errors import HbisInputError
from hbis_torch.optics import landing_at, landing_map, landing_on_grid, sensor_position
from hbis_torch.scan import plan_scan
from hbis_torch.simulate import SensorModel, airy_otf, airy_psf, expose, lens_otf, sample_positions
from hbis_torch.simulate.psf import blur_transfer, defocus_waves
from hbis_torch.simulate.sensor import normalise

SYSTEM = FoveaSystem()


# ----------------------------------------------------------------------------------- PSF


def test_airy_psf_first_zero_and_unit_integral():
    lam_f = 0.55 * 1.4  # um
    r = np.linspace(0, 200 * lam_f, 400001)
    psf = airy_psf(r, 1.4, 550)
    energy = np.trapezoid(psf * 2 * np.pi * r, r)
    assert energy == pytest.approx(1.0, abs=2e-3)  # the rest lies beyond 200 lambda F
    first_zero = r[np.argmax(np.diff(psf) > 0)]  # first minimum
    assert first_zero == pytest.approx(1.22 * lam_f, rel=2e-3)
    assert first_zero == pytest.approx(0.9394, abs=1e-3)  # Table 1: F = 1.4, 550 nm


def test_airy_otf_is_the_fourier_transform_of_the_airy_psf():
    """Sample the PSF finely, FFT it, compare with the closed-form pupil autocorrelation."""
    lam_f = 0.55 * 1.4
    n, step = 1024, lam_f / 8
    c = (np.arange(n) - n // 2) * step
    psf = airy_psf(np.hypot(c[None, :], c[:, None]), 1.4, 550) * step**2
    otf = np.abs(np.fft.fft2(np.fft.ifftshift(psf)))[0, : n // 2]
    freq = np.fft.fftfreq(n, d=step)[: n // 2]
    expected = lens_otf(freq, 1.4, 550)
    assert np.abs(otf - expected).max() < 0.01  # the window truncates the PSF's tails
    assert np.all(expected[freq * lam_f >= 1] == 0) and expected[0] == 1.0


def test_defocus_otf():
    nu = np.linspace(0, 1, 200)
    freq = nu / (0.55 * 1.4)
    focused = lens_otf(freq, 1.4, 550, 0.0)
    # the numerical pupil autocorrelation reproduces the closed form when in focus
    from hbis_torch.simulate.psf import _defocus_otf_table

    table_nu, table = _defocus_otf_table(0.0)
    assert np.abs(table - airy_otf(table_nu)).max() < 0.01
    blurred = lens_otf(freq, 1.4, 550, 1.0)  # one wave of defocus
    assert blurred[0] == pytest.approx(1.0)
    assert np.all(blurred <= focused + 1e-9)  # defocus never raises the MTF
    assert blurred.min() < -0.05  # and reverses contrast somewhere (a known feature)
    assert defocus_waves(4.0, 1.4, 550) == pytest.approx(4.0 / (8 * 1.96 * 0.55))


def test_blur_transfer_is_one_at_dc_and_sinc_at_the_pixel_frequency():
    t = blur_transfer((64, 64), 0.125, 3.75, 1.4, 550, 1.0).numpy()
    assert t[0, 0] == pytest.approx(1.0)
    # DCT frequency k / (2 N step) = 1 cycle/pixel at k = 16: the unit box's sinc is zero there
    assert t[0, 16] == pytest.approx(0.0, abs=1e-7)
    with pytest.raises(HbisInputError):
        blur_transfer((8, 8), 0.1, 3.75, 1.4, 550, 0.0)


# -------------------------------------------------------------------------------- sensor


@pytest.mark.parametrize(
    "level,full_well,read,black,bits",
    [(0.5, 10000, 2.0, 0, 12), (0.1, 2000, 8.0, 64, 12), (0.8, 30000, 3.0, 16, 10), (0.3, 500, 1.0, 8, 8)],
)
def test_noise_mean_and_variance_match_the_model(level, full_well, read, black, bits):
    sensor = SensorModel(full_well_e=full_well, read_noise_e=read, black_level_dn=black, bit_depth=bits)
    n = 400_000
    frames = expose(torch.full((n,), level), sensor, torch.Generator().manual_seed(1))
    assert frames.dtype == (np.uint8 if bits <= 8 else np.uint16)
    dn = frames.astype(np.float64)
    gain = (2**bits - 1 - black) / full_well
    mean = black + level * full_well * gain
    variance = gain**2 * (level * full_well + read**2) + 1 / 12
    assert dn.mean() == pytest.approx(mean, abs=4 * math.sqrt(variance / n))
    # sample variance of n draws has relative standard error sqrt(2 / n) = 0.2 %
    assert dn.var() == pytest.approx(variance, rel=0.015)
    # to_float inverts the mapping on average
    assert float(normalise(frames, sensor).double().mean()) == pytest.approx(level, abs=2e-3)


def test_noise_is_poisson_at_low_light_and_deterministic_per_seed():
    sensor = SensorModel(full_well_e=100, read_noise_e=0.0, bit_depth=16)
    x = torch.full((200_000,), 0.03)  # 3 electrons
    a = expose(x, sensor, torch.Generator().manual_seed(3))
    b = expose(x, sensor, torch.Generator().manual_seed(3))
    assert np.array_equal(a, b)
    electrons = a / sensor.gain_dn_per_e
    counts = np.bincount(np.round(electrons).astype(int))[:6] / len(electrons)
    poisson = np.array([math.exp(-3) * 3**k / math.factorial(k) for k in range(6)])
    assert np.abs(counts - poisson).max() < 0.005


def test_noise_free_and_float_output():
    x = torch.tensor([0.0, 0.25, 1.0, 1.2])
    quiet = expose(x, SensorModel(noise=False, bit_depth=12))
    assert quiet.tolist() == [0, round(0.25 * 4095), 4095, 4095]
    floats = expose(x, SensorModel(noise=False, bit_depth=None))
    assert floats.dtype == np.float32 and floats.tolist() == [0.0, 0.25, 1.0, 1.0]
    noisy = expose(torch.full((1000,), 0.999), SensorModel(bit_depth=None, full_well_e=100))
    assert noisy.max() <= 1.0 and noisy.min() >= 0.0
    with pytest.raises(HbisInputError, match="NaN"):
        expose(torch.tensor([float("nan")]), SensorModel())


@pytest.mark.parametrize(
    "kwargs,message",
    [
        ({"fill_factor": 0.0}, "fill factor"),
        ({"fill_factor": 1.5}, "fill factor"),
        ({"full_well_e": -1}, "full well"),
        ({"read_noise_e": float("nan")}, "read noise"),
        ({"bit_depth": 17}, "bit depth"),
        ({"bit_depth": 8, "black_level_dn": 255}, "black level"),
    ],
)
def test_sensor_model_rejects_bad_values(kwargs, message):
    with pytest.raises(HbisInputError, match=message):
        SensorModel(**kwargs)


# ------------------------------------------------------------------------------ geometry


def test_sample_positions_interpolated_match_the_contract_definition():
    """Spline-interpolated positions agree with sensor_position(landing_map(...)) - (u0, v0)."""
    plan = plan_scan(SYSTEM, 3)
    for roi in [(0, 0, 70, 50), (1180, 880, 100, 80)]:
        fast = sample_positions(SYSTEM, plan.phases_deg, plan.reference_index, roi)
        exact = sample_positions(SYSTEM, plan.phases_deg, plan.reference_index, roi, exact=True)
        ref = plan.phases_deg[plan.reference_index]
        by_hand = sensor_position(
            SYSTEM, landing_map(SYSTEM, plan.phases_deg[:, 0], plan.phases_deg[:, 1], roi), ref[0], ref[1]
        ) - torch.tensor(roi[:2], dtype=torch.float64)
        assert float((exact - by_hand).abs().max()) < 1e-9
        assert float((fast - exact).abs().max()) < 1e-6
        grid = torch.stack(torch.meshgrid(torch.arange(roi[2]), torch.arange(roi[3]), indexing="xy"), -1)
        assert float((exact[plan.reference_index] - grid).abs().max()) < 1e-9


def test_landing_on_grid_matches_exact_trace():
    u = 1000.0 + np.arange(300) / 8
    v = 20.0 + np.arange(200) / 8
    fast = landing_on_grid(SYSTEM, u, v, 5.0, 70.0)
    exact = landing_at(SYSTEM, torch.from_numpy(u)[None, :], torch.from_numpy(v)[:, None], 5.0, 70.0)
    assert float((fast - exact).abs().max()) / SYSTEM.object_pixel_mm < 1e-7
    rel = landing_on_grid(SYSTEM, u, v, 5.0, 70.0, origin_mm=(6.0, -3.0), dtype=torch.float32)
    back = rel.double() + torch.tensor([6.0, -3.0], dtype=torch.float64)
    assert float((back - exact).abs().max()) / SYSTEM.object_pixel_mm < 1e-4


def test_small_camera_geometry():
    system = FoveaSystem(camera=Camera(rows=40, cols=60))
    pos = sample_positions(system, [[5.0, 70.0], [5.2, 70.1]], 0, None)
    assert pos.shape == (2, 40, 60, 2)
    with pytest.raises(HbisInputError, match="reference index"):
        sample_positions(system, [[5.0, 70.0]], 1, None)
    with pytest.raises(HbisInputError, match=r"shape \(F, 2\)"):
        sample_positions(system, [[5.0, 70.0, 1.0]], 0, None)
