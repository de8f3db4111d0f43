"""Stage one's object detection: motion between consecutive frames of one camera.

A blob is a connected region (scipy.ndimage.label) where the smoothed absolute frame
difference exceeds ``threshold``; its centre is the difference-weighted centroid. Frame
differencing marks both where the object was and where it is, so the centroid lags the object
by about half a frame's motion: plenty for pointing the fovea, whose ROI is much larger.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from scipy import ndimage
from torch import Tensor

from hbis_torch.errors import HbisInputError


@dataclass
class Blob:
    """One moving region in a frame.

    Attributes
    ----------
    centre_px : (u, v) in the frame's pixel coordinates (0-based centres)
    area_px : int, pixels above threshold
    strength : float, the largest smoothed difference in the blob
    """

    centre_px: tuple[float, float]
    area_px: int
    strength: float


def motion_blobs(previous: Tensor, current: Tensor, threshold: float = 0.06, min_area: int = 4,
                 sigma_px: float = 1.0, merge_px: int = 2) -> list[Blob]:
    """Moving regions between two frames (H, W) in [0, 1], largest first.

    ``threshold`` should sit well above the noise of a difference of two frames (about
    sqrt(2) x the per-frame noise, reduced by the Gaussian smoothing of ``sigma_px``). Parts
    closer than ``merge_px`` pixels count as one region: a textured object's difference image
    breaks into fragments.
    """
    if previous.shape != current.shape or previous.ndim != 2:
        raise HbisInputError(
            f"need two frames of the same (H, W) shape, got {tuple(previous.shape)} and {tuple(current.shape)}")
    if not (torch.isfinite(previous).all() and torch.isfinite(current).all()):
        raise HbisInputError("a frame contains NaN or inf")
    diff = (current.float() - previous.float()).abs().numpy()
    if sigma_px > 0:  # scipy: small frames, no thread start-up cost
        diff = ndimage.gaussian_filter(diff, sigma_px, truncate=2.0)
    mask = diff > threshold
    if merge_px > 0:
        grouped, count = ndimage.label(ndimage.binary_dilation(mask, iterations=merge_px))
        labels = np.where(mask, grouped, 0)
    else:
        labels, count = ndimage.label(mask)
    if count == 0:
        return []
    index = np.arange(1, count + 1)
    areas = ndimage.sum_labels(np.ones_like(diff), labels, index)
    peaks = ndimage.maximum(diff, labels, index)
    centres = ndimage.center_of_mass(diff, labels, index)  # (row, col) each
    blobs = [
        Blob((float(c[1]), float(c[0])), int(a), float(p))
        for c, a, p in zip(centres, areas, peaks)
        if a >= min_area
    ]
    return sorted(blobs, key=lambda b: -b.area_px)
