"""Learned SR inputs and runner: registered order, offsets, clear errors for what cannot be served."""

import numpy as np
import pytest

from hbis_torch.errors import HbisInputError
from hbis_torch.scan import scan_offsets
from hbis_torch.reconstruct.learned import prepare_inputs


def scan_positions(h, rows, cols, gain=1.0, bias=(0.0, 0.0), order=None):
    """Positions of an ideal-ish scan: eq. 7 offsets / h, scaled and shifted; (F, rows, cols, 2)."""
    offsets, ref = scan_offsets(h)
    shifts = offsets.numpy() / h * gain + np.asarray(bias)
    shifts[ref] = 0.0
    yy, xx = np.mgrid[0:rows, 0:cols].astype(np.float64)
    pos = np.stack((xx, yy), -1)[None] + shifts[:, None, None, :]
    if order is not None:
        pos = pos[order]
    return pos


@pytest.mark.parametrize("h", [2, 3, 4, 7])
def test_registered_order_puts_each_frame_at_its_phase(h):
    rows, cols = 6, 9
    rng = np.random.default_rng(h)
    order = rng.permutation(h * h)  # frames in any order
    pos = scan_positions(h, rows, cols, gain=1.05, bias=(0.03, -0.02), order=order)
    # Frame k carries its own index as value, so we can see where it went.
    frames = np.broadcast_to(np.arange(h * h, dtype=np.float32)[:, None, None], (h * h, rows, cols)).copy()
    frames_reg, offsets = prepare_inputs(frames, pos, h)
    for k in range(h * h):
        shift = h * (pos[k, 0, 0] - [0, 0])
        phase = np.mod(np.rint(shift), h).astype(int)
        channel = phase[1] * h + phase[0]
        assert frames_reg[channel, rows // 2, cols // 2] == k
        # The residual offset is the part of the shift that is not the whole output pixel.
        expected = shift - np.rint(shift)
        np.testing.assert_allclose(offsets[2 * channel:2 * channel + 2, rows // 2, cols // 2], expected, atol=1e-5)


def test_whole_pixel_shifts_move_the_frame():
    h = 2
    pos = scan_positions(h, 5, 5)
    # Frame 1 is at (0, -1/2) LR pixel: output-pixel shift (0, -1) = phase (0, 1) one row up.
    # Moved one LR pixel right, its shift is (2, -1): the same phase, one column further.
    pos[1, ..., 0] += 1.0
    frames = np.random.default_rng(0).random((4, 5, 5)).astype(np.float32)
    frames_reg, offsets = prepare_inputs(frames, pos, h)
    c = 1 * h + 0
    np.testing.assert_array_equal(frames_reg[c, :-1, 1:], frames[1, 1:, :-1])
    # Interior residuals stay small; the repeated edge pixels record how far off they are.
    assert np.abs(offsets[2 * c:2 * c + 2, :-1, 1:]).max() < 1e-6
    assert offsets[2 * c, 0, 0] == pytest.approx(h, abs=1e-6)  # column 0 repeats column 1
    assert offsets[2 * c + 1, -1, 1] == pytest.approx(-h, abs=1e-6)  # last row repeats the one above


def test_frame_count_that_does_not_match_h_is_refused():
    pos = scan_positions(3, 4, 4)
    frames = np.zeros((9, 4, 4), np.float32)
    with pytest.raises(HbisInputError, match="9 frames but the model needs h\\^2 = 16"):
        prepare_inputs(frames, pos, 4)


def test_two_frames_at_the_same_phase_are_refused():
    pos = scan_positions(2, 4, 4)
    pos[3] = pos[0]
    with pytest.raises(HbisInputError, match="sub-pixel phases"):
        prepare_inputs(np.zeros((4, 4, 4), np.float32), pos, 2)


@pytest.mark.parametrize("bad", ["nan_frame", "inf_position", "shape"])
def test_non_finite_or_misshapen_input_is_refused(bad):
    pos = scan_positions(2, 4, 4)
    frames = np.zeros((4, 4, 4), np.float32)
    if bad == "nan_frame":
        frames[1, 2, 2] = np.nan
    elif bad == "inf_position":
        pos[2, 1, 1, 0] = np.inf
    else:
        pos = pos[:, :3]
    with pytest.raises(HbisInputError):
        prepare_inputs(frames, pos, 2)


def test_exposure_gain_leaves_normal_stacks_alone_and_lifts_dark_ones():
    from hbis_torch.reconstruct.learned import MAX_GAIN, exposure_gain

    rng = np.random.default_rng(1)
    bright = rng.uniform(0, 0.9, (4, 16, 16)).astype(np.float32)
    assert exposure_gain(bright) == 1.0
    dark = bright * 0.05
    assert exposure_gain(dark) == pytest.approx(0.5 / np.percentile(dark, 99.9))
    assert exposure_gain(np.zeros((4, 16, 16), np.float32)) == MAX_GAIN


def reference_prepare_inputs(frames, positions, h):
    """prepare_inputs written the plain way (index arrays, temporaries): what the fast one must equal."""
    count, rows, cols = frames.shape
    centre = np.array([(cols - 1) / 2, (rows - 1) / 2])
    steps = np.rint(h * (positions.reshape(count, -1, 2).mean(axis=1) - centre)).astype(np.int64)
    phases = np.mod(steps, h)
    whole = (steps - phases) // h
    frames_reg = np.empty((count, rows, cols), np.float32)
    offsets = np.empty((2 * count, rows, cols), np.float32)
    for k in range(count):
        src_x = np.clip(np.arange(cols) - whole[k, 0], 0, cols - 1)
        src_y = np.clip(np.arange(rows) - whole[k, 1], 0, rows - 1)
        pos = positions[k][src_y][:, src_x]
        c = phases[k, 1] * h + phases[k, 0]
        frames_reg[c] = frames[k][src_y][:, src_x]
        offsets[2 * c] = np.clip(h * (pos[..., 0] - np.arange(cols)) - phases[k, 0], -h, h)
        offsets[2 * c + 1] = np.clip(h * (pos[..., 1] - np.arange(rows)[:, None]) - phases[k, 1], -h, h)
    return frames_reg, offsets


@pytest.mark.parametrize("h, rows, cols", [(2, 5, 7), (3, 4, 4), (4, 9, 6), (7, 6, 11)])
def test_prepare_inputs_equals_the_plain_computation_bit_for_bit(h, rows, cols):
    # Whole-pixel shifts of up to 12 LR pixels per frame and axis: more than the frame in places,
    # so some frames are nothing but repeated edge pixels.
    rng = np.random.default_rng(rows * cols + h)
    pos = scan_positions(h, rows, cols, gain=1.02, bias=(0.04, -0.03), order=rng.permutation(h * h))
    pos = pos + rng.integers(-12, 13, (h * h, 1, 1, 2)) + rng.normal(0, 0.02, pos.shape)
    frames = rng.random((h * h, rows, cols), dtype=np.float32)
    got = prepare_inputs(frames, pos, h)
    want = reference_prepare_inputs(frames, pos, h)
    np.testing.assert_array_equal(got[0], want[0])
    np.testing.assert_array_equal(got[1], want[1])


def test_positions_too_large_to_sum_are_refused_by_name():
    pos = scan_positions(2, 4, 4)
    pos[1] = 1e308
    with pytest.raises(HbisInputError, match="too large"):
        prepare_inputs(np.zeros((4, 4, 4), np.float32), pos, 2)


def test_exposure_gain_fast_path_gives_the_percentile_answer():
    """The count that recognises bright stacks never answers 1 where the percentile would not."""
    from hbis_torch.reconstruct.learned import DARK_TARGET, MAX_GAIN, exposure_gain

    def by_percentile(x):
        high = float(np.percentile(x, 99.9))
        return 1.0 if high >= DARK_TARGET else min(MAX_GAIN, DARK_TARGET / max(high, DARK_TARGET / MAX_GAIN))

    rng = np.random.default_rng(2)
    cases = []
    for size in (16, 300, 4 * 37 * 29, 16 * 64 * 64):
        cases.append(rng.random(size, dtype=np.float32))  # bright
        cases.append(rng.random(size, dtype=np.float32) * 0.45)  # dark
        cases.append(np.full(size, DARK_TARGET, np.float32))  # exactly at the target
        for count in (size // 1000, size // 1000 + 1, size // 1000 + 2, 5):
            # all just below the target but for `count` values at or just above it: the
            # percentile crosses the target right here
            x = np.full(size, np.nextafter(np.float32(DARK_TARGET), np.float32(0)), np.float32)
            x[rng.choice(size, min(count, size), replace=False)] = rng.choice(
                [DARK_TARGET, np.nextafter(np.float32(DARK_TARGET), np.float32(1)), 0.51, 1.0])
            cases.append(x)
    for x in cases:
        assert exposure_gain(x) == by_percentile(x)
