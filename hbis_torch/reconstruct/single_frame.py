"""The single-frame estimate: one frame enlarged onto the output grid, bicubically.

It is what a burst's reconstruction falls back on where the other frames bring nothing
(:mod:`hbis_torch.reconstruct.burst`) and the baseline every method is scored against
(``hbis validate``, :mod:`hbis_torch.validate`): one definition, so the two agree.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F


def single_frame(frame, h: int) -> np.ndarray:
    """The frame enlarged h times by bicubic interpolation (torch's, a = -0.75) on the output grid
    (HR pixel (U, V) centred at LR ((U + 0.5) / h - 0.5, (V + 0.5) / h - 0.5)), clipped to [0, 1].

    Parameters
    ----------
    frame : array, shape (H, W) or (H, W, C), float in [0, 1]
    h : int

    Returns
    -------
    np.ndarray, shape (h H, h W) or (h H, h W, C), float32

    Examples
    --------
    >>> import numpy as np
    >>> single_frame(np.full((3, 4), 0.25), 2).shape
    (6, 8)
    """
    return _bicubic(frame, scale_factor=h)


def enlarge(image, size: tuple[int, int]) -> np.ndarray:
    """An image on a coarser grid of the same field enlarged onto ``size`` (rows, cols) pixels by
    bicubic interpolation, pixel centres as :func:`single_frame`'s, clipped to [0, 1].

    Parameters
    ----------
    image : array, shape (rows, cols) or (rows, cols, C), float in [0, 1]
    size : (int, int)

    Returns
    -------
    np.ndarray, shape ``size`` or ``size + (C,)``, float32
    """
    return _bicubic(image, size=tuple(size))


def _bicubic(image, **scale) -> np.ndarray:
    """``F.interpolate`` bicubic (half-pixel centres) of a (rows, cols) or (rows, cols, C) image by
    ``scale_factor`` or to ``size``, clipped to [0, 1], float32."""
    x = torch.as_tensor(np.asarray(image, dtype=np.float32))
    x = x[None, None] if x.ndim == 2 else x.permute(2, 0, 1)[None]
    up = F.interpolate(x, mode="bicubic", align_corners=False, **scale)[0].clamp_(0.0, 1.0)
    return (up[0] if np.ndim(image) == 2 else up.permute(1, 2, 0)).numpy()
