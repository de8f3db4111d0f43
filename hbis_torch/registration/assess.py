"""Assessment of a fit: precision, confidence, the problems found, and frames out of order.

Per-frame results are (F,) float64 (confidence in [0, 1], precision in px) or (F,) bool, with
messages that name the frame. Homographies are (F, 3, 3), frame px -> reference px; frames are
H x W px.
"""

from __future__ import annotations

import torch
from torch import Tensor

from hbis_torch.notices import act
from hbis_torch.registration.homography import _grid_jacobian
from hbis_torch.registration.lucas_kanade import _Fit

# Thresholds behind the flags (px unless said otherwise).
PRECISION_SCALE_PX = 0.05  # confidence exp(-(precision / this)^2); "too little texture" above it
OCCLUSION_FRACTION = 0.10  # share of compared pixels in non-matching tiles that is reported
MIN_CORRELATION = 0.5  # frame and reference correlate less than this at the compared points: another scene


def _assess(fit: _Fit, precision: Tensor, flat: Tensor, noise: Tensor, ref: int,
            iterations: int) -> tuple[Tensor, list[str]]:
    """Confidence (F,) in [0, 1] and one message per problem found.

    The confidence multiplies three factors: the expected error from the fit's curvature and
    the noise (exp(-(e / 0.05 px)^2): texture), the share of pixels in tiles that matched
    (occlusion), and, where the residual is more than noise explains, how well frame and
    reference correlate at the compared points (a different scene). A fit that did not
    converge counts half.
    ``precision`` (F,) is the expected error in px (:func:`_precision_px`) and ``noise`` (F,)
    the expected residual scale from noise alone.
    """
    F = len(flat)
    precision = precision.clone()
    mismatch = fit.mismatch_fraction
    residual = fit.sigma
    unexplained = residual > 2 * noise
    confidence = torch.exp(-((precision / PRECISION_SCALE_PX) ** 2))
    confidence = confidence * (1 - mismatch).clamp(0, 1)
    match = ((fit.correlation - MIN_CORRELATION) / (1 - MIN_CORRELATION)).clamp(0, 1)
    confidence = torch.where(unexplained, confidence * match, confidence)
    confidence = torch.where(fit.converged, confidence, 0.5 * confidence)
    confidence = torch.where(flat, torch.zeros_like(confidence), confidence)
    messages: list[str] = []
    if bool(flat[ref]):
        messages.append(act(f"reference frame {ref} is flat: there is nothing to register against; "
                            "choose a frame with texture as the reference"))
        confidence[:] = 0.0
    # Plain Python lists from here: one conversion each instead of one tensor op per frame.
    is_flat, converged = flat.tolist(), fit.converged.tolist()
    other_scene = ((fit.correlation < MIN_CORRELATION) & unexplained).tolist()
    correlation, occluded, error = fit.correlation.tolist(), mismatch.tolist(), precision.tolist()
    misfit, over_noise = unexplained.tolist(), (residual / noise.clamp_min(1e-12)).tolist()
    for k in range(F):
        if k == ref or is_flat[ref]:
            continue
        if is_flat[k]:
            messages.append(f"frame {k} is flat (no image)")
        elif other_scene[k]:
            messages.append(f"frame {k} does not match the reference (correlation "
                            f"{correlation[k]:.2f} where they are compared): a different scene?")
        elif occluded[k] > OCCLUSION_FRACTION:
            messages.append(f"frame {k}: {100 * occluded[k]:.0f}% of its pixels do not match "
                            "the reference and were left out (occlusion or a moving object?)")
        elif error[k] > PRECISION_SCALE_PX and misfit[k]:  # the error comes from the residual, not the texture
            messages.append(f"frame {k}: its motion does not fit it (residual {over_noise[k]:.0f} times the "
                            f"noise's; expected error {error[k]:.3f} px): a turn, perspective or shift beyond "
                            "the fit's reach from its start, a changed scene, or aliasing")
        elif error[k] > PRECISION_SCALE_PX:
            messages.append(f"frame {k}: too little texture above the noise to register "
                            f"(expected error {error[k]:.3f} px)")
        if not converged[k] and not is_flat[k]:
            messages.append(f"frame {k}: registration did not converge in {iterations} iterations")
    confidence[ref] = 1.0
    return confidence.clamp(0, 1), messages


def _precision_px(fit: _Fit, model: str, H: int, W: int, corr_area: float) -> Tensor:
    """RMS over a 5 x 5 grid on the frame of the displacement's standard error, in px, (F,).

    The least-squares covariance assumes independent residuals; the blurred frames have
    residuals correlated over about ``corr_area`` pixels, so the variance is scaled by it.
    """
    jac = _grid_jacobian(H, W, model)  # (2 P, k)
    var = ((jac @ fit.covariance) * jac).sum(-1)  # (F, 2 P): variance of dx, dy at each point
    return torch.sqrt(var.clamp_min(0).mean(-1) * 2 * corr_area) * (max(H, W) / 2.0)


def _check_order(measured: Tensor, predicted: Tensor, H: int, W: int, ref: int, ok: Tensor):
    """Registered frames whose measured position is nearer another frame's planned position
    than their own.

    Returns (out_of_order (F,) bool, messages).
    """
    centre = torch.tensor([(W - 1) / 2, (H - 1) / 2, 1.0], dtype=torch.float64)
    m, p = (h @ centre for h in (measured, predicted))  # (F, 3) each
    m, p = m[:, :2] / m[:, 2:], p[:, :2] / p[:, 2:]
    spacing = torch.cdist(p, p)
    spacing.fill_diagonal_(float("inf"))
    half_step = 0.5 * float(spacing.min())
    dist = torch.cdist(m, p)
    nearest, own, registered = dist.argmin(1).tolist(), dist.diagonal().tolist(), ok.tolist()
    flags = [False] * len(m)
    out = []
    for k, (j, d) in enumerate(zip(nearest, own)):
        if k == ref or not registered[k] or d <= half_step:
            continue
        if j != k:
            flags[k] = True
            out.append(f"frame {k} sits where frame {j} was planned "
                       f"({d:.3f} px from its own plan): frames out of order?")
        else:
            out.append(f"frame {k} is {d:.3f} px from its planned position")
    return torch.tensor(flags), out
