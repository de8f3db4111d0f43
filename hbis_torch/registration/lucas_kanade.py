"""The Lucas-Kanade fitter: robust Gauss-Newton refinement of every frame's homography.

Homographies are (F, 3, 3) float64, frame px -> reference px (see
:mod:`hbis_torch.registration.homography`). The fit compares the frames at N fixed points,
(N, 2) (u, v) integer px in float64, with the reference's cubic B-spline (:mod:`.bspline`);
per-point quantities are (F, N), in the resampling dtype (float32 or float64); the normal
equations, parameter steps (F, k) and covariances (F, k, k) are float64, in normalised units.

The fit is the forward-compositional form of the Lucas-Kanade algorithm [1]_ (the warp is
updated as H <- H W(dp)), with robust weights, as laid out by Baker and Matthews [2]_.

References
----------
.. [1] B. D. Lucas and T. Kanade, "An iterative image registration technique with an application
   to stereo vision", Proc. 7th International Joint Conference on Artificial Intelligence
   (IJCAI), 1981, pp. 674-679.
.. [2] S. Baker and I. Matthews, "Lucas-Kanade 20 years on: a unifying framework",
   International Journal of Computer Vision 56(3), 2004, pp. 221-255.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass

import torch
from torch import Tensor

from hbis_torch.registration.bspline import _spline_fetch
from hbis_torch.registration.homography import (
    _EMBEDDING,
    N_PARAMS,
    _corner_jacobian,
    _frame_constants,
    _update_basis,
    _warp_jacobian,
)

COARSE_POINTS = 256  # points of a fit's first Gauss-Newton step (see _LucasKanade)


@dataclass
class _Fit:
    homographies: Tensor  # (F, 3, 3) frame -> reference, float64
    residual: Tensor  # (F, N) aligned difference at the solution (0 where not compared)
    weights: Tensor  # (F, N) robust weights (0 where not compared)
    slope: Tensor  # (F, N, 2) d reference value / d frame motion (normalised units), at the solution
    rss: Tensor  # (F,) weighted sum of squared residuals
    n_valid: Tensor  # (F,) pixels compared
    mismatch_fraction: Tensor  # (F,) compared pixels in tiles that do not match (occlusion)
    mismatch_points: Tensor  # (F, N) bool: those points
    covariance: Tensor  # (F, k, k) of the normalised parameters
    converged: Tensor  # (F,) bool
    sigma: Tensor  # (F,) robust residual scale
    correlation: Tensor  # (F,) correlation of frame and reference at the compared points


class _LucasKanade:
    """Forward-compositional Gauss-Newton fit of every frame's homography against the reference.

    Each frame is compared with the reference at a fixed set of its own pixels p (the share of
    pixels where the blurred reference has its strongest gradient): the reference, sampled where
    the frame's homography sends p, must match the frame there up to a gain and an offset,
    ``ref(H_k p) = gain_k frame_k(p) + offset_k``. Only the reference is ever interpolated (a
    cubic B-spline), and the frames are read at the points alone, so a fit costs in proportion
    to the number of points, not to the number of frame pixels.

    The reference's gradient is the exact derivative of its interpolant (B-spline coefficients of
    the Fourier derivative, fetched with the value), so the Gauss-Newton steps converge in about
    one step; an earlier bilinear gradient of central differences converged only linearly. The
    first steps use a few of the points (``coarse``), so the full set usually needs one
    evaluation. The warp update is parametrised in normalised coordinates (centred, half-size 1)
    so that the normal equations stay well conditioned for every model.
    """

    huber = 1.345  # Huber's constant: 95% efficiency on Gaussian residuals
    tile_ratio = 4.0  # a tile this many times worse than the median tile does not match

    def __init__(self, coefficients: Tensor, samples: Tensor, points: Tensor, margin: int):
        """``coefficients`` (3, H, W): B-spline coefficients of the blurred reference and of its
        exact d/du and d/dv (:func:`_reference_splines`); ``samples`` (F, N): the blurred frames
        at ``points`` (N, 2), (u, v) integer pixel coordinates in float64."""
        H, W = coefficients.shape[-2:]
        self.H, self.W, self.margin, self.dtype = H, W, margin, coefficients.dtype
        self.coefficients = coefficients
        self.scale = max(H, W) / 2.0
        self.norm, self.norm_inv, self.eye3, self.corners_h, self.centre_h = _frame_constants(H, W)
        self._set_points(samples, points)
        # The first step of a fit only has to get near the solution: on large point sets it
        # is taken on every few points (at most COARSE_POINTS, plain least squares), and the
        # full, robust set then usually converges in one evaluation.
        step = len(points) // COARSE_POINTS
        self.coarse = None
        if step >= 2:
            self.coarse = copy.copy(self)
            self.coarse._set_points(samples[:, ::step], points[::step])

    def _set_points(self, samples: Tensor, points: Tensor) -> None:
        """What depends on the compared points (everything else is shared with ``coarse``)."""
        self.samples, self.points = samples, points
        self.points_h = torch.cat((points, torch.ones(len(points), 1, dtype=torch.float64)), -1)  # (N, 3)
        u, v = points[:, 0], points[:, 1]
        self.xy = ((u - (self.W - 1) / 2) / self.scale, (v - (self.H - 1) / 2) / self.scale)
        self._jacobian: dict[str, tuple[Tensor, Tensor]] = {}
        self._score_cache: tuple | None = None
        # 8 x 8 tiles over the frame, for the mismatch (occlusion) measure.
        self.n_tiles = 64
        self.tile_index = ((v * 8 / self.H).long() * 8 + (u * 8 / self.W).long())[None]

    def jacobian(self, model: str) -> tuple[Tensor, Tensor]:
        """d(x', y')/dp of the update warp at the points, two (N, k) tensors (normalised units)."""
        if model not in self._jacobian:
            jx, jy = _warp_jacobian(*self.xy, model)
            self._jacobian[model] = (torch.stack(jx, -1).to(self.dtype), torch.stack(jy, -1).to(self.dtype))
        return self._jacobian[model]

    def steepest(self, slope: Tensor, model: str) -> Tensor:
        """Steepest-descent images (F, N, k): minus d residual / d parameters."""
        if model == "translation":  # the warp's Jacobian is the identity
            return slope
        jx, jy = self.jacobian(model)
        return slope[..., :1] * jx + slope[..., 1:] * jy

    def residual(self, homographies: Tensor, samples: Tensor, keep: Tensor | None = None, robust: bool = True):
        """Aligned difference at the points, with robust weights, for the frames given.

        Each frame gets its own gain and offset (weighted least squares against the reference,
        refitted with the robust weights), so that exposure changes and an occluder that shifts
        the frame's mean do not leak into the motion.

        Returns
        -------
        r : Tensor, shape (F, N)
            gain * frame + offset - reference, 0 where not compared.
        mask : Tensor, shape (F, N), bool
            Points that land well inside the reference (and are in ``keep``, if given).
        w : Tensor, shape (F, N)
            Huber weights (0 where not compared).
        sigma : Tensor, shape (F,), or None
            Robust scale of r (None, and plain least-squares weights, if not ``robust``).
        slope : Tensor, shape (F, N, 2)
            Change of the reference value at the point per unit of frame motion (normalised
            units) along x and y: r changes by minus this.
        target : Tensor, shape (F, N)
            The reference at the points, through each frame's homography.
        """
        qh = homographies @ self.points_h.T  # (F, 3, N) float64
        q = (qh[:, :2] / qh[:, 2:]).mT.contiguous()  # (F, N, 2)
        u, v = q[..., 0], q[..., 1]
        m = self.margin
        mask = (u >= m) & (u <= self.W - 1 - m) & (v >= m) & (v <= self.H - 1 - m)
        if keep is not None:
            mask = mask & keep
        values = _spline_fetch(self.coefficients, q)  # value, d/du, d/dv: (3, F, N)
        target, t_uv = values[0], values[1:]
        w = mask.to(self.dtype)
        r = self._photometric(samples, target, w) * w
        sigma = None
        if robust:
            w, sigma = self._huber(r, mask)
            r = self._photometric(samples, target, w) * mask  # again, with an occluder's points down-weighted
            w, _ = self._huber(r, mask, sigma)
        # The reference's gradient at q, through dq/dp of the homography (the motion is a change
        # of p), times the normalised unit: how fast the reference value at q changes. dq/dp is
        # (H[i, j] - q_i H[2, j]) / (H[2] . [p, 1]); it is taken at the frame's centre: for a
        # scan's nearly affine motions it changes by at most 1.2e-4 of itself out to the corners
        # (the plan's homographies, full 960 x 1280 frame; 5e-5 on a 512^2 ROI).
        c = homographies @ self.centre_h  # (F, 3)
        jac = (homographies[:, :2, :2] - (c[:, :2, None] / c[:, 2:, None]) * homographies[:, 2:, :2])
        jac = jac * (self.scale / c[:, 2, None, None])
        slope = t_uv.permute(1, 2, 0) @ jac.to(self.dtype)
        return r, mask, w, sigma, slope, target

    def _photometric(self, values: Tensor, target: Tensor, w: Tensor) -> Tensor:
        """gain * values + offset - target, gain and offset fitted by weighted least squares."""
        sw = w.sum(-1).clamp_min(1e-12)
        wx = w * values
        mx, mt = wx.sum(-1) / sw, (w * target).sum(-1) / sw
        # Weighted (co)variances from the raw sums: the frames are normalised to unit spread, so
        # nothing cancels badly.
        var = (wx * values).sum(-1) - sw * mx * mx
        cov = (wx * target).sum(-1) - sw * mx * mt
        gain = torch.where(var > 1e-12, cov / var.clamp_min(1e-12), 1.0)
        return gain[:, None] * (values - mx[:, None]) + (mt[:, None] - target)

    def _huber(self, r: Tensor, mask: Tensor, sigma: Tensor | None = None) -> tuple[Tensor, Tensor]:
        if sigma is None:
            sigma = _robust_scale(r, mask)
        # Huber weights min(1, c sigma / |r|), 0 where not compared.
        w = ((self.huber * sigma[:, None]) / r.abs()).clamp_max(1.0) * mask
        return w, sigma

    def first_step(self, init: Tensor, samples: Tensor, model: str) -> Tensor:
        """One plain (not robust) Gauss-Newton step from ``init`` (F, 3, 3) on these (few)
        points; frames whose step is not finite or over 2 px stay where they were."""
        r, _, w, _, slope, _ = self.residual(init, samples, robust=False)
        sd = self.steepest(slope, model)
        hess, grad = _normal_equations(w, sd, r)
        dp = torch.linalg.solve(hess + 1e-12 * torch.eye(sd.shape[-1], dtype=torch.float64), grad)
        move = self.motion_px(dp, model)
        good = torch.isfinite(move) & (move <= 2.0)
        return torch.where(good[:, None, None], self.compose(init, dp.nan_to_num(0.0), model), init)

    def compose(self, homographies: Tensor, dp: Tensor, model: str) -> Tensor:
        """Forward composition H <- H W(dp), W in normalised coordinates; (F, 3, 3), (F, k)."""
        upd = homographies @ (self.update_basis(model) @ dp.T).permute(2, 0, 1).add_(self.eye3)
        return upd / upd[:, 2:3, 2:3]

    def update_basis(self, model: str) -> Tensor:
        """(3, 3, k): the warp update W(dp) = I + basis @ dp in pixel coordinates (the parameters
        are normalised: W is conjugated by the normaliser)."""
        return _update_basis(self.H, self.W, model)

    def corner_distance(self, a: Tensor, b: Tensor) -> Tensor:
        """Largest distance (px) between where homographies a and b (F, 3, 3) send the frame's
        corners, (F,)."""
        qa, qb = self.corners_h @ a.mT, self.corners_h @ b.mT  # (F, 4, 3)
        return (qa[..., :2] / qa[..., 2:] - qb[..., :2] / qb[..., 2:]).norm(dim=-1).amax(-1)

    def motion_px(self, dp: Tensor, model: str) -> Tensor:
        """Largest displacement (px) a small parameter step causes at the frame's corners, (F,)."""
        moves = _corner_jacobian(self.H, self.W, model) @ dp.T  # (8, F): dx at the 4 corners, then dy
        return torch.hypot(moves[:4], moves[4:]).amax(0)

    def fit(self, init: Tensor, model: str, iterations: int, tol: float,
            frames: Tensor | None = None, keep: Tensor | None = None) -> _Fit:
        """Refine ``init`` (F, 3, 3) so that the reference, sampled through each frame's
        homography, matches the frame.

        ``frames`` (F,) long, optional, picks the frames that ``init`` belongs to (default: all);
        ``keep`` (F, N) bool, optional, leaves out points (for example an occluded region).
        """
        samples = self.samples if frames is None else self.samples[frames]
        F, N = samples.shape
        k = N_PARAMS[model]
        eye = 1e-12 * torch.eye(k, dtype=torch.float64)
        Hk = init.clone()
        if self.coarse is not None and keep is None:
            Hk = self.coarse.first_step(Hk, self.coarse.samples if frames is None else self.coarse.samples[frames], model)
        converged = torch.zeros(F, dtype=torch.bool)
        # A frame whose step exceeds 2 px, or that wanders over 3 px from its start, has no basin
        # to converge in: it is left where it is (and flagged by the caller).
        diverged = torch.zeros(F, dtype=torch.bool)
        # Each frame's residual at its last evaluation; a converged frame moved less than
        # ``tol`` since (its last, small step is applied), so these are its statistics:
        # [r, mask, w, sigma, slope, target, normal matrix], each with the frames first.
        last: list[Tensor] = []
        from hbis_torch.progress import progress

        for _ in progress(range(iterations), desc=f"registration ({model})", unit="it"):
            todo = ~(converged | diverged)
            everyone = bool(todo.all())
            active = slice(None) if everyone else todo.nonzero()[:, 0]
            found = list(self.residual(Hk[active], samples[active], None if keep is None else keep[active]))
            ra, wa, ga = found[0], found[2], found[4]
            sd = self.steepest(ga, model)
            hess, grad = _normal_equations(wa, sd, ra)
            found.append(hess)
            if everyone:
                last = found
            else:
                for full, part in zip(last, found):
                    full[active] = part
            dp = torch.linalg.solve(hess + eye, grad)
            Hk[active] = self.compose(Hk[active], dp, model)
            move = self.motion_px(dp, model)
            converged[active] = move < tol
            wandered = self.corner_distance(Hk[active], init[active])
            diverged[active] = ~torch.isfinite(move) | (move > 2.0) | (wandered > 3.0)
            if bool((converged | diverged).all()):
                break
        r, mask, w, sigma, slope, target, hess = last
        n_valid = mask.sum(-1).double()
        r, w, sigma = r.double(), w.double(), sigma.double()
        rss = (w * r * r).sum(-1)
        # Noise-limited covariance: the robust scale, not the RSS, so that an occluder shows up
        # as a mismatch and not as a loss of precision.
        cov = torch.linalg.inv(hess + eye) * (sigma * sigma)[:, None, None]
        fraction, points = self.mismatch(r, mask)
        return _Fit(Hk, r, w, slope, rss, n_valid, fraction, points, cov, converged, sigma,
                    _correlation(samples, target, mask))

    def mismatch(self, r: Tensor, mask: Tensor) -> tuple[Tensor, Tensor]:
        """Points in tiles whose mean |residual| is far above the frame's typical tile.

        An occluder or a moving object is coherent in space, whereas the aliasing that differs
        between shifted frames is spread thinly over every edge. Returns the share of compared
        points in such tiles (F,) and the points themselves (F, N) bool.
        """
        F = r.shape[0]
        tiles = self.tile_index.expand(F, -1)
        count = torch.zeros(F, self.n_tiles, dtype=r.dtype).scatter_add_(1, tiles, mask.to(r.dtype))
        total = torch.zeros(F, self.n_tiles, dtype=r.dtype).scatter_add_(1, tiles, r.abs())
        used = count >= 8
        mean = torch.where(used, total / count.clamp_min(1), torch.full_like(total, float("nan")))
        typical = torch.nanmedian(mean, dim=1).values.nan_to_num(0.0)
        bad = used & (mean > self.tile_ratio * typical[:, None])
        if not bool(bad.any()):  # the usual case
            return torch.zeros(F, dtype=r.dtype), torch.zeros_like(mask)
        fraction = (count * bad).sum(1) / count.sum(1).clamp_min(1)
        # The points to leave out: bad tiles and their neighbours (an occluder's edge rarely
        # follows the tiles).
        grown = torch.nn.functional.max_pool2d(bad.reshape(F, 1, 8, 8).to(r.dtype), 3, 1, 1)
        return fraction, grown.reshape(F, -1).bool().gather(1, tiles) & mask

    def score_test(self, fit: _Fit, model: str, base: str, corr_area: float, use: Tensor) -> tuple[float, float]:
        """What one Gauss-Newton step of a richer ``model`` would gain over one of ``base``, the
        model of ``fit``, from ``fit``'s last evaluation.

        Both steps are taken, so that what is left of ``base``'s own convergence (less than the
        fit's tolerance) is not counted for the richer model.

        Returns (BIC gain summed over the frames in ``use`` (F,) bool, largest extra motion in px
        over them); the gain is compared with the extra parameters' penalty by the caller.
        """
        # Every model's warp is a linear map of the homography's parameters: one set of normal
        # equations serves every model tested against the same fit.
        def step(m: str) -> tuple[Tensor, Tensor]:
            """The step as homography parameters (F, 8), and the drop of the RSS it brings (F,)."""
            embed = _EMBEDDING[m]
            grad = grad8 @ embed
            dp = torch.linalg.solve(embed.T @ hess8 @ embed + 1e-12 * torch.eye(embed.shape[1], dtype=torch.float64), grad)
            return dp @ embed.T, (dp * grad).sum(-1).clamp_min(0)

        if self._score_cache is None or self._score_cache[0] is not fit or self._score_cache[1] != base:
            sd = self.steepest(fit.slope, "homography")
            hess8, grad8 = _normal_equations(fit.weights.to(sd.dtype), sd, fit.residual.to(sd.dtype))
            self._score_cache = (fit, base, hess8, grad8, step(base))
        _, _, hess8, grad8, (simple, drop_simple) = self._score_cache
        rich, drop = step(model)
        n_eff = (fit.n_valid / corr_area).clamp_min(1.0)
        gain = n_eff * torch.log((fit.rss - drop_simple).clamp_min(1e-300) / (fit.rss - drop).clamp_min(1e-300))
        return float(gain[use].sum()), float(self.motion_px(rich - simple, "homography")[use].max())


def _merge(fit: _Fit, part: _Fit, index: Tensor) -> _Fit:
    """``fit`` with the frames ``index`` replaced by those of ``part`` (fitted on them alone)."""
    out = _Fit(**{name: getattr(fit, name).clone() for name in fit.__dataclass_fields__})
    for name in fit.__dataclass_fields__:
        getattr(out, name)[index] = getattr(part, name)
    return out


def _correlation(a: Tensor, b: Tensor, mask: Tensor) -> Tensor:
    """Pearson correlation of a and b (F, N) over the points in ``mask`` (F, N), (F,) float64."""
    m = mask.double()
    n = m.sum(-1).clamp_min(1)
    a, b = a.double(), b.double()
    da = (a - (a * m).sum(-1, keepdim=True) / n[:, None]) * m
    db = (b - (b * m).sum(-1, keepdim=True) / n[:, None]) * m
    den = ((da * da).sum(-1) * (db * db).sum(-1)).sqrt()
    return torch.where(den > 0, (da * db).sum(-1) / den.clamp_min(1e-300), torch.zeros_like(den))


def _normal_equations(w: Tensor, sd: Tensor, r: Tensor) -> tuple[Tensor, Tensor]:
    """J^T W J (F, k, k) and J^T W r (F, k) for every frame, from one batched product, float64:
    weights (F, N), steepest-descent images (F, N, k), residuals (F, N). (Summed in the inputs'
    precision: float32 sums of a few thousand terms are good to 1e-6, far below what the motion
    needs.)"""
    k = sd.shape[-1]
    both = torch.cat((sd, r[..., None]), -1)  # (F, N, k + 1)
    product = ((w[..., None] * both).mT @ sd).double()  # (F, k + 1, k)
    return product[:, :k], product[:, k]


def _robust_scale(r: Tensor, mask: Tensor) -> Tensor:
    """Per-frame residual scale 1.4826 * median |r| over the compared pixels, (F,)."""
    # Every other point is plenty for a median, at half the cost.
    r, mask = r[:, ::2], mask[:, ::2]
    vals = torch.where(mask, r.abs(), torch.full_like(r, float("nan")))
    mad = torch.nanmedian(vals, dim=-1).values
    return (1.4826 * mad).nan_to_num(1.0).clamp_min(1e-12)


def _strongest_points(strength: Tensor, margin: int, keep_fraction: float, max_points: int) -> Tensor:
    """Flat indices (N,), sorted, of pixels where ``strength`` (H, W) is high, at least
    ``margin`` px from the border: those above the (1 - ``keep_fraction``) quantile of the inner
    pixels (at least 64), thinned evenly to at most ``max_points``.

    Thinning a large strong set, rather than taking only the very strongest pixels, keeps the
    set's mix: on fine, aliased bars the strongest pixels are exactly those where the shifted
    frames disagree most. The quantile is read from a subsample of about 4k inner pixels.
    """
    H, W = strength.shape
    inner = strength[margin:H - margin, margin:W - margin]
    h, w = inner.shape
    values = inner.reshape(-1)
    n_keep = min(h * w, max(64, int(keep_fraction * h * w)))
    sub = values[::max(1, values.numel() // 4096)]
    threshold = torch.kthvalue(sub, max(1, min(len(sub), int(round(len(sub) * (1 - n_keep / (h * w))))))).values
    local = (values >= threshold).nonzero()[:, 0]
    if len(local) < min(64, h * w):
        local = torch.topk(values, min(64, h * w)).indices.sort().values
    if len(local) > max_points:
        local = local[torch.linspace(0, len(local) - 1, max_points).round().long()]
    return (local // w + margin) * W + local % w + margin
