"""The not-a-knot cubic spline as a matrix: what ``scipy.interpolate.CubicSpline(knots, eye)(at)`` gives.

The landing maps are traced exactly at a few nodes and interpolated by a not-a-knot cubic
spline between them (:mod:`hbis_torch.optics.pixels`, :mod:`hbis_torch.optics.sample_geometry`);
the spline is linear in the values at the nodes, so one matrix per node layout does it.
Importing ``scipy.interpolate`` costs about 0.7 s, half of ``import torch`` and more than a
small reconstruction's compute, for a few-by-few linear system; so the system is solved here,
with the equations of scipy's ``CubicSpline`` (the slopes at the knots, not-a-knot ends), and
tests/test_optics.py checks the matrix against scipy's to 1e-12.
"""

from __future__ import annotations

import numpy as np


def not_a_knot_basis(knots, at) -> np.ndarray:
    """(len(at), len(knots)) float64 matrix B such that ``B @ y`` is the not-a-knot cubic spline
    through ``(knots, y)`` evaluated at ``at`` (extrapolated by the end pieces outside the knots).

    Parameters
    ----------
    knots : array, shape (n,)
        Increasing; with n < 4 the interpolant is the polynomial of degree n - 1 through them
        (as scipy's, which also reduces to it).
    at : array, shape (m,)
        Where to evaluate.
    """
    x = np.asarray(knots, dtype=np.float64)
    at = np.asarray(at, dtype=np.float64)
    n = len(x)
    eye = np.eye(n)
    if n < 4:
        if n == 1:
            return np.ones((len(at), 1))
        coeffs = np.polyfit(x, eye, n - 1)
        return np.stack([np.polyval(c, at) for c in coeffs.T], axis=1)
    dx = np.diff(x)
    slope = np.diff(eye, axis=0) / dx[:, None]  # (n - 1, n): the chords' slopes for each unit value
    a = np.zeros((n, n))
    b = np.zeros((n, n))
    i = np.arange(1, n - 1)
    a[i, i - 1], a[i, i], a[i, i + 1] = dx[1:], 2 * (dx[:-1] + dx[1:]), dx[:-1]
    b[1:-1] = 3 * (dx[1:, None] * slope[:-1] + dx[:-1, None] * slope[1:])
    d = x[2] - x[0]  # not-a-knot at the start: the first two pieces are one cubic
    a[0, 0], a[0, 1] = dx[1], d
    b[0] = ((dx[0] + 2 * d) * dx[1] * slope[0] + dx[0] ** 2 * slope[1]) / d
    d = x[-1] - x[-3]  # and at the end
    a[-1, -1], a[-1, -2] = dx[-2], d
    b[-1] = (dx[-1] ** 2 * slope[-2] + (2 * d + dx[-1]) * dx[-2] * slope[-1]) / d
    s = np.linalg.solve(a, b)  # (n, n): the slope at each knot for each unit value
    piece = np.clip(np.searchsorted(x, at, side="right") - 1, 0, n - 2)
    h, u = dx[piece][:, None], (at - x[piece])[:, None]
    s0, s1, m = s[piece], s[piece + 1], slope[piece]
    c2 = (3 * m - 2 * s0 - s1) / h
    c3 = (s0 + s1 - 2 * m) / h**2
    return eye[piece] + u * (s0 + u * (c2 + u * c3))
