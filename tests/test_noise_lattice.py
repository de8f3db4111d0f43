"""The frames' noise measured on the classical step's lattice (``lattice_noise_params``), and the
learned method's inputs from a stack that does not record its sensor (``classical_and_noise``)."""

import json

import numpy as np
import pytest

from hbis_torch.config import FoveaSystem
from hbis_torch.reconstruct.classical import optics_cutoff, reconstruct_classical
from hbis_torch.reconstruct.learned import LearnedSR, estimate_noise_params, learned_sr, noise_params_from_meta
from hbis_torch.reconstruct.learned.domain import noise_at_mid_grey
from hbis_torch.reconstruct.learned.method import classical_and_noise
from hbis_torch.sensor.noise import fit_noise_params
from hbis_torch.scan import plan_scan
from hbis_torch.simulate import SensorModel, simulate_stack
from hbis_torch.simulate.stacks import scene_for_roi
from hbis_torch.stack_io import Stack

SYSTEM = FoveaSystem()


def photograph_stack(h: int, full_well: float, size: int = 48):
    """A photograph's stack at the sensor's centre (12 bit, 2 e- read noise), its sensor model
    recorded; and the same stack without it, as a camera's assembled stack comes."""
    cam = SYSTEM.camera
    roi = ((cam.cols - size) // 2, (cam.rows - size) // 2, size, size)
    sensor = SensorModel(full_well_e=full_well, read_noise_e=2.0, bit_depth=12)
    stack, _ = simulate_stack(scene_for_roi("astronaut", SYSTEM, roi, h), SYSTEM, plan_scan(SYSTEM, h),
                              roi=roi, sensor=sensor, seed=5)
    meta = json.loads(json.dumps(stack.meta))
    for key in ("full_well_e", "read_noise_e"):
        meta["simulation"]["sensor"].pop(key)
    return stack, Stack(stack.frames, meta).validate("test stack")


def test_the_lattice_measures_a_photographs_low_noise_where_a_single_frame_overstates_it():
    stack, _ = photograph_stack(h=4, full_well=50_000)
    truth = noise_at_mid_grey(noise_params_from_meta(stack.meta))
    measured = []
    reconstruct_classical(stack, "optics", noise_params_out=measured)
    assert noise_at_mid_grey(measured[0]) == pytest.approx(truth, rel=0.15)
    assert noise_at_mid_grey(estimate_noise_params(stack.to_float().numpy())) > 2 * truth  # the aliased detail


def test_the_learned_methods_noise_is_the_sensors_else_the_lattices():
    stack, bare = photograph_stack(h=2, full_well=10_000, size=32)
    image, params = classical_and_noise(stack)
    assert params == noise_params_from_meta(stack.meta)
    np.testing.assert_array_equal(image, reconstruct_classical(stack, "optics"))
    image, params = classical_and_noise(bare)
    measured = []
    np.testing.assert_array_equal(image, reconstruct_classical(bare, "optics", noise_params_out=measured))
    assert params == measured[0]
    truth = noise_at_mid_grey(noise_params_from_meta(stack.meta))  # h = 2: a coarser lattice, still nearer
    frames = noise_at_mid_grey(estimate_noise_params(bare.to_float().numpy()))
    assert truth < noise_at_mid_grey(params) < frames
    runner = LearnedSR(h=2, threads=1, provider="cpu")
    np.testing.assert_array_equal(learned_sr(bare, threads=1, provider="cpu"),
                                  runner(image, params, optics_cutoff(bare.system)))


def test_the_noise_fit_with_too_few_values_for_any_bin_is_one_level():
    residual = np.abs(np.random.default_rng(0).standard_normal(30)) * 6 * 0.01
    a, b = fit_noise_params(residual, np.linspace(0, 1, 30), 6.0)
    assert a == 0 and np.sqrt(b) == pytest.approx(0.01, rel=0.5)
    with pytest.raises(ValueError, match="no pixels"):
        fit_noise_params(residual, np.linspace(0, 1, 30), 6.0, where=np.zeros(30, bool))


def test_a_stack_too_small_to_measure_its_noise_on_is_refused_before_any_work(monkeypatch):
    import importlib

    from hbis_torch.errors import HbisInputError

    _, bare = photograph_stack(h=2, full_well=10_000, size=1)  # a 2 x 2 lattice
    method = importlib.import_module("hbis_torch.reconstruct.learned.method")
    monkeypatch.setattr(method, "reconstruct_classical", lambda *a, **k: pytest.fail("work was done"))
    with pytest.raises(HbisInputError, match="too small to measure its noise"):
        learned_sr(bare)
