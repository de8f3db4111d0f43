"""Stuck pixels of a burst's sensor (hot, or dead), found from the burst itself, and filled.

A hot pixel reads bright in every frame, a dead one dark, at the same place on the sensor. Most
sensors have a few; long exposures and warm sensors have more. The reference frame's stay in its
enlarged image wherever no other frame's sample outweighs them, as spots the size of an output
pixel or more.

A burst shows them apart from the scene: the scene moves across the sensor from frame to frame
and they do not. A pixel is stuck (:func:`find_stuck_pixels`) when it stands out from all eight of
its neighbours, the same way, in the reference and in nearly every frame that moved at least
:data:`MOVED_PX` there (a point of the scene, a star or a glint, moved with those frames; a pixel
that stands out where the scene did not move cannot be told from one, and is left). Stuck pixels
are then filled with the mean of their neighbours that are not stuck (:func:`fill_stuck_pixels`),
as a bad-pixel map's are: the other frames' samples cover the place.
"""

from __future__ import annotations

import numpy as np

#: How far (px) a frame's motion must move the scene at a pixel for that frame to tell the pixel
#: from a point of the scene.
MOVED_PX = 1.0
#: Frames that moved that far, at least: fewer, and the burst cannot tell (nothing is found).
MIN_MOVED_FRAMES = 3
#: The share of those frames in which a stuck pixel stands out (by half the step that the
#: reference's must).
STANDS_OUT_SHARE = 0.9
#: How far a pixel must stand out from the nearest of its neighbours: this many times the
#: reference's noise (a robust spread of its pixels against their neighbours' mean), and at least
#: :data:`MIN_STEP` of white.
NOISE_TIMES = 8.0
MIN_STEP = 0.02
#: The noise is measured on every this many rows (a spread needs no more).
SPREAD_ROW_STEP = 4
_RING = ((-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 1), (1, -1), (1, 0), (1, 1))


def find_stuck_pixels(grey: np.ndarray, reference: int, motions: np.ndarray, trusted: np.ndarray,
                      spacing: int = 1) -> np.ndarray:
    """The pixels that stand out from their neighbours, the same way, wherever the scene moved.

    Parameters
    ----------
    grey : np.ndarray, shape (F, H, W), float32 in [0, 1]
        The frames' luminance (or a raw burst's normalised mosaics, with ``spacing`` 2).
    reference : int
    motions : np.ndarray, shape (F, 3, 3)
        Frame px -> reference px.
    trusted : np.ndarray, shape (F,), bool
        The frames whose motion is trusted (the others say nothing).
    spacing : int
        How far apart (px) a pixel's eight neighbours lie: 1, or 2 on a Bayer mosaic (its
        neighbours of the same colour).

    Returns
    -------
    np.ndarray, shape (N, 2), int
        (row, column) of each stuck pixel (none within ``spacing`` of the frame's edge).
    """
    import cv2

    ref = np.ascontiguousarray(grey[reference], dtype=np.float32)
    s = spacing
    ring = np.zeros((2 * s + 1, 2 * s + 1), np.uint8)
    ring[::s, ::s] = 1
    ring[s, s] = 0
    step = max(NOISE_TIMES * _noise(ref, s), MIN_STEP)
    above = ref - cv2.dilate(ref, ring, borderType=cv2.BORDER_REPLICATE)
    below = cv2.erode(ref, ring, borderType=cv2.BORDER_REPLICATE) - ref
    found = []
    for sign, apart in ((1.0, above), (-1.0, below)):
        inner = apart[s:-s, s:-s] > step
        rows, cols = np.nonzero(inner)
        if rows.size:
            found.append((sign, rows + s, cols + s))
    others = [k for k in range(len(grey)) if k != reference and trusted[k]]
    out = []
    for sign, rows, cols in found:
        moved = _moved(motions[others], rows, cols)  # (others, N) bool
        enough = moved.sum(0) >= MIN_MOVED_FRAMES
        if not enough.any():
            continue
        rows, cols, moved = rows[enough], cols[enough], moved[:, enough]
        values = np.asarray(grey[:, rows, cols])[others] * sign  # (others, N)
        nearest = np.max([np.asarray(grey[:, rows + s * dr, cols + s * dc])[others] * sign for dr, dc in _RING],
                         axis=0)
        stands = (values - nearest) > step / 2
        share = (stands & moved).sum(0) / moved.sum(0)
        keep = share >= STANDS_OUT_SHARE
        out.append(np.stack([rows[keep], cols[keep]], -1))
    return np.concatenate(out) if out else np.zeros((0, 2), int)


def without_stuck_pixels(frames: np.ndarray, grey: np.ndarray, reference: int, motions: np.ndarray,
                         trusted: np.ndarray, spacing: int = 1) -> tuple[np.ndarray, np.ndarray, list]:
    """:func:`find_stuck_pixels` then :func:`fill_stuck_pixels`: (the frames, filled where any
    was found, the pixels (N, 2), and the line that says so, or none)."""
    pixels = find_stuck_pixels(grey, reference, motions, trusted, spacing)
    if not len(pixels):
        return frames, pixels, []
    return fill_stuck_pixels(frames, pixels, spacing), pixels, [
        f"{len(pixels)} stuck pixel(s) of the sensor (hot or dead: they stand out in every frame while the scene "
        "moves) filled from their neighbours and given no weight"]


def fill_stuck_pixels(frames: np.ndarray, pixels: np.ndarray, spacing: int = 1) -> np.ndarray:
    """``frames`` (F, H, W) or (F, H, W, C), any dtype, with each of ``pixels`` ((N, 2) row,
    column, none within ``spacing`` of the edge) set to the mean of its eight neighbours
    ``spacing`` px away that are not among them (a pixel with none keeps its value): a copy, in
    the frames' dtype (rounded)."""
    out = np.array(frames)
    if not len(pixels):
        return out
    rows, cols = pixels[:, 0], pixels[:, 1]
    H, W = frames.shape[1:3]
    stuck = np.zeros((H, W), bool)
    stuck[rows, cols] = True
    total = np.zeros((len(frames), len(rows), *frames.shape[3:]))
    count = np.zeros(len(rows))
    for dr, dc in _RING:
        r, c = rows + spacing * dr, cols + spacing * dc
        good = ~stuck[r, c]
        total += frames[:, r, c] * good.reshape(-1, *[1] * (frames.ndim - 3))
        count += good
    filled = count > 0
    mean = total[:, filled] / count[filled].reshape(-1, *[1] * (frames.ndim - 3))
    if np.issubdtype(out.dtype, np.integer):
        mean = np.round(mean)
    out[:, rows[filled], cols[filled]] = mean.astype(out.dtype)
    return out


def _noise(image: np.ndarray, s: int = 1) -> float:
    """A robust spread of the image's pixels against the mean of their four neighbours ``s`` px
    away (scaled to one pixel's noise for white noise; texture adds to it, so a textured frame asks
    more)."""
    step = SPREAD_ROW_STEP
    rows = slice(s, image.shape[0] - s, step)
    centre = image[rows, s:-s]
    mean = (image[0:-2 * s:step, s:-s] + image[2 * s::step, s:-s] + image[rows, :-2 * s] + image[rows, 2 * s:]) / 4
    residual = centre - mean
    mad = float(np.median(np.abs(residual - np.median(residual))))
    return 1.4826 * mad / np.sqrt(1.25)  # (the residual's variance: 1 + 4/16 of a pixel's)


def _moved(motions: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """(frames, N) whether each frame's motion moves pixel (row, column) at least :data:`MOVED_PX`."""
    points = np.stack([cols, rows, np.ones_like(cols)]).astype(np.float64)  # (3, N)
    mapped = motions @ points  # (frames, 3, N)
    xy = mapped[:, :2] / mapped[:, 2:]
    return np.hypot(xy[:, 0] - cols, xy[:, 1] - rows) >= MOVED_PX
