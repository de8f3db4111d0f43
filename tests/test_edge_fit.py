"""The lens estimate's edges fitted all at once (hbis_torch/reconstruct/edge_fit.py) against one
scipy.optimize.least_squares per edge, the fit it replaced, on the same samples."""

import math
import sys

import numpy as np
import pytest
import torch

from hbis_torch.reconstruct import lens_blur
from hbis_torch.reconstruct.edge_fit import _model, profile


def _edge(rng, sigma: float, second: bool = False):
    """One edge's samples as the burst gives them: ~650 positions in the window around the edge
    point (a dozen frames at sub-pixel offsets), a step through a pixel and a Gaussian lens, noise
    of 0.01, a few outliers; ``second``: a parallel edge in the window too (a fit to refuse)."""
    theta = rng.uniform(-math.pi, math.pi)
    normal, along = np.array([math.cos(theta), math.sin(theta)]), np.array([-math.sin(theta), math.cos(theta)])
    across_px, along_px = rng.uniform(-3.5, 3.5, 650), rng.uniform(-4, 4, 650)
    xy = across_px[:, None] * normal + along_px[:, None] * along
    t = rng.uniform(-0.4, 0.4)
    unit = lambda d: profile(torch.from_numpy(d), torch.tensor(theta), torch.tensor(sigma), 1.0, derivatives=False).numpy()
    values = 0.2 + 0.5 * unit(xy @ normal - t) + rng.normal(0, 0.01, 650)
    if second:
        values -= 0.3 * unit(xy @ normal - t - 1.6)
    stray = rng.random(650) < 0.02  # a few samples misregistered
    values[stray] += rng.normal(0.1, 0.2, stray.sum())
    return xy, values, theta + rng.normal(0, 0.05)  # the normal's angle from the structure tensor is a guess


def _scipy_fit(xy, values, theta0, noise, aperture=1.0):
    """The fit edge_fit replaced, as it was: one least_squares per edge (soft-L1, bounds, the
    footprint's term left out of theta's Jacobian)."""
    from scipy.optimize import least_squares

    proj = xy @ np.array([math.cos(theta0), math.sin(theta0)])
    lo, hi = float(np.median(values[proj < -1.5])), float(np.median(values[proj > 1.5]))

    def model(q):
        c0, c1, t, th, sigma = q
        normal = np.array([math.cos(th), math.sin(th)])
        d = torch.from_numpy(xy @ normal - t)
        e, e_d, e_s, _ = profile(d, torch.tensor(th), torch.tensor(sigma), aperture).numpy()
        return e, e_d, e_s, normal

    def residual(q):
        return (q[0] + q[1] * model(q)[0] - values) / noise

    def jacobian(q):
        e, e_d, e_s, normal = model(q)
        across = xy @ np.array([-normal[1], normal[0]])
        return np.stack([np.ones_like(e), e, -q[1] * e_d, q[1] * e_d * across, q[1] * e_s], axis=1) / noise

    fit = least_squares(residual, [lo, hi - lo, 0.0, theta0, 0.4], jac=jacobian,
                        bounds=([-np.inf, -np.inf, -2, theta0 - 0.5, 0.02], [np.inf, np.inf, 2, theta0 + 0.5, 3.0]),
                        loss="soft_l1", f_scale=3.0, x_scale=[0.1, 0.1, 0.1, 0.05, 0.1], max_nfev=40)
    if abs(fit.x[2]) > 1.5:
        return None
    J = jacobian(fit.x)
    r = residual(fit.x)
    rms = float(np.sqrt(np.mean(r * r)))
    return float(fit.x[4]), math.sqrt(max(np.linalg.inv(J.T @ J)[4, 4], 0.0)) * max(rms, 1.0), float(fit.x[1]), rms


def _accepted(fit, noise):
    if fit is None:
        return False
    _, error, c1, rms = fit
    contrast = abs(c1) / noise
    return (error < lens_blur.MAX_SIGMA_ERROR and contrast > lens_blur.MIN_CONTRAST_NOISE
            and rms < lens_blur.MAX_RESIDUAL_NOISE + lens_blur.MAX_RESIDUAL_STEP * contrast)


def test_the_batch_fit_agrees_with_one_least_squares_per_edge(monkeypatch):
    """Same accepted edges, sigmas within 1e-3 LR px (flat minima, where scipy stops early, differ
    most), on clean edges of every sharpness and on edges with a second one in the window; and
    scipy.optimize is never imported (it cost a third of a second)."""
    pytest.importorskip("scipy.optimize")
    rng = np.random.default_rng(3)
    edges = [_edge(rng, sigma) for sigma in np.linspace(0.05, 0.9, 24)] + [_edge(rng, 0.3, second=True) for _ in range(6)]
    noise = 0.01
    expected = [_scipy_fit(xy, values, theta, noise) for xy, values, theta in edges]
    monkeypatch.setitem(sys.modules, "scipy.optimize", None)  # importing it now fails
    found = lens_blur._fit_edges([(xy, values) for xy, values, _ in edges], [theta for *_, theta in edges], noise, 1.0)
    decisions = [(_accepted(a, noise), _accepted(b, noise)) for a, b in zip(expected, found)]
    assert all(a == b for a, b in decisions), decisions
    assert sum(a for a, _ in decisions) >= 20 and not all(a for a, _ in decisions[-6:])  # both kinds were tried
    for a, b in zip(expected, found):
        if _accepted(a, noise):
            assert abs(a[0] - b[0]) < 1e-3 and abs(a[1] - b[1]) < 0.1 * a[1], (a, b)


def test_an_edge_with_too_few_samples_on_a_side_is_not_fitted():
    rng = np.random.default_rng(0)
    xy, values, theta = _edge(rng, 0.3)
    side = xy @ np.array([math.cos(theta), math.sin(theta)]) > -1.0
    fits = lens_blur._fit_edges([(xy[side], values[side]), (xy, values), (xy[:30], values[:30])], [theta] * 3, 0.01, 1.0)
    assert fits[0] is None and fits[1] is not None and fits[2] is None


@pytest.mark.parametrize("theta", [0.3, -2.0, 1.2, 3.1])
def test_the_jacobian_is_the_model_s_derivative(theta):
    """Theta's column counts the pixel's footprint on the normal too (finite differences)."""
    gen = torch.Generator().manual_seed(0)
    xy = torch.rand(2, 2, 60, dtype=torch.float64, generator=gen) * 8 - 4
    values = torch.rand(2, 60, dtype=torch.float64, generator=gen)
    scale = torch.ones(2, 60, dtype=torch.float64)
    q = torch.tensor([[0.1, 0.5, 0.2, theta, 0.3], [0.3, -0.4, -0.1, theta + 0.1, 0.6]], dtype=torch.float64)
    _, jacobian = _model(q, xy, values, scale, 0.9)
    h = 1e-6
    numeric = torch.stack([(_model(q + h * step, xy, values, scale, 0.9)[0] - _model(q - h * step, xy, values, scale, 0.9)[0])
                           / (2 * h) for step in torch.eye(5, dtype=torch.float64)[:, None, :]], 1)
    torch.testing.assert_close(jacobian, numeric, atol=1e-6, rtol=1e-6)
