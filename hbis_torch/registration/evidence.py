"""How well each motion model explains a frame: the evidence a burst's per-frame model choice reads.

:func:`model_evidence` scores each model's fitted motion by the BIC of the whole frame's
prediction error (:func:`~hbis_torch.capture.burst.register_burst` keeps, per frame, the model
with the lowest); :func:`trimmed_line_mse` is the robust error both it and the burst's
prediction check use. Frames are (F, H, W) float32; motions (F, 3, 3) float64, frame px ->
reference px.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from hbis_torch.registration.bspline import _spline_fetch, prefilter

#: Share of the points a trimmed error keeps (the best ones): a moving object's are left out.
TRIM = 0.75
#: Pixels of a frame that score each model's motion (:func:`model_evidence`): a regular grid of about this many.
EVIDENCE_POINTS = 32768
#: How much less noise the reference's cubic B-spline gives halfway between two pixels than at a
#: pixel, along one axis (its variance, for white noise blurred by the evidence's 5-tap Gaussian:
#: derived in tests/test_burst_fast_paths.py); in between, the drop times sin^2(pi f) (within 3e-4).
SPLINE_NOISE_DROP = 0.0067


def model_evidence(grey: torch.Tensor, reference: int, motions: dict, frames: list) -> dict:
    """BIC of each model's motion from the whole frame's prediction error, per frame.

    A frame's samples at up to :data:`EVIDENCE_POINTS` pixels spread over it are compared with
    the reference read where each motion puts them (both blurred by a Gaussian of 1 px against
    aliasing, a gain and an offset fitted, the worst quarter left out: a moving object). With
    ``n`` such residuals, independent over about 4 pi px^2 of a blurred frame, and ``k`` the
    model's parameters, ``BIC = n log(mse) + k log(n)``: a richer model must explain the frame
    better by more than its parameters could by chance, and that margin shrinks as the frame
    grows.

    Every model is scored on the same points, those all of them keep on the reference: with
    ``n`` in the BIC, a model that kept a few dozen points more would win by them alone. The
    reference is read between pixels by its cubic B-spline, not bilinearly: a bilinear read
    averages the noise of two neighbours, a ninth less of its variance halfway along an axis, so
    in a dim light a slight turn, which spreads the points over fractions of a pixel, would seem
    to explain a frame that only shifted by a whole pixel better; the spline's own drop
    (:data:`SPLINE_NOISE_DROP`) is divided out of each squared residual.

    Parameters
    ----------
    grey : Tensor, shape (F, H, W), float32
    reference : int
    motions : dict of str -> np.ndarray, shape (F, 3, 3)
        Each model's motions, frame px -> reference px.
    frames : list of int
        The frames to score.

    Returns
    -------
    dict of str -> dict of int -> float
        Lower is better; inf where a motion leaves too little of the frame on the reference.
    """
    from hbis_torch.registration.homography import N_PARAMS

    F, H, W = grey.shape
    kernel = _evidence_kernel()
    step = max(1, int(np.sqrt(H * W / EVIDENCE_POINTS)))
    v, u = torch.meshgrid(torch.arange(3, H - 3, step, dtype=torch.float64),
                          torch.arange(3, W - 3, step, dtype=torch.float64), indexing="ij")
    rows, cols = v.shape
    points = torch.stack((u.reshape(-1), v.reshape(-1), torch.ones(u.numel(), dtype=torch.float64)))
    # the reference blurred everywhere and taken as its cubic B-spline (it is read between
    # pixels); a frame only at its points, 5 x 5 taps a point (a strided convolution; the points
    # are 3 px or more inside the frame)
    _, coefficients = prefilter(grey[reference][None], kernel=_evidence_taps())
    window = (slice(1, 1 + (rows - 1) * step + 5), slice(1, 1 + (cols - 1) * step + 5))
    # Residuals of the blurred frames are correlated over about 4 pi px^2.
    independent = max(1.0, (H - 6) * (W - 6) / (4 * np.pi))
    names = list(motions)
    out = {m: {} for m in names}
    for k in frames:
        values = torch.nn.functional.conv2d(grey[k][window][None, None], kernel, stride=step).reshape(-1).double()
        q = torch.from_numpy(np.stack([motions[m][k] for m in names])) @ points  # (models, 3, N)
        qu, qv = q[:, 0] / q[:, 2], q[:, 1] / q[:, 2]
        inside = (qu >= 3) & (qu <= W - 4) & (qv >= 3) & (qv <= H - 4)
        # (float32 places: a frame of 4000 px is read within 2e-4 px, far below what the models differ by)
        where = torch.stack((qu, qv), -1).nan_to_num_(0.0, 0.0, 0.0).float()  # (models, N, 2) px
        target = _spline_fetch(coefficients, where)[0].double()
        scale = _noise_scale(where)  # (models, N)
        scored = [i for i, model in enumerate(names)  # (finite points, finite motion)
                  if int(inside[i].sum()) >= 64 and np.isfinite(motions[model][k]).all()]
        # every model on the same points (those all of them keep on the reference): with n in the
        # BIC, a model that kept a few dozen points more would win by them alone
        common = inside[scored].all(0) if scored else None
        for i, model in enumerate(names):
            if i not in scored:
                out[model][k] = float("inf")
                continue
            kept = common if int(common.sum()) >= 64 else inside[i]
            count = int(kept.sum())
            mse = trimmed_line_mse(values[kept], target[i][kept], scale[i][kept]) + 1e-20
            n = min(float(count), independent * count / inside.shape[1])
            out[model][k] = n * np.log(mse) + N_PARAMS[model] * np.log(n)
    return out


def _noise_scale(places: Tensor) -> Tensor:
    """(...) float64: the factor that brings a residual's squared noise at the reference's points
    ``places`` (..., 2) (u, v) px to its level at whole pixels (:data:`SPLINE_NOISE_DROP`):
    2 / (1 + g), g the spline's noise gain there, the frame's side (at whole pixels) and the
    reference's alike in noise."""
    gain = torch.sin(torch.pi * places.double()).square_().mul_(-SPLINE_NOISE_DROP).add_(1).prod(-1)
    return gain.add_(1).reciprocal_().mul_(2)


def _evidence_kernel() -> Tensor:
    """(1, 1, 5, 5) float32: the Gaussian of 1 px that :func:`model_evidence` blurs frames by
    (Kornia's 5-tap kernel, as its ``gaussian_blur2d`` weighs it)."""
    taps = _evidence_taps()
    return (taps[:, None] * taps[None, :])[None, None].float()


def _evidence_taps() -> Tensor:
    """(5,) float32: :func:`_evidence_kernel`'s taps along one axis."""
    import kornia

    return kornia.filters.get_gaussian_kernel1d(5, 1.0)[0].float()


def trimmed_line_mse(x: torch.Tensor, y: torch.Tensor, scale: torch.Tensor | None = None) -> float:
    """Mean squared residual of ``y`` (N,) about its least-squares line in ``x`` (N,) (a gain and
    an offset), over the best :data:`TRIM` of the points: a moving object's are left out.
    ``scale`` (N,), optional: factors of the squared residuals (before the best are taken).

    The line in closed form about the means (float64: the same fit as a least-squares solver's to
    rounding, without its overhead; a constant ``x`` leaves ``y``'s mean, as the minimum-norm
    solution would)."""
    dx, dy = x - x.mean(), y - y.mean()
    sxx = float(dx.dot(dx))
    slope = float(dx.dot(dy)) / sxx if sxx > 0 else 0.0
    squared = (dy - slope * dx).pow(2)
    if scale is not None:
        squared.mul_(scale)
    # the smallest TRIM of them, unsorted (a selection: a fifth of a sort's time, the same values)
    return float(torch.topk(squared, int(TRIM * len(squared)), largest=False, sorted=False).values.mean())
