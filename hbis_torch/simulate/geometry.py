"""Where scene points fall on the sensor during a scan: landing maps and sample positions.

Coordinates: sensor pixels (u, v), 0-based pixel centres of the full sensor, unless a name says
"roi-local" (then minus (u0, v0)). Object-plane points are (x, y) in mm.

The *sample position* of pixel (u, v) of frame k is where the object point it sees lands on the
sensor at the reference phases (the output-grid convention of docs/data.md):

    q_k(u, v) = sensor_position(system, landing(u, v; phi_k), phi_ref)

Both maps are smooth over the sensor (the prisms add a slowly varying distortion to a pinhole),
so the fast paths trace exactly on a coarse grid of nodes and interpolate with separable
not-a-knot cubic splines; tests/test_simulate_parts.py bounds the error (< 1e-6 pixel).
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np
import torch
from torch import Tensor

from hbis_torch.checks import check_phases, check_roi
from hbis_torch.config import FoveaSystem
from hbis_torch.errors import HbisInputError
from hbis_torch.optics import exit_directions, land_on_plane, rays_at, sensor_position

Roi = tuple[int, int, int, int]


def landing_at(system: FoveaSystem, u: Tensor, v: Tensor, phi1_deg, phi2_deg) -> Tensor:
    """Exact landing points (mm) of the chief rays at fractional pixel positions.

    ``u``, ``v`` broadcast to (*R); phases broadcast to (*P) with trailing singleton dims for R.
    Returns (*P, *R, 2) in mm.
    """
    rays = rays_at(system.camera, u, v)
    directions = exit_directions(rays, phi1_deg, phi2_deg, system.prisms)
    return land_on_plane(directions, system.object_distance_mm)


def spline_basis(knots: np.ndarray, at: np.ndarray) -> Tensor:
    """(len(at), len(knots)) float64 matrix evaluating the not-a-knot cubic spline through values
    at ``knots`` (increasing) at the points ``at``. With fewer than 4 knots the interpolant is the
    polynomial through them."""
    from scipy.interpolate import CubicSpline

    knots = np.asarray(knots, dtype=np.float64)
    eye = np.eye(len(knots))
    if len(knots) == 1:
        return torch.ones(len(at), 1, dtype=torch.float64)
    if len(knots) < 4:
        coeffs = np.polyfit(knots, eye, len(knots) - 1)
        return torch.from_numpy(np.stack([np.polyval(c, at) for c in coeffs.T], axis=1))
    return torch.from_numpy(CubicSpline(knots, eye)(np.asarray(at, dtype=np.float64)))


@lru_cache(maxsize=256)
def _regular_basis(count_at: int, count_nodes: int) -> Tensor:
    """Spline basis from ``count_nodes`` nodes to ``count_at`` points, both spread evenly over the
    same interval (the matrix does not depend on where the interval is)."""
    return spline_basis(np.linspace(0.0, 1.0, count_nodes), np.linspace(0.0, 1.0, count_at))


def _nodes(lo: float, hi: float, step: float) -> np.ndarray:
    count = max(4, math.ceil((hi - lo) / step) + 1)
    return np.linspace(lo, hi, count)


def landing_on_grid(
    system: FoveaSystem,
    u: np.ndarray,
    v: np.ndarray,
    phi1_deg: float,
    phi2_deg: float,
    node_step: float = 8.0,
    origin_mm=(0.0, 0.0),
    dtype=torch.float64,
) -> Tensor:
    """Landing points (mm) at every (u[j], v[i]) of a regular product grid, (len(v), len(u), 2).

    ``u`` and ``v`` must be evenly spaced and increasing. Traced exactly (float64) on nodes every
    ``node_step`` pixels; what is interpolated is the landing minus its pinhole part, the prisms'
    smooth distortion. ``origin_mm`` is subtracted before the result is cast to ``dtype``, so a
    float32 result relative to a nearby origin keeps about 1e-7 of the distance to it. The
    result is a (non-contiguous) view of a (2, len(v), len(u)) tensor.
    """
    u = np.asarray(u, dtype=np.float64)
    v = np.asarray(v, dtype=np.float64)
    nu, nv = _nodes(u[0], u[-1], node_step), _nodes(v[0], v[-1], node_step)
    uu = torch.from_numpy(nu)[None, :]
    vv = torch.from_numpy(nv)[:, None]
    exact = landing_at(system, uu, vv, phi1_deg, phi2_deg) - _pinhole(system, uu, vv)
    # the prisms' part is a large constant (the deviation, mm) plus a small variation; only the
    # variation goes through the (possibly float32) spline, the constant stays in float64
    offset = exact.mean(dim=(0, 1))
    bu = _regular_basis(len(u), len(nu)).to(dtype)
    bv = _regular_basis(len(v), len(nv)).to(dtype)
    out = bv @ (exact - offset).movedim(-1, 0).to(dtype) @ bu.T  # (2, len(v), len(u))
    cam = system.camera
    scale = cam.pitch_mm * system.object_distance_mm / cam.focal_length_mm
    px = (u - (cam.cols - 1) / 2) * scale - float(origin_mm[0]) + float(offset[0])
    py = (v - (cam.rows - 1) / 2) * scale - float(origin_mm[1]) + float(offset[1])
    out[0] += torch.from_numpy(px).to(dtype)[None, :]
    out[1] += torch.from_numpy(py).to(dtype)[:, None]
    return out.movedim(0, -1)


def _pinhole(system: FoveaSystem, u: Tensor, v: Tensor) -> Tensor:
    cam = system.camera
    scale = cam.pitch_mm * system.object_distance_mm / cam.focal_length_mm
    u, v = torch.broadcast_tensors(u, v)
    return torch.stack(((u - (cam.cols - 1) / 2) * scale, (v - (cam.rows - 1) / 2) * scale), -1)


def sample_positions(
    system: FoveaSystem,
    phases_deg,
    reference_index: int,
    roi: Roi | None = None,
    exact: bool = False,
    node_step: float = 8.0,
    local: bool = True,
) -> Tensor:
    """Sample positions of every pixel of every frame on the reference frame's pixel grid.

    Parameters
    ----------
    system : FoveaSystem
    phases_deg : array-like, shape (F, 2)
        Phases of the frames, degrees.
    reference_index : int
        Frame whose phases define the output grid.
    roi : (u0, v0, width, height) or None
        Pixels of each frame (None: the whole sensor).
    exact : bool
        Trace every pixel (the contract's definition, slower) instead of interpolating exact
        node values with cubic splines (error < 1e-6 pixel).
    local : bool
        Return roi-local coordinates (minus (u0, v0)), as the contract states; False gives
        full-sensor pixel coordinates.

    Returns
    -------
    Tensor, shape (F, H, W, 2), float64
        (u, v) of each sample in reference-frame pixels.
    """
    phases = check_phases(phases_deg)
    if not 0 <= int(reference_index) < phases.shape[0]:
        raise HbisInputError(f"reference index {reference_index} is not a frame index (0..{phases.shape[0] - 1})")
    u0, v0, width, height = check_roi(system.camera, roi)
    ref = phases[int(reference_index)]
    u = np.arange(u0, u0 + width, dtype=np.float64)
    v = np.arange(v0, v0 + height, dtype=np.float64)
    if exact:
        uu, vv = torch.from_numpy(u)[None, :], torch.from_numpy(v)[:, None]
        grid_u, grid_v = uu, vv
    else:
        nu, nv = _nodes(u[0], u[-1], node_step), _nodes(v[0], v[-1], node_step)
        grid_u, grid_v = torch.from_numpy(nu)[None, :], torch.from_numpy(nv)[:, None]
    p1, p2 = phases[:, 0, None, None], phases[:, 1, None, None]
    landing = landing_at(system, grid_u, grid_v, p1, p2)  # (F, n_v, n_u, 2)
    positions = sensor_position(system, landing, ref[0], ref[1])
    if not exact:
        base = torch.stack(torch.broadcast_tensors(grid_u, grid_v), -1)
        shift = (positions - base).movedim(-1, 1)  # (F, 2, n_v, n_u): smooth displacement
        bu, bv = _regular_basis(len(u), len(nu)), _regular_basis(len(v), len(nv))
        shift = (bv @ shift @ bu.T).movedim(1, -1)
        uu, vv = torch.from_numpy(u)[None, :], torch.from_numpy(v)[:, None]
        positions = shift + torch.stack(torch.broadcast_tensors(uu, vv), -1)
    if local:
        positions = positions - torch.tensor([u0, v0], dtype=torch.float64)
    return positions
