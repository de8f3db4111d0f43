"""The burst kind of hbis-stack/1: its JSON is checked, written, read back, and turned into
sample positions on the reference grid."""

import numpy as np
import pytest
import torch

from hbis_torch.errors import HbisInputError, StackFormatError
from hbis_torch.reconstruct.positions import stack_sample_positions
from hbis_torch.stack_io import Stack, make_burst_meta, read_stack, validate_stack, write_stack


def _burst(count=3, h=2, shape=(10, 20)):
    motions = np.repeat(np.eye(3)[None], count, 0)
    motions[1, :2, 2] = (0.5, -0.25)
    if count > 2:
        motions[2] = [[1.01, -0.02, 0.3], [0.02, 1.01, 0.1], [1e-4, 0, 1]]
    meta = make_burst_meta(h, (0, 0, shape[1], shape[0]), motions, [1.0, 0.9, 0.2][:count] + [1.0] * (count - 3),
                           ["identity", "translation", "homography"][:count] + ["translation"] * (count - 3),
                           [[1.0, 0.0]] * count, bit_depth=8)
    frames = np.random.default_rng(0).integers(0, 256, (count, *shape), dtype=np.uint8)
    return Stack(frames, meta), motions


def test_burst_round_trip_and_positions(tmp_path):
    stack, motions = _burst()
    write_stack(tmp_path / "b.tif", stack)
    back = read_stack(tmp_path / "b.tif")  # 3 frames at h = 2: a burst need not hold h x h
    assert back.kind == "burst" and back.h == 2 and back.reference_index == 0
    np.testing.assert_allclose(back.motions, motions)
    positions, trusted = stack_sample_positions(back)
    assert positions.shape == (3, 10, 20, 2) and positions.dtype == torch.float64
    assert trusted.tolist() == [True, True, False]  # confidence 0.2 is below the bar
    np.testing.assert_allclose(positions[1, 3, 4].numpy(), [4.5, 2.75])
    u, v = 7.0, 5.0  # a projective frame: the homography's own arithmetic
    x, y, w = motions[2] @ [u, v, 1.0]
    np.testing.assert_allclose(positions[2, 5, 7].numpy(), [x / w, y / w], rtol=1e-12)
    with pytest.raises(HbisInputError, match="no prism phases"):
        back.phases_deg
    assert Stack(stack.frames, {**stack.meta, "kind": "hbis"}).kind == "hbis"
    validate_stack(stack.frames, {**stack.meta, "stuck_pixels": [[0, 0], [9, 19]]}, "b.tif")  # inside


@pytest.mark.parametrize("change, message", [
    ({"kind": "video"}, "kind must be one of"),
    ({"motions": [[[1, 0, 0], [0, 1, 0], [0, 0, 1]]] * 2}, "one entry per frame"),
    ({"confidence": [1.0, 1.5, 0.2]}, r"confidence must be one number in \[0, 1\]"),
    ({"motion_models": ["identity", "spline", "homography"]}, "motion_models must each be one of"),
    ({"gain_offset": [[1, 0], [0, 0], [1, 0]]}, "gain > 0"),
    ({"motions": [[[1, 0, 0], [0, 1, 0], [0, 0, 1]], [[0, 0, 0], [0, 0, 0], [0, 0, 1]],
                  [[1, 0, 0], [0, 1, 0], [0, 0, 1]]]}, "singular"),
    ({"motions": [[[1, 0, float("nan")], [0, 1, 0], [0, 0, 1]]] * 3}, "finite"),
    ({"scale": 3}, "differs from h"),
    ({"reference_index": 3}, "not a frame index"),
    ({"roi": [0, 0, 20, 11]}, "roi is 20 x 11"),
    ({"stuck_pixels": [[3, 20]]}, "stuck_pixels must be"),
    ({"stuck_pixels": [[3, 4.0]]}, "stuck_pixels must be"),
    ({"stuck_pixels": [3, 4]}, "stuck_pixels must be"),
])
def test_bad_burst_meta_is_refused_in_one_line(change, message):
    stack, _ = _burst()
    meta = {**stack.meta, **change}
    with pytest.raises(StackFormatError, match=message):
        validate_stack(stack.frames, meta, "b.tif")


def test_missing_burst_keys_are_named():
    stack, _ = _burst()
    meta = {k: v for k, v in stack.meta.items() if k != "gain_offset"}
    with pytest.raises(StackFormatError, match="missing key.*gain_offset"):
        validate_stack(stack.frames, meta, "b.tif")
