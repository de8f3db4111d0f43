"""Stuck pixels (hot, dead) of a burst's sensor: found from the burst itself, told from points of
the scene, and filled before the reconstruction."""

import numpy as np
import pytest
from skimage import data, transform

from hbis_torch.capture.burst import assemble_burst
from hbis_torch.capture.stuck_pixels import fill_stuck_pixels, find_stuck_pixels
from hbis_torch.metrics import psnr
from hbis_torch.reconstruct.registry import reconstruct
from hbis_torch.simulate.burst import random_motions, simulate_burst

pytestmark = pytest.mark.usefixtures("one_thread")
W, H = 96, 72


def _burst(max_shift=2.0, seed=4, truth=None):
    truth = transform.resize(data.camera() / 255.0, (2 * H, 2 * W), anti_aliasing=True) if truth is None else truth
    motions = random_motions(8, (H, W), np.random.default_rng(seed), max_shift, 0.3)
    return simulate_burst(truth, 2, motions, noise=0.005, seed=seed)


def _with_stuck(frames, count=30, seed=0):
    """``frames`` with ``count`` hot pixels (white) and as many dead ones (black), apart from each
    other and from the edges: the frames and the pixels' (row, column), sorted."""
    rng = np.random.default_rng(seed)
    cells = rng.choice((H // 4 - 2) * (W // 4 - 2), 2 * count, replace=False)  # one per 4 x 4 cell
    rows, cols = 4 + 4 * (cells // (W // 4 - 2)), 4 + 4 * (cells % (W // 4 - 2))
    out = frames.copy()
    out[:, rows[:count], cols[:count]] = 255
    out[:, rows[count:], cols[count:]] = 0
    return out, np.stack([rows, cols], -1)


def test_hot_and_dead_pixels_are_found_filled_and_cost_nothing():
    burst = _burst()
    frames, planted = _with_stuck(burst.frames)
    stack, messages = assemble_burst(frames, 2)
    # those that stand out from the scene around them: the most of them
    found = find_stuck_pixels(frames.astype(np.float32) / 255, 0, stack.motions, stack.confidence > 0.5)
    assert {tuple(p) for p in found} <= {tuple(p) for p in planted} and len(found) >= 50, len(found)
    assert any(f"{len(found)} stuck pixel(s)" in m for m in messages), messages
    # filled in the frames, recorded, and given no weight in any frame
    from hbis_torch.reconstruct.burst import burst_samples

    rows, cols = np.array(stack.meta["stuck_pixels"]).T
    assert sorted(map(tuple, stack.meta["stuck_pixels"])) == sorted(map(tuple, found.tolist()))
    assert (np.abs(stack.frames[:, rows, cols].astype(int) - frames[:, rows, cols]) > 0).all()
    assert (burst_samples(stack)[3][:, rows, cols] == 0).all()
    clean = psnr(reconstruct(assemble_burst(burst.frames, 2)[0], "classical"), burst.truth)
    filled = psnr(reconstruct(stack, "classical"), burst.truth)
    import hbis_torch.capture.burst as capture_burst

    kept = capture_burst.without_stuck_pixels
    try:  # the burst as it was before: the reference's stuck pixels stay in the image
        capture_burst.without_stuck_pixels = lambda frames, *_: (frames, np.zeros((0, 2), int), [])
        left = psnr(reconstruct(assemble_burst(frames, 2)[0], "classical"), burst.truth)
    finally:
        capture_burst.without_stuck_pixels = kept
    assert filled > clean - 0.3 and filled > left + 1.0, (clean, filled, left)


def test_points_of_the_scene_are_not_stuck_pixels():
    # a star field: single bright pixels of the scene, which move with the frames
    rng = np.random.default_rng(2)
    sky = np.full((2 * H, 2 * W), 0.05)
    stars = rng.integers(4, 2 * H - 4, 60), rng.integers(4, 2 * W - 4, 60)
    sky[stars] = 1.0
    burst = _burst(truth=sky)
    stack, messages = assemble_burst(burst.frames, 2)
    assert not any("stuck" in m for m in messages), messages
    trusted = np.ones(len(burst.frames), bool)
    assert len(find_stuck_pixels(burst.frames.astype(np.float32) / 255, 0, burst.motions, trusted)) == 0
    # and where the frames hardly moved, nothing can be told apart: nothing is found
    still = _burst(max_shift=0.3)
    frames, _ = _with_stuck(still.frames)
    assert len(find_stuck_pixels(frames.astype(np.float32) / 255, 0, still.motions, trusted)) == 0


def test_a_pixel_is_filled_from_its_neighbours_that_are_not_stuck():
    frames = np.arange(2 * 5 * 5 * 3, dtype=np.uint8).reshape(2, 5, 5, 3)
    out = fill_stuck_pixels(frames, np.array([[2, 2], [2, 3]]))
    ring = [(1, 1), (1, 2), (1, 3), (2, 1), (3, 1), (3, 2), (3, 3)]  # (2, 3) is stuck too
    expected = np.round(np.mean([frames[:, r, c].astype(float) for r, c in ring], axis=0))
    np.testing.assert_array_equal(out[:, 2, 2], expected.astype(np.uint8))
    assert out.dtype == np.uint8 and np.array_equal(np.delete(out.reshape(2, 25, 3), [12, 13], 1),
                                                    np.delete(frames.reshape(2, 25, 3), [12, 13], 1))
    np.testing.assert_array_equal(fill_stuck_pixels(frames, np.zeros((0, 2), int)), frames)
