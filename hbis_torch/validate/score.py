"""How well a predicted frame matches the observed one: gain and offset fitted by least squares,
then PSNR over the samples away from the estimate's border."""

from __future__ import annotations

import dataclasses

import numpy as np

from hbis_torch.errors import HbisInputError
from hbis_torch.metrics import psnr

#: Samples within this many LR pixels of the reference frame's edge are not scored: there the
#: estimates lean on one side only, and a frame's samples may lie off the grid altogether.
DEFAULT_BORDER_PX = 2.0


@dataclasses.dataclass(frozen=True)
class FrameScore:
    """The score of one predicted frame.

    Attributes
    ----------
    psnr : float
        dB, of the fitted prediction against the observed frame, intensities in [0, 1].
    gain, offset : float
        The fit: observed ~ gain * predicted + offset.
    samples : int
        How many samples were scored.
    """

    psnr: float
    gain: float
    offset: float
    samples: int


def inside(positions, rows: int, cols: int, border: float = DEFAULT_BORDER_PX) -> np.ndarray:
    """(H', W') bool: samples whose positions lie at least ``border`` LR pixels inside the
    reference frame's rows x cols pixel centres."""
    q = np.asarray(positions, dtype=np.float64)
    u, v = q[..., 0], q[..., 1]
    with np.errstate(invalid="ignore"):
        return ((u >= border) & (u <= cols - 1 - border) & (v >= border) & (v <= rows - 1 - border)
                & np.isfinite(u) & np.isfinite(v))


def fit_and_score(predicted, observed, mask) -> FrameScore:
    """Fit ``observed ~ gain * predicted + offset`` (least squares, float64) on ``mask`` and
    return the PSNR of the fitted prediction there.

    Parameters
    ----------
    predicted, observed : array, same shape
        Intensities in [0, 1] (observed); the prediction before gain and offset.
    mask : array of bool, the same shape (or broadcastable)
        Samples to fit and score.

    Returns
    -------
    FrameScore

    Raises
    ------
    HbisInputError
        Fewer than 16 samples in ``mask`` (the frame lies off the estimate), or a non-finite value.
    """
    p = np.asarray(predicted, dtype=np.float64)
    o = np.asarray(observed, dtype=np.float64)
    m = np.broadcast_to(np.asarray(mask, dtype=bool), p.shape)
    if p.shape != o.shape:
        raise HbisInputError(f"predicted {p.shape} and observed {o.shape} frames differ in shape")
    p, o = p[m], o[m]
    if p.size < 16:
        raise HbisInputError(f"only {p.size} sample(s) of the held-out frame lie inside the reference frame's "
                             "border: too few to score")
    if not (np.isfinite(p).all() and np.isfinite(o).all()):
        raise HbisInputError("the prediction or the frame holds NaN or infinite values")
    design = np.stack((p, np.ones_like(p)), axis=1)
    (gain, offset), *_ = np.linalg.lstsq(design, o, rcond=None)
    return FrameScore(psnr(gain * p + offset, o), float(gain), float(offset), int(p.size))
