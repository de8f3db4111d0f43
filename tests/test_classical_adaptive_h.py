"""Scene-adaptive h: the predicted gains behave physically, and the choice follows the scene."""

from functools import lru_cache

import numpy as np
import pytest
import torch

from hbis_torch.config import FoveaSystem
from hbis_torch.errors import HbisInputError
from hbis_torch.scan import plan_scan
from hbis_torch.simulate import SensorModel, simulate_stack
from hbis_torch.simulate.stacks import scene_for_roi
from hbis_torch.reconstruct.classical.adaptive_h import cubic_transfer, predict_psnr, recommend_h
from hbis_torch.reconstruct.classical import optical_sample_positions, optics_cutoff

SYSTEM = FoveaSystem()
ROI = (616, 456, 48, 48)


pytestmark = pytest.mark.usefixtures("one_thread")


@lru_cache(maxsize=None)
def _prescan(name: str, full_well: float = 20000.0):
    """A 2 x 2 pre-scan of a scene at a quarter of the exposure each (same total light)."""
    scene = scene_for_roi(name, SYSTEM, ROI, 7, seed=1)
    sensor = SensorModel(full_well_e=full_well / 4)
    stack, _ = simulate_stack(scene, SYSTEM, plan_scan(SYSTEM, 2), roi=ROI, sensor=sensor, seed=1)
    return stack.to_float(), optical_sample_positions(stack)


def test_more_frames_never_hurt_when_each_frame_keeps_its_exposure():
    psnr = predict_psnr(1e-3, 2.0, 0.005, optics_cutoff(SYSTEM), 7, budget="frame")
    values = [psnr[h] for h in range(1, 8)]
    assert all(b >= a - 1e-9 for a, b in zip(values, values[1:]))
    assert values[-1] > values[0] + 3.0


def test_under_a_fixed_light_budget_noise_caps_the_useful_h():
    cutoff = optics_cutoff(SYSTEM)
    quiet = predict_psnr(1e-3, 2.0, 0.002, cutoff, 7)
    noisy = predict_psnr(1e-3, 2.0, 0.05, cutoff, 7)
    gain = lambda p: max(p.values()) - p[2]  # noqa: E731 - what going beyond h = 2 buys
    assert gain(quiet) > gain(noisy)
    # A scene with little fine detail gains less from large h than a detailed one.
    smooth = predict_psnr(1e-3, 3.5, 0.005, cutoff, 7)
    detailed = predict_psnr(1e-3, 1.5, 0.005, cutoff, 7)
    assert gain(smooth) < gain(detailed)


def test_cubic_transfer_is_one_at_dc_and_small_at_the_sampling_rate():
    t = cubic_transfer(torch.tensor([0.0, 0.5, 1.0], dtype=torch.float64))
    assert abs(float(t[0]) - 1) < 1e-6 and 0.3 < float(t[1]) < 0.7 and abs(float(t[2])) < 1e-6


def test_smooth_scene_needs_a_smaller_h_than_a_star():
    smooth = recommend_h(*_prescan("gradient")[:1], SYSTEM, positions=_prescan("gradient")[1], h_max=7)
    frames, positions = _prescan("siemens-star")
    star = recommend_h(frames, SYSTEM, positions=positions, h_max=7)
    assert smooth.h <= 2 < star.h
    assert star.frames == star.h ** 2 and "recommended h" in star.report()


def test_noise_lowers_the_recommendation():
    quiet = recommend_h(*_prescan("words")[:1], SYSTEM, positions=_prescan("words")[1], h_max=7)
    frames, positions = _prescan("words", full_well=600.0)
    noisy = recommend_h(frames, SYSTEM, positions=positions, h_max=7)
    assert noisy.h < quiet.h


def test_single_frame_mode_runs_and_defaults_to_the_design_h_max():
    frames, _ = _prescan("camera")
    choice = recommend_h(frames[0].numpy(), SYSTEM)
    assert choice.h_max == 7 and 1 <= choice.h <= 7
    assert set(choice.predicted_psnr_db) == set(range(1, 8))


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(frames=np.zeros((4, 4))), "at least 16 x 16"),
        (dict(frames=np.full((32, 32), np.nan)), "non-finite"),
        (dict(h_max=0), "h_max"),
        (dict(tolerance_db=-1.0), "tolerance_db"),
        (dict(budget="daily"), "budget"),
        (dict(fill_factor=0.0), "fill_factor"),
        (dict(noise=-1.0), "noise"),
        (dict(frames=np.zeros((4, 32, 32)), positions=np.zeros((4, 32, 32))), "positions must have shape"),
    ],
)
def test_bad_input_is_rejected_with_a_clear_message(kwargs, match):
    args = dict(frames=np.random.default_rng(0).random((32, 32)))
    args.update(kwargs)
    with pytest.raises(HbisInputError, match=match):
        recommend_h(args.pop("frames"), SYSTEM, **args)
