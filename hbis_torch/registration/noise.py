"""Per-frame intensity statistics: mean, spread and the sensor's noise level.

Frames are (F, H, W); every statistic is per frame, (F,), in the frames' units and dtype.
"""

from __future__ import annotations

import torch
from torch import Tensor


def _mean_and_spread(frames: Tensor) -> tuple[Tensor, Tensor]:
    """Per-frame mean and standard deviation (population) of (F, H, W), each (F,).

    One pass for the sum of squares (a dot product); frames whose variance is small next to
    their squared mean, where that shortcut cancels badly, are recomputed in two passes.
    """
    F = frames.shape[0]
    flat = frames.reshape(F, -1)
    mean = flat.mean(-1)
    var = (torch.linalg.vecdot(flat, flat) / flat.shape[1] - mean * mean).clamp_min(0)
    unsure = (var < 1e-3 * mean * mean).nonzero()[:, 0]
    if len(unsure):
        var[unsure] = (flat[unsure] - mean[unsure, None]).square().mean(-1)
    return mean, var.sqrt()


def immerkaer(frames):
    """Immerkaer's (1996) 3 x 3 operator [[1, -2, 1], [-2, 4, -2], [1, -2, 1]] at every inner pixel.

    It cancels smooth content; on white noise of level s its output has standard deviation 6 s.
    Written with slices only, so it takes a Tensor or a numpy array alike.

    Parameters
    ----------
    frames : Tensor or ndarray, shape (..., H, W)

    Returns
    -------
    Tensor or ndarray, shape (..., H - 2, W - 2)
    """
    # The operator is [1, -2, 1] along rows times the same along columns: two second differences,
    # each written in place (two input-sized temporaries at most: a full frame's output grid is
    # 60 M pixels at h = 7).
    d = frames[..., 1:-1] * -2
    d += frames[..., :-2]
    d += frames[..., 2:]
    out = d[..., 1:-1, :] * -2
    out += d[..., :-2, :]
    out += d[..., 2:, :]
    return out


def noise_sigma(frames: Tensor) -> Tensor:
    """Robust per-frame noise level (F,), in the frames' units (:func:`immerkaer`, median form).

    The median makes edges count little.
    """
    out = immerkaer(frames).flatten(1)
    step = max(1, out.shape[1] // 2048)  # a couple of thousand values make a good median
    return 1.4826 * out[:, ::step].abs().median(-1).values / 6.0
