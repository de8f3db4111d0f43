"""Bayer colour filter arrays: which pixel sees which colour, mosaicking RGB, and demosaicking.

A pattern ("RGGB", "BGGR", "GRBG", "GBRG") names the colours of the top-left 2 x 2 pixels row by
row, as the stack's ``cfa`` key does. Demosaicking uses OpenCV (the ``camera`` extra).
"""

from __future__ import annotations

import numpy as np

from hbis_torch.optional import import_cv2


def bayer_masks(cfa: str, height: int, width: int) -> np.ndarray:
    """(3, H, W) bool: which pixels carry R, G and B under the pattern ``cfa`` (e.g. "RGGB")."""
    masks = np.zeros((3, height, width), dtype=bool)
    for k, colour in enumerate(cfa):
        masks["RGB".index(colour), k // 2::2, k % 2::2] = True
    return masks


def mosaic(rgb: np.ndarray, cfa: str) -> np.ndarray:
    """The raw Bayer frames (..., H, W) a sensor with pattern ``cfa`` records of RGB (..., H, W, 3)."""
    masks = bayer_masks(cfa, *rgb.shape[-3:-1])
    return np.einsum("...hwc,chw->...hw", rgb, masks.astype(rgb.dtype))


_OPENCV_CODES = {"RGGB": "COLOR_BayerRGGB2RGB_EA", "BGGR": "COLOR_BayerBGGR2RGB_EA",
                 "GRBG": "COLOR_BayerGRBG2RGB_EA", "GBRG": "COLOR_BayerGBRG2RGB_EA"}


def demosaic(raw: np.ndarray, cfa: str) -> np.ndarray:
    """Raw Bayer frames (F, H, W) float in [0, 1] -> RGB (F, H, W, 3) float32, OpenCV edge-aware."""
    cv2 = import_cv2("demosaicking Bayer frames")
    code = getattr(cv2, _OPENCV_CODES[cfa])
    scaled = np.round(np.clip(raw, 0.0, 1.0) * 65535).astype(np.uint16)
    out = np.stack([cv2.cvtColor(np.ascontiguousarray(f), code) for f in scaled])
    return out.astype(np.float32) / 65535
