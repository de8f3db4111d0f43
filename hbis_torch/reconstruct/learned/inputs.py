"""The learned method's inputs and glue, in numpy (no torch, no onnxruntime).

:func:`prepare_inputs` puts the frames in *registered order* and computes the per-pixel residual
offsets the network takes; :func:`exposure_gain` brightens dark stacks; :func:`run_tiled` runs
any network function over overlapping tiles; :func:`super_resolve` chains them around any runner
of the network (the onnxruntime session of :class:`~hbis_torch.reconstruct.learned.LearnedSR`,
or eager torch in the benchmark).
"""

from __future__ import annotations

import numpy as np

from hbis_torch.errors import HbisInputError

# Least halo (LR pixels) around each tile: more than the network's receptive field radius (13
# for the shipped models: head + 2 per block + tail + the bilinear base), so that tiling does
# not change the result; deeper models get a wider one.
TILE_HALO = 16


def _check_frames_positions(frames, positions) -> tuple[np.ndarray, np.ndarray]:
    frames = np.asarray(frames)
    positions = np.asarray(positions)
    if frames.ndim != 3:
        raise HbisInputError(f"frames must have shape (F, H, W), got {frames.shape}")
    if positions.shape != frames.shape + (2,):
        raise HbisInputError(
            f"positions must have shape (F, H, W, 2) = {frames.shape + (2,)}, got {positions.shape}"
        )
    frames = frames.astype(np.float32, copy=False)
    if not np.isfinite(frames).all():
        raise HbisInputError("frames contain NaN or infinite values")
    # (the positions are checked by their sums in prepare_inputs: one pass fewer over them)
    return frames, positions.astype(np.float64, copy=False)


def _shift_segments(shift: int, size: int) -> list[tuple[slice, slice]]:
    """(destination, source) slices of one axis moved by ``shift`` whole pixels, edges repeated.

    Destination index i takes source index ``clip(i - shift, 0, size - 1)``; a source slice of
    length 1 is broadcast over its destination slice. Empty pieces are left out.
    """
    m = min(abs(int(shift)), size)
    if shift > 0:
        pieces = [(slice(0, m), slice(0, 1)), (slice(m, size), slice(0, size - m))]
    elif shift < 0:
        pieces = [(slice(0, size - m), slice(m, size)), (slice(size - m, size), slice(size - 1, size))]
    else:
        pieces = [(slice(0, size), slice(0, size))]
    return [(dst, src) for dst, src in pieces if dst.stop > dst.start]


def prepare_inputs(frames, positions, h: int) -> tuple[np.ndarray, np.ndarray]:
    """Put the frames in registered order and compute the per-pixel residual offsets.

    Frame k's mean displacement from the reference grid, in output pixels, is rounded to an
    integer ``s_k = h * n_k + phase_k`` (``phase_k`` in 0 .. h-1 per axis). The frame goes to
    channel ``phase_y * h + phase_x`` and is moved by the whole LR pixels ``n_k`` (edge pixels
    repeated), so that its pixel (x, y) sits near output pixel (h x + phase_x, h y + phase_y)
    minus the constant ``(h - 1) / 2`` of the output grid convention. The offset channels hold
    what is left, exactly: ``h * (position - (x, y)) - phase`` for the sample that landed there.

    Parameters
    ----------
    frames : array, shape (F, H, W)
        Frames in [0, 1] (any order), F = h^2.
    positions : array, shape (F, H, W, 2)
        Sample positions in ROI-local reference-frame LR pixel coordinates (x, y).
    h : int
        Resolution improvement factor.

    Returns
    -------
    frames_reg : ndarray, shape (h^2, H, W), float32
    offsets : ndarray, shape (2 h^2, H, W), float32
        Channels (2c, 2c+1) are (x, y) of registered channel c, in output pixels.

    Raises
    ------
    HbisInputError
        Wrong shapes, non-finite values, F != h^2, or frames that do not sample each of the
        h x h sub-pixel phases once.
    """
    frames, positions = _check_frames_positions(frames, positions)
    count, rows, cols = frames.shape
    if count != h * h:
        raise HbisInputError(
            f"the stack has {count} frames but the model needs h^2 = {h * h} (h = {h})"
        )
    # mean(position - pixel) = mean(position) - centre of the frame
    centre = np.array([(cols - 1) / 2, (rows - 1) / 2])
    # (einsum: numpy's mean over two strided axes is several times slower)
    position_sum = np.einsum("fnc->fc", positions.reshape(count, -1, 2))
    if not np.isfinite(position_sum).all():  # NaN and infinities reach the sums
        if np.isfinite(positions).all():
            raise HbisInputError("sample positions are too large (their sum overflows)")
        raise HbisInputError("sample positions contain NaN or infinite values")
    mean_shift = h * (position_sum / (rows * cols) - centre)  # (F, 2), output pixels
    steps = np.rint(mean_shift).astype(np.int64)
    phases = np.mod(steps, h)
    whole = (steps - phases) // h  # (F, 2) whole LR pixels
    channel = phases[:, 1] * h + phases[:, 0]
    if len(set(channel.tolist())) != count:
        raise HbisInputError(
            "the frames do not sample each of the h x h sub-pixel phases once "
            f"(rounded shifts in output pixels: {steps.tolist()}); the scan does not fit h = {h}"
        )
    grids = (np.arange(cols, dtype=np.float64), np.arange(rows, dtype=np.float64)[:, None])
    frames_reg = np.empty((count, rows, cols), np.float32)
    offsets = np.empty((2 * count, rows, cols), np.float32)
    scratch = np.empty((rows, cols), np.float64)  # reused: no new temporaries per frame
    for k in range(count):
        c = channel[k]
        # Output-grid block (x, y) takes the frame's pixel (x - n_x, y - n_y), clamped at the
        # edges: slices (edge rows and columns broadcast), no index arrays, no copies.
        for dst_y, src_y in _shift_segments(whole[k, 1], rows):
            for dst_x, src_x in _shift_segments(whole[k, 0], cols):
                frames_reg[c, dst_y, dst_x] = frames[k, src_y, src_x]
                for axis, grid in ((0, grids[0][dst_x]), (1, grids[1][dst_y])):
                    # h * (position - pixel) - phase, in this order (as float64): the residual.
                    # Only edge-repeated pixels can be far off; bound them so no input runs away.
                    t = scratch[:dst_y.stop - dst_y.start, :dst_x.stop - dst_x.start]
                    np.subtract(positions[k, src_y, src_x, axis], grid, out=t)
                    np.multiply(t, h, out=t)
                    np.subtract(t, phases[k, axis], out=t)
                    np.clip(t, -h, h, out=offsets[2 * c + axis, dst_y, dst_x], casting="same_kind")
    return frames_reg, offsets


# Dark stacks are brightened before the network (and its output darkened by the same factor):
# the training exposures put the highlights above half scale, and a stack whose brightest
# pixels sit far below that is outside what the network has seen. Normal stacks are untouched.
DARK_TARGET = 0.5
MAX_GAIN = 64.0


def exposure_gain(frames: np.ndarray) -> float:
    """1 for stacks whose 99.9th percentile reaches DARK_TARGET, else up to MAX_GAIN to get there.

    The usual, bright stack is recognised by one count (enough values at or above the target put
    the percentile there, whatever the interpolation), which is several times cheaper than the
    percentile itself; only the others compute it. Same answer either way.
    """
    frames = np.asarray(frames)
    # If fewer than rank values lie below `sure`, the sorted value at rank - 1 and every value
    # above it are >= sure, so the percentile (interpolated between sorted values at
    # floor(0.999 (n - 1)) >= rank and the next) is too. `sure` sits a little above the target so
    # that the interpolation's rounding cannot take it below.
    sure = np.float32(DARK_TARGET * (1 + 1e-6))
    rank = int(np.floor(0.999 * (frames.size - 1))) - 1
    if rank > 0 and np.count_nonzero(frames < sure) < rank:
        return 1.0
    high = float(np.percentile(frames, 99.9))
    if high >= DARK_TARGET:
        return 1.0
    return float(min(MAX_GAIN, DARK_TARGET / max(high, DARK_TARGET / MAX_GAIN)))


def run_tiled(infer, frames_reg: np.ndarray, offsets: np.ndarray, h: int, tile: int = 256,
              halo: int = TILE_HALO) -> np.ndarray:
    """Run ``infer`` over overlapping tiles and stitch the centres.

    Parameters
    ----------
    infer : callable
        (1, h^2, h_t, w_t), (1, 2h^2, h_t, w_t) float32 arrays -> (1, 1, h h_t, h w_t).
    frames_reg, offsets : ndarray, shapes (h^2, H, W) and (2h^2, H, W)
    h, tile, halo : int
        Factor, tile side and halo in LR pixels; a halo wider than the network's receptive field
        radius makes the result independent of the tiling.

    Returns
    -------
    ndarray, shape (hH, hW), float32
    """
    _, rows, cols = frames_reg.shape
    if rows <= tile and cols <= tile:  # one tile: no halo, no stitching, no copies
        return infer(np.ascontiguousarray(frames_reg[None]), np.ascontiguousarray(offsets[None]))[0, 0]
    out = np.empty((h * rows, h * cols), np.float32)
    for y0 in range(0, rows, tile):
        for x0 in range(0, cols, tile):
            y1, x1 = min(y0 + tile, rows), min(x0 + tile, cols)
            ya, xa = max(y0 - halo, 0), max(x0 - halo, 0)
            yb, xb = min(y1 + halo, rows), min(x1 + halo, cols)
            image = infer(np.ascontiguousarray(frames_reg[None, :, ya:yb, xa:xb]),
                          np.ascontiguousarray(offsets[None, :, ya:yb, xa:xb]))[0, 0]
            out[h * y0:h * y1, h * x0:h * x1] = image[h * (y0 - ya):h * (y1 - ya), h * (x0 - xa):h * (x1 - xa)]
    return out


def super_resolve(run_network, frames, positions, h: int, name: str = "the network") -> np.ndarray:
    """Frames and sample positions -> image, around any runner of the network.

    :func:`prepare_inputs`, the dark-stack gain (:func:`exposure_gain`), ``run_network``, then
    a check that the output is finite and the clip to [0, 1]. :class:`LearnedSR` passes its
    onnxruntime session; the benchmark passes eager torch, so that both pay for the same glue.

    Parameters
    ----------
    run_network : callable
        (h^2, H, W), (2h^2, H, W) float32 -> (hH, hW) float32, the raw network output, a new
        array (it is clipped in place).
    frames : array, shape (F, H, W)
    positions : array, shape (F, H, W, 2)
    h : int
    name : str
        How the error message names the model.

    Returns
    -------
    ndarray, shape (hH, hW), float32 in [0, 1]
    """
    frames_reg, offsets = prepare_inputs(frames, positions, h)
    gain = exposure_gain(frames_reg)
    if gain == 1.0:  # the usual case: no copies
        image = run_network(frames_reg, offsets)
    else:
        image = run_network(frames_reg * np.float32(gain), offsets) / np.float32(gain)
    # A model is a function of float32 inputs in [0, 1]; anything non-finite here is a bug
    # in the model file, not in the stack.
    if not np.isfinite(image).all():
        raise HbisInputError(f"model {name} produced non-finite values")
    return np.clip(image, 0.0, 1.0, out=image)  # the image is ours: clip in place
