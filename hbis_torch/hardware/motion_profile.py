"""Trapezoidal velocity profiles: how long a move takes, and how far it has gone at time t.

A rough model of GRBL's planner for one isolated straight move (start and end at rest): accelerate
at ``accel`` up to ``speed``, cruise, decelerate. Used by the simulator to time its moves and by
the driver to size its move timeouts.
"""

from __future__ import annotations

import math


def move_duration_s(distance: float, speed: float, accel: float) -> float:
    """Time for a move of ``distance`` from rest to rest.

    Parameters
    ----------
    distance : float
        Path length (deg), >= 0.
    speed : float
        Cruise speed (deg/s), > 0.
    accel : float
        Acceleration (deg/s^2), > 0.
    """
    if distance <= 0:
        return 0.0
    if distance <= speed * speed / accel:  # never reaches cruise speed: a triangle
        return 2.0 * math.sqrt(distance / accel)
    return distance / speed + speed / accel


def distance_at(t: float, distance: float, speed: float, accel: float) -> float:
    """Path length covered ``t`` seconds into the move described by :func:`move_duration_s`."""
    total = move_duration_s(distance, speed, accel)
    if t <= 0 or total == 0:
        return 0.0
    if t >= total:
        return distance
    peak = min(speed, math.sqrt(distance * accel))
    t_ramp = peak / accel
    if t < t_ramp:
        return 0.5 * accel * t * t
    if t <= total - t_ramp:
        return 0.5 * accel * t_ramp * t_ramp + peak * (t - t_ramp)
    left = total - t
    return distance - 0.5 * accel * left * left


def axis_limited(direction: tuple[float, ...], limits: tuple[float, ...]) -> float:
    """Largest path rate (speed or acceleration) that keeps every axis within its own limit.

    ``direction`` is the move's unit vector, ``limits`` the per-axis maxima (GRBL's $110.. or $120..).
    """
    rate = math.inf
    for d, lim in zip(direction, limits):
        if abs(d) > 1e-12:
            rate = min(rate, lim / abs(d))
    return rate
