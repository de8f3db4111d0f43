"""hbis_torch.training.independent_render: a second forward model that agrees with the simulator where
both are exact, and draws the sensor's noise."""

import dataclasses

import numpy as np
import pytest

from hbis_torch.config import FoveaSystem
from hbis_torch.metrics import psnr
from hbis_torch.scan import plan_scan
from hbis_torch.simulate import SensorModel, simulate_stack
from hbis_torch.simulate.stacks import scene_for_roi
from hbis_torch.training import independent_render


@pytest.fixture(scope="module")
def ir():
    return independent_render


def simulated(h, size, f_number, sensor, corner=False):
    base = FoveaSystem()
    system = dataclasses.replace(base, camera=dataclasses.replace(base.camera, f_number=f_number))
    cam = system.camera
    roi = (8, 8, size, size) if corner else ((cam.cols - size) // 2, (cam.rows - size) // 2, size, size)
    scene = scene_for_roi("camera", system, roi, h)
    stack, truth = simulate_stack(scene, system, plan_scan(system, h), roi=roi, sensor=sensor, seed=1)
    return stack, truth, scene


@pytest.mark.parametrize("h, f_number, corner", [(2, 1.4, False), (3, 2.8, True)])
def test_both_forward_models_agree_without_noise(ir, h, f_number, corner):
    """Two independent renderings of one scan of a photograph: every frame and the truth agree to
    better than 44 dB (the noise of a 10,000 e- sensor is at 40 dB), at the centre and a corner."""
    clean = SensorModel(noise=False, bit_depth=None)
    stack, truth, scene = simulated(h, 20, f_number, clean, corner)
    frames, truth2 = ir.render_like(stack, scene, clean, seed=0)
    assert frames.shape == stack.frames.shape and truth2.shape == truth.shape
    b = 2
    assert psnr(stack.to_float().numpy()[:, b:-b, b:-b], frames[:, b:-b, b:-b]) > 44
    assert psnr(truth[b * h:-b * h, b * h:-b * h], truth2[b * h:-b * h, b * h:-b * h]) > 44
    # and a scene placed elsewhere does not: the agreement is not trivial
    shifted = dict(stack.meta["simulation"], scene_center_mm=[c + 0.01 for c in stack.meta["simulation"]["scene_center_mm"]])
    moved = type(stack)(stack.frames, dict(stack.meta, simulation=shifted))
    frames_moved, _ = ir.render_like(moved, scene, clean, seed=0)
    assert psnr(stack.to_float().numpy()[:, b:-b, b:-b], frames_moved[:, b:-b, b:-b]) < 35


def test_noise_is_the_sensors(ir):
    """Frames minus their noise-free rendering have the Poisson-Gaussian variance a x + b of the
    sensor (full well, read noise, quantisation), and the frames are stored as the sensor does."""
    sensor = SensorModel(full_well_e=5_000, read_noise_e=6.0, bit_depth=12)
    stack, _, scene = simulated(2, 24, 1.4, sensor)
    frames, _ = ir.render_like(stack, scene, sensor, seed=3)
    clean, _ = ir.render_like(stack, scene, SensorModel(noise=False, bit_depth=None), seed=3)
    assert frames.dtype == np.uint16 and frames.max() <= 4095
    x = frames.astype(np.float64) / 4095
    expected = clean / 5_000 + (6.0 / 5_000) ** 2 + 1 / 12 / 4095 ** 2
    ratio = ((x - clean) ** 2).mean() / expected.mean()
    assert 0.9 < ratio < 1.1
    again, _ = ir.render_like(stack, scene, sensor, seed=3)
    assert np.array_equal(frames, again)  # seeded
