"""Model choice: the simplest motion model that explains the residual.

A richer model (:data:`~hbis_torch.registration.homography.MODELS`, simplest first) is tried
only when a score test on the simpler fit's residual says it would pay (BIC over the effective
number of independent residuals n / ``corr_area``, ``corr_area`` in compared points per
correlated area of the blurred frames) and its extra motion, in px at the frame's corners, is
measurable; it is kept only if the full fit confirms both. Per-frame statistics are (F,);
``use`` (F,) bool picks the frames that take part.
"""

from __future__ import annotations

import torch
from torch import Tensor

from hbis_torch.registration.homography import MODELS, N_PARAMS, lk_motion_difference
from hbis_torch.registration.lucas_kanade import _Fit, _LucasKanade


def _bic(fit: _Fit, k: int, corr_area: float, use: Tensor) -> float:
    """Bayesian information criterion of a fit, summed over the frames in ``use`` (lower is
    better), with the effective number of independent residuals n / corr_area."""
    n_eff = (fit.n_valid / corr_area).clamp_min(k + 1.0)
    per_frame = n_eff * torch.log(fit.rss.clamp_min(1e-300) / fit.n_valid.clamp_min(1)) + k * torch.log(n_eff)
    return float(per_frame[use].sum())


def _penalty(fit: _Fit, k_extra: int, corr_area: float, use: Tensor) -> float:
    n_eff = (fit.n_valid / corr_area).clamp_min(2.0)
    return float(k_extra * torch.log(n_eff[use]).sum())


def _choose_model(lk: _LucasKanade, fit: _Fit, chosen: str, keep: Tensor | None, corr_area: float, use: Tensor,
                  iterations: int, tolerance_px: float, motion_tolerance_px: float,
                  ladder: tuple[str, ...] = MODELS) -> tuple[str, _Fit]:
    """The simplest model that explains the residual, starting from ``fit`` of model ``chosen``.

    Each richer model in turn is fitted (from the current fit, on the points in ``keep`` (F, N)
    bool, if given) only when the score test says it would pay and move some pixel by more than
    ``motion_tolerance_px``, and kept only if the full fit confirms both over the frames in
    ``use`` (F,) bool. ``ladder``: the models to climb, simplest first (a scan's :data:`MODELS`,
    or a burst's :data:`~hbis_torch.registration.homography.ALL_MODELS` with the affine step).

    Returns (the model kept, its fit).
    """
    H, W = lk.H, lk.W
    for richer in ladder[ladder.index(chosen) + 1:]:
        extra = N_PARAMS[richer] - N_PARAMS[chosen]
        gain, moved = lk.score_test(fit, richer, chosen, corr_area, use)
        if gain <= _penalty(fit, extra, corr_area, use) or moved <= motion_tolerance_px:
            continue
        trial = lk.fit(fit.homographies, richer, iterations, tolerance_px, keep=keep)
        moved = float(lk_motion_difference(trial.homographies, fit.homographies, H, W, use))
        if _bic(trial, N_PARAMS[richer], corr_area, use) < _bic(fit, N_PARAMS[chosen], corr_area, use) \
                and moved > motion_tolerance_px:
            chosen, fit = richer, trial
    return chosen, fit
