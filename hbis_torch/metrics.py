"""Image quality against a ground truth: PSNR and SSIM, from scikit-image.

Both take images of the same shape, (H, W) or (B, C, H, W), as NumPy arrays or torch tensors of
any float dtype; they are compared in float64 with intensities in [0, ``data_range``].
"""

from __future__ import annotations

import numpy as np

from hbis_torch.errors import HbisInputError


def _pair(image, truth) -> tuple[np.ndarray, np.ndarray]:
    a, b = (np.asarray(x.detach().cpu() if hasattr(x, "detach") else x, dtype=np.float64) for x in (image, truth))
    if a.shape != b.shape:
        raise HbisInputError(f"image {a.shape} and truth {b.shape} differ in shape")
    return a, b


def psnr(image, truth, data_range: float = 1.0) -> float:
    """Peak signal-to-noise ratio of ``image`` against ``truth``, dB (inf where they are equal).

    Examples
    --------
    An error of 0.01 everywhere, on images in [0, 1], is 40 dB:

    >>> import numpy as np
    >>> from hbis_torch.metrics import psnr
    >>> truth = np.zeros((32, 32))
    >>> round(psnr(truth + 0.01, truth), 6)
    40.0
    >>> psnr(truth, truth)
    inf
    """
    from skimage.metrics import peak_signal_noise_ratio  # scipy.stats with it: 1.5 s, paid at the first score

    a, b = _pair(image, truth)
    with np.errstate(divide="ignore"):
        return float(peak_signal_noise_ratio(b, a, data_range=data_range))


def ssim(image, truth, data_range: float = 1.0) -> float:
    """Structural similarity of two (H, W) images (scikit-image's defaults: 7 x 7 windows).

    Examples
    --------
    >>> import numpy as np
    >>> from hbis_torch.metrics import ssim
    >>> truth = np.zeros((32, 32))
    >>> truth[8:24, 8:24] = 1.0
    >>> ssim(truth, truth)
    1.0
    >>> ssim(0.5 * truth, truth) < 1.0
    True
    """
    from skimage.metrics import structural_similarity

    a, b = _pair(image, truth)
    return float(structural_similarity(b, a, data_range=data_range))
