"""Many straight edges' slanted-edge fits at once (:mod:`hbis_torch.reconstruct.lens_blur`'s model).

Each edge's samples are fitted with

    value(p) = c0 + c1 * E(n . p - t),   n = (cos theta, sin theta),

``E`` the step through the pixel's area and a Gaussian lens of standard deviation sigma
(:func:`profile`), for the parameters (c0, c1, t, theta, sigma) within bounds, by the robust
least squares that ``scipy.optimize.least_squares(loss="soft_l1", f_scale=3)`` solves: the
residuals in noise units ``r`` weigh in as ``2 C^2 (sqrt(1 + r^2 / C^2) - 1)`` (C =
:data:`F_SCALE`), near ``r^2`` for the noise and growing as ``|r|`` for outliers.

All edges are solved together, in float64 tensors of shape (edges, samples), by one
Levenberg-Marquardt: each edge's step is the Gauss-Newton step of its robust cost (the Hessian's
samples weighed by the loss's rho'(z) + 2 z rho''(z), as scipy's does), damped by its own factor
(Marquardt's scaling, Nielsen's update of the factor), kept where it lowers that edge's cost; a
parameter on its bound whose gradient points out is held there. The Jacobian is exact, theta's
column included (the pixel's footprint on the normal turns with theta): where sigma is barely
pinned (a fit near the pixel's own width), the minimum is then one point, not wherever a step
stalls. Against one ``least_squares`` call per edge (the fit this replaced), the accepted edges'
sigmas agree to 1e-3 LR px and the same edges are accepted (tests/test_edge_fit.py); that loop
cost several times as much, most of it Python per call, and importing scipy.optimize a third of
a second more.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

F_SCALE = 3.0
"""The soft-L1 loss's scale (noise units): residuals beyond it count less than squared."""
MAX_ITERATIONS = 100
"""Levenberg-Marquardt steps at most (a dozen on average on the bursts tried; a few edges take many)."""
COST_TOLERANCE = 1e-10
"""An edge is done when a step lowers its cost by less than this share of it ..."""
STEP_TOLERANCE = 1e-9
"""... or moves no parameter by more than this share of its scale (:data:`SCALES`)."""
DAMPING = 1.0
"""The damping factor each edge starts from (Marquardt's scaling: a share of the Hessian's diagonal)."""
SCALES = (0.1, 0.1, 0.1, 0.05, 0.1)
"""The parameters' typical scales (c0, c1 in the units of frames in [0, 1]; t, sigma LR px;
theta radians)."""


def profile(d: Tensor, theta: Tensor, sigma: Tensor, aperture: float, derivatives: bool = True) -> Tensor:
    """A pixel's response to a unit step at signed distance ``d`` (LR px), and its derivatives.

    The step, blurred by the Gaussian lens, averaged over the pixel's area: along the edge's
    normal the area is two boxes, of widths a = aperture x abs(cos theta) and b = aperture x
    abs(sin theta), so the average is four terms of the blurred step's second antiderivative
    F2(x) = ((x^2 + sigma^2) Phi(x / sigma) + x sigma phi(x / sigma)) / 2 = (x F1 + sigma^2 Phi) / 2,
    where F1 = x Phi + sigma phi is its derivative in x and sigma Phi its derivative in sigma.

    Parameters
    ----------
    d : Tensor, float64
        Distance of the pixel's centre from the edge along its normal, LR px.
    theta, sigma : Tensor, float64
        The normal's angle to the pixel's x axis (radians) and the lens's standard deviation
        (LR px, > 0), broadcast against ``d`` (shape (E, 1) for E edges' rows of samples).
    aperture : float
        The pixel's sensitive side, LR px.
    derivatives : bool
        Also the derivatives.

    Returns
    -------
    Tensor, shape (4,) + d's shape (``derivatives``) or d's shape
        The response (in [0, 1], 1 far on the side d > 0), then its derivatives in ``d``, in
        ``sigma`` and in ``theta`` through the pixel's footprint (a and b) at a fixed ``d``.
    """
    cos, sin = theta.cos(), theta.sin()
    a, b = (aperture * cos.abs()).clamp(min=1e-2), (aperture * sin.abs()).clamp(min=1e-2)
    da = torch.where(aperture * cos.abs() > 1e-2, -aperture * cos.sign() * sin, 0.0)  # a's derivative in theta
    db = torch.where(aperture * sin.abs() > 1e-2, aperture * sin.sign() * cos, 0.0)
    cdfs, f1s, x_f1s, f1_shifts = (torch.zeros_like(d) for _ in range(4))
    spread, inverse = sigma / math.sqrt(2 * math.pi), 1 / sigma
    for sa, sb in ((1, 1), (1, -1), (-1, 1), (-1, -1)):  # the shifts (sa a + sb b) / 2, of sign sa sb
        x = d + (sa * a + sb * b) / 2
        z = x * inverse
        cdf = torch.special.ndtr(z)
        f1 = torch.exp(z.square_().mul_(-0.5)).mul_(spread).addcmul_(x, cdf)  # x Phi + sigma phi
        sign = sa * sb
        cdfs.add_(cdf, alpha=sign)
        f1s.add_(f1, alpha=sign)
        x_f1s.addcmul_(x, f1, value=sign)
        if derivatives:
            f1_shifts.addcmul_(f1, sign * (sa * da + sb * db) / 2)
    area = a * b
    f2 = x_f1s.addcmul_(cdfs, sigma * sigma).mul_(0.5 / area)
    if not derivatives:
        return f2
    return torch.stack([f2, f1s.div_(area), cdfs.mul_(sigma / area), f1_shifts.div_(area).sub_(f2 * (da / a + db / b))])


def _model(q: Tensor, xy: Tensor, values: Tensor, scale: Tensor, aperture: float) -> tuple[Tensor, Tensor]:
    """The residuals (E, N) in noise units and their Jacobian (E, 5, N) at parameters ``q`` (E, 5);
    ``scale``: 1 / noise at the samples, 0 at the padding. Theta moves d and the pixel's footprint
    on the normal."""
    c0, c1, t, theta, sigma = q.T[..., None]
    cos, sin = theta.cos(), theta.sin()
    x, y = xy.unbind(1)
    e, e_d, e_s, e_theta = profile(x * cos + y * sin - t, theta, sigma, aperture)
    c1_scale = c1 * scale
    jacobian = torch.stack([scale, e * scale, -c1_scale * e_d, c1_scale * (e_d * (y * cos - x * sin) + e_theta),
                            c1_scale * e_s], 1)
    return (e * c1 + c0 - values) * scale, jacobian


def _cost(r: Tensor) -> Tensor:
    """Each edge's soft-L1 cost (E,) of its residuals (E, N)."""
    return 2 * F_SCALE**2 * (torch.sqrt(1 + (r / F_SCALE) ** 2) - 1).sum(1)


def fit_edges(xy: Tensor, values: Tensor, valid: Tensor, start: Tensor, lower: Tensor, upper: Tensor,
              noise: float, aperture: float) -> tuple[Tensor, Tensor, Tensor]:
    """Fit E edges' samples at once (module docstring).

    Parameters
    ----------
    xy : Tensor, shape (E, 2, N), float64
        Each sample's position (x, y) relative to its edge's point, LR px (the padding: anything
        finite).
    values : Tensor, shape (E, N), float64
        The samples' values.
    valid : Tensor, shape (E, N), bool
        Which samples are real (the rest pad the edges to N).
    start, lower, upper : Tensor, shape (E, 5), float64
        The parameters (c0, c1, t, theta, sigma) to start from and their bounds (infinite: none).
    noise : float
        The samples' noise standard deviation (values' units).
    aperture : float
        The pixel's sensitive side, LR px.

    Returns
    -------
    q : Tensor, shape (E, 5)
        The fitted parameters.
    rms : Tensor, shape (E,)
        The RMS residual at ``q``, noise units.
    sigma_error : Tensor, shape (E,)
        Sigma's standard error, LR px: from the Jacobian at ``q``, times ``max(rms, 1)``
        (infinite where the Jacobian is singular).
    """
    scale = valid / noise
    eye, tolerance = torch.eye(5, dtype=torch.float64), STEP_TOLERANCE * torch.tensor(SCALES, dtype=torch.float64)
    q = torch.maximum(torch.minimum(start, upper), lower)
    r, jac = _model(q, xy, values, scale, aperture)
    cost = _cost(r)
    damping, growth = torch.full_like(cost, DAMPING), torch.full_like(cost, 2.0)
    todo = torch.arange(len(q))
    for _ in range(MAX_ITERATIONS):
        if len(todo) == 0:
            break
        rows = slice(None) if len(todo) == len(q) else todo  # every edge: views, not copies
        qt, rt, jt, lo, hi, before = q[rows].clone(), r[rows], jac[rows], lower[rows], upper[rows], cost[rows].clone()
        slope = 1 / torch.sqrt(1 + (rt / F_SCALE) ** 2)  # the loss's rho'(z), z = r^2 / C^2
        gradient = (jt @ (slope * rt)[..., None])[..., 0]
        hessian = (jt * slope[:, None, :] ** 3) @ jt.transpose(1, 2)  # rho' + 2 z rho'' = rho'^3
        held = ((qt <= lo) & (gradient > 0)) | ((qt >= hi) & (gradient < 0))
        gradient = gradient.masked_fill(held, 0.0)
        system = hessian + damping[rows, None, None] * hessian.diagonal(dim1=1, dim2=2).clamp(min=1e-300)[:, None] * eye
        system = torch.where(held[:, :, None] | held[:, None, :], eye, system)
        step = -torch.linalg.solve_ex(system, gradient)[0]  # a singular system: a step that fails
        trial = torch.maximum(torch.minimum(qt + step, hi), lo)
        step = trial - qt
        r_new, jac_new = _model(trial, xy[rows], values[rows], scale[rows], aperture)
        after = _cost(r_new)
        better = after < before
        gain = (before - after) / -(2 * (gradient * step).sum(1) + (step * (hessian @ step[..., None])[..., 0]).sum(1))
        done = (step.abs() <= tolerance).all(1) | (better & (before - after <= COST_TOLERANCE * before))
        kept = todo[better]
        q[kept], r[kept], jac[kept], cost[kept] = trial[better], r_new[better], jac_new[better], after[better]
        # Nielsen: a step that gained as predicted lowers the damping, a failed one raises it faster each time
        damping[todo] = torch.where(better, damping[todo] * (1 - (2 * gain - 1) ** 3).clamp(min=1 / 3),
                                    damping[todo] * growth[todo])
        growth[todo] = torch.where(better, 2.0, growth[todo] * 2)
        todo = todo[~done & (damping[todo] < 1e16)]
    rms = torch.sqrt((r * r).sum(1) / valid.sum(1).clamp(min=1))
    inverse, info = torch.linalg.inv_ex(jac @ jac.transpose(1, 2))
    error = inverse[:, 4, 4].clamp(min=0).sqrt() * rms.clamp(min=1)
    return q, rms, torch.where(info == 0, error, torch.inf)
