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
    F, H, W = frames.shape
    win = torch.outer(torch.hann_window(H, periodic=False, dtype=frames.dtype),
                      torch.hann_window(W, periodic=False, dtype=frames.dtype))
    a = torch.fft.rfft2((reference - reference.mean()) * win)
    b = torch.fft.rfft2((frames - frames.mean((-2, -1), keepdim=True)) * win)
    cross = a * b.conj()
    corr = torch.fft.irfft2(cross / cross.abs().clamp_min(1e-12), s=(H, W))
    idx = corr.reshape(F, -1).argmax(-1)
    iv, iu = idx // W, idx % W
    f = torch.arange(F)

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
