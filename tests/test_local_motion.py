"""The local motion on top of each frame's homography (hbis_torch.registration.local): smoothed
across tiles, it follows a rolling shutter and stays near zero where the motion is a translation."""

import numpy as np
import pytest
import torch

from hbis_torch.capture.burst import assemble_burst
from hbis_torch.registration import local
from hbis_torch.registration.local import sample_offsets, smooth_offsets
from hbis_torch.training.handheld_render import render_burst

pytestmark = pytest.mark.usefixtures("one_thread")
W, H = 640, 480


def test_smoothing_keeps_a_constant_field_and_fills_tiles_without_a_say():
    rng = np.random.default_rng(0)
    weight = rng.uniform(0, 1, (6, 8))
    weight[2, 3] = 0.0
    field = np.broadcast_to([0.3, -0.2], (6, 8, 2)).copy()
    field[2, 3] = [5.0, 5.0]  # a tile without a say (its own content moved) does not count
    np.testing.assert_allclose(smooth_offsets(field, weight, 2.0)[2, 3], [0.3, -0.2], atol=1e-12)
    np.testing.assert_allclose(smooth_offsets(field, weight, 2.0)[0, 0], [0.3, -0.2], atol=1e-12)
    assert not smooth_offsets(field, np.zeros((6, 8)), 2.0).any()  # no tile has a say: no local motion


def _flow_error(burst, stack) -> tuple[np.ndarray, np.ndarray]:
    """Per frame, the RMS distance (px) between the true flow and the homography alone, and the
    homography with the local field, over every 4th pixel inside a border of 8 px."""
    offsets = torch.tensor(stack.meta["local_motion"]["offsets"])
    v, u = np.mgrid[8:H - 8:4, 8:W - 8:4].astype(np.float64)
    alone, both = [], []
    for k in range(1, len(burst.frames)):
        m = stack.motions[k]
        w = m[2, 0] * u + m[2, 1] * v + m[2, 2]
        x, y = (m[0, 0] * u + m[0, 1] * v + m[0, 2]) / w, (m[1, 0] * u + m[1, 1] * v + m[1, 2]) / w
        true = burst.flow(k)[v.astype(int), u.astype(int)]
        d = sample_offsets(offsets[k:k + 1], torch.tensor(np.stack((x, y), -1))[None]).numpy()[0]
        alone.append(np.sqrt(((x - true[..., 0]) ** 2 + (y - true[..., 1]) ** 2).mean()))
        both.append(np.sqrt(((x + d[..., 0] - true[..., 0]) ** 2 + (y + d[..., 1] - true[..., 1]) ** 2).mean()))
    return np.array(alone), np.array(both)


def test_the_local_field_follows_a_rolling_shutter():
    burst = render_burst("rolling_shutter", 2, 4, W, H, seed=1)
    stack, _ = assemble_burst(burst.frames, 2)
    alone, both = _flow_error(burst, stack)
    assert (both < alone).all() and both.mean() < 0.6 * alone.mean(), (alone, both)


def test_the_local_field_of_a_translation_is_near_zero_and_smoothing_keeps_it_there(monkeypatch):
    """Each tile's own estimate carries its noise and aliasing (0.03-0.04 px here); across tiles
    they average out, what a homography leaves does not."""
    burst = render_burst("translation", 2, 4, W, H, seed=1)
    smoothed, _ = assemble_burst(burst.frames, 2)
    monkeypatch.setattr(local, "SMOOTH_TILES", 1e-3)  # each tile on its own
    raw, _ = assemble_burst(burst.frames, 2)
    error_smoothed, error_raw = _flow_error(burst, smoothed)[1], _flow_error(burst, raw)[1]
    assert error_smoothed.max() < 0.02 and (error_smoothed < 0.5 * error_raw).all(), (error_smoothed, error_raw)
