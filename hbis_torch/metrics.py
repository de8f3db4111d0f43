"""Image quality against a ground truth: PSNR and SSIM, from scikit-image.

Both take images of the same shape, (H, W) or (B, C, H, W), as NumPy arrays or torch tensors of
any float dtype; they are compared in float64 with intensities in [0, ``data_range``].
"""

from __future__ import annotations

import numpy as np
from skimage.metrics import peak_signal_noise_ratio, structural_similarity

from hbis_torch.errors import HbisInputError


def _pair(image, truth) -> tuple[np.ndarray, np.ndarray]:
    a, b = (np.asarray(x.detach().cpu() if hasattr(x, "detach") else x, dtype=np.float64) for x in (image, truth))
    if a.shape != b.shape:
        raise HbisInputError(f"image {a.shape} and truth {b.shape} differ in shape")
    return a, b


def psnr(image, truth, data_range: float = 1.0) -> float:
    """Peak signal-to-noise ratio of ``image`` against ``truth``, dB (inf where they are equal)."""
    a, b = _pair(image, truth)
    with np.errstate(divide="ignore"):
        return float(peak_signal_noise_ratio(b, a, data_range=data_range))


def ssim(image, truth, data_range: float = 1.0) -> float:
    """Structural similarity of two (H, W) images (scikit-image's defaults: 7 x 7 windows)."""
    a, b = _pair(image, truth)
    return float(structural_similarity(b, a, data_range=data_range))
