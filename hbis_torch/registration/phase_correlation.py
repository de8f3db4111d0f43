"""Phase correlation: the coarse translation that starts the fit when there is no prediction.

Frames are (F, H, W) with a reference (H, W); shifts are (F, 2) px as (du, dv), with the sign of
the homographies (content at u in the frame sits at u + du in the reference), and become
(F, 3, 3) float64 translation homographies.
"""

from __future__ import annotations

import torch
from torch import Tensor


def phase_correlation_shifts(frames: Tensor, reference: Tensor) -> Tensor:
    """Coarse translation of each frame relative to the reference, (F, 2) px as (du, dv).

    Normalised cross-power spectrum of Hann-windowed frames; the integer peak is refined by a
    parabola through its neighbours. Good to a few tenths of a pixel, which is all the
    Lucas-Kanade refinement needs to start from any shift. The sign is the homography's: content
    at u in the frame sits at u + du in the reference.

    References
    ----------
    .. [1] C. D. Kuglin and D. C. Hines, "The phase correlation image alignment method",
       Proc. IEEE International Conference on Cybernetics and Society, 1975, pp. 163-165.
    """
    return phase_correlation_peaks(frames, reference, 1)[:, 0]


def phase_correlation_peaks(frames: Tensor, reference: Tensor, count: int, separation: int = 2) -> Tensor:
    """The ``count`` strongest peaks of each frame's phase correlation, strongest first,
    (F, count, 2) px as (du, dv) (the sign of :func:`phase_correlation_shifts`).

    Each peak is the surface's largest value more than ``separation`` px (in u or v) from every
    stronger one, refined by a parabola. A burst with a moving object has two peaks: the object,
    which only translates, can give the sharper one while the turned background's is smeared, so
    the caller fits from each and keeps the motion that explains most of the frame.
    """
    F, H, W = frames.shape
    win = torch.outer(torch.hann_window(H, periodic=False, dtype=frames.dtype),
                      torch.hann_window(W, periodic=False, dtype=frames.dtype))
    a = torch.fft.rfft2((reference - reference.mean()) * win)
    b = torch.fft.rfft2((frames - frames.mean((-2, -1), keepdim=True)) * win)
    cross = a * b.conj()
    corr = torch.fft.irfft2(cross / cross.abs().clamp_min(1e-12), s=(H, W))
    searched = corr.clone()
    f = torch.arange(F)
    near = torch.arange(-separation, separation + 1)
    peaks = []
    for _ in range(count):
        idx = searched.reshape(F, -1).argmax(-1)
        iv, iu = idx // W, idx % W
        peaks.append(_refined(corr, f, iv, iu))
        rows, cols = (iv[:, None] + near) % H, (iu[:, None] + near) % W  # (F, 2 s + 1) each
        searched[f[:, None, None], rows[:, :, None], cols[:, None, :]] = -torch.inf
    return torch.stack(peaks, 1)


def _refined(corr: Tensor, f: Tensor, iv: Tensor, iu: Tensor) -> Tensor:
    """(F, 2) (du, dv): the integer peaks (iv, iu) of ``corr`` (F, H, W), refined by a parabola
    through their neighbours and wrapped to signed shifts."""
    H, W = corr.shape[-2:]

    def parabola(minus, centre, plus):
        den = minus - 2 * centre + plus
        return torch.where(den.abs() > 1e-12, 0.5 * (minus - plus) / den, torch.zeros_like(den))

    c0 = corr[f, iv, iu]
    du = iu + parabola(corr[f, iv, (iu - 1) % W], c0, corr[f, iv, (iu + 1) % W])
    dv = iv + parabola(corr[f, (iv - 1) % H, iu], c0, corr[f, (iv + 1) % H, iu])
    du = torch.where(du > W / 2, du - W, du)
    dv = torch.where(dv > H / 2, dv - H, dv)
    return torch.stack((du, dv), -1)


def _translation(shifts: Tensor) -> Tensor:
    m = torch.eye(3, dtype=torch.float64).repeat(len(shifts), 1, 1)
    m[:, :2, 2] = shifts
    return m
