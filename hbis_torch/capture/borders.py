"""Still black bands at a burst's edges (a letterbox or a pillarbox) and the picture inside them.

A video made for another shape of screen carries black bands, and so does a frame a phone or an
editor padded. The bands are part of every frame at the same place: they do not move with the
camera, so their edges with the picture pull a burst's registration towards no motion, and they
hold nothing to super-resolve. :func:`picture_inside_bands` finds them from the frames' edges
inward, so a burst is cut to the picture before any work.

A band is a run of whole rows (or columns) at an edge that hold one dark value in every frame:
within :data:`BAND_SPREAD` of white, and no brighter than :data:`BAND_DARKEST` of white. The
sensor's noise moves a photographed row by more than that, even in the dark; only a value written
by software holds it, as video codecs hold a flat black band.
"""

from __future__ import annotations

import numpy as np

#: A band row's spread (largest minus smallest value, over its pixels and every frame), as a
#: fraction of white: two steps of 8 bits, for a codec's rounding.
BAND_SPREAD = 2 / 255
#: A band is black or nearly (video's limited range puts black at 16 of 255).
BAND_DARKEST = 0.1


def picture_inside_bands(frames: np.ndarray, white: float) -> tuple[int, int, int, int] | None:
    """The rectangle inside still black bands at the frames' edges, or None if there are none.

    Parameters
    ----------
    frames : np.ndarray, shape (F, H, W) or (F, H, W, 3)
        Any dtype (a memory map is read a row or column at a time, from the edges inward).
    white : float
        The value of white in the frames' units (255 for 8 bits, 1023 for 10 bits in a 16-bit
        file, 1 for float).

    Returns
    -------
    (u0, v0, width, height) or None
        The picture's rectangle, in the frames' px; None where no edge has a band or where the
        bands leave nothing (a burst of black frames is the registration's to refuse).
    """
    H, W = frames.shape[1:3]
    top = _band(lambda i: frames[:, i], H, white)
    if top == H:
        return None
    bottom = _band(lambda i: frames[:, H - 1 - i], H - top, white)
    left = _band(lambda j: frames[:, top:H - bottom, j], W, white)
    right = _band(lambda j: frames[:, top:H - bottom, W - 1 - j], W - left, white)
    if not top + bottom + left + right or top + bottom >= H or left + right >= W:
        return None
    return left, top, W - left - right, H - top - bottom


def _band(line, length: int, white: float) -> int:
    """How many lines from an edge (``line(i)``: the i-th from it, in every frame) hold one dark
    value (:data:`BAND_SPREAD`, :data:`BAND_DARKEST`), at most ``length``."""
    for i in range(length):
        values = line(i)
        low, high = float(values.min()), float(values.max())
        if high - low > BAND_SPREAD * white or high > BAND_DARKEST * white:
            return i
    return length
