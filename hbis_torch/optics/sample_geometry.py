"""Where scene points fall on the sensor during a scan: landing maps and sample positions.

Coordinates: sensor pixels (u, v), 0-based pixel centres of the full sensor, unless a name says
"roi-local" (then minus (u0, v0)). Object-plane points are (x, y) in mm.

The *sample position* of pixel (u, v) of frame k is where the object point it sees lands on the
sensor at the reference phases (the output-grid convention of docs/data.md):

    q_k(u, v) = sensor_position(system, landing(u, v; phi_k), phi_ref)

Both maps are smooth over the sensor (the prisms add a slowly varying distortion to a pinhole),
so the fast paths trace exactly on a coarse grid of nodes and interpolate with separable
not-a-knot cubic splines; tests/test_simulate_parts.py bounds the error (< 1e-6 pixel; nodes
32 px apart for the sample positions, 8 px for the simulator's landing maps).
"""

from __future__ import annotations

import math
from functools import lru_cache
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

from hbis_torch.checks import check_phases, check_roi
from hbis_torch.config import FoveaSystem
from hbis_torch.errors import HbisInputError
from hbis_torch.optics.pixels import rays_at, sensor_position
from hbis_torch.optics.risley import exit_directions, land_on_plane

Roi = tuple[int, int, int, int]


def landing_at(system: FoveaSystem, u: Tensor, v: Tensor, phi1_deg, phi2_deg) -> Tensor:
    """Exact landing points (mm) of the chief rays at fractional pixel positions.

    ``u``, ``v`` broadcast to ``(*R)``; phases broadcast to ``(*P)`` with trailing singleton dims for R.
    Returns ``(*P, *R, 2)`` in mm.
    """
    rays = rays_at(system.camera, u, v)
    directions = exit_directions(rays, phi1_deg, phi2_deg, system.prisms)
    return land_on_plane(directions, system.object_distance_mm)


def spline_basis(knots: np.ndarray, at: np.ndarray) -> Tensor:
    """(len(at), len(knots)) float64 matrix evaluating the not-a-knot cubic spline through values
    at ``knots`` (increasing) at the points ``at``. With fewer than 4 knots the interpolant is the
    polynomial through them (:func:`~hbis_torch.optics.cubic_spline.not_a_knot_basis`)."""
    from hbis_torch.optics.cubic_spline import not_a_knot_basis

    return torch.from_numpy(not_a_knot_basis(knots, at))


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
    node_step: float = 32.0,
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
        node values with cubic splines (:func:`node_positions`, :func:`interpolate_positions`;
        error < 1e-6 pixel).
    local : bool
        Return roi-local coordinates (minus (u0, v0)), as the contract states; False gives
        full-sensor pixel coordinates.

    Returns
    -------
    Tensor, shape (F, H, W, 2), float64
        (u, v) of each sample in reference-frame pixels.
    """
    if not exact:
        nodes = node_positions(system, phases_deg, reference_index, roi, node_step, local)
        return interpolate_positions(nodes)
    phases = check_phases(phases_deg)
    ref = _reference_phases(phases, reference_index)
    u0, v0, width, height = check_roi(system.camera, roi)
    uu = torch.arange(u0, u0 + width, dtype=torch.float64)[None, :]
    vv = torch.arange(v0, v0 + height, dtype=torch.float64)[:, None]
    p1, p2 = phases[:, 0, None, None], phases[:, 1, None, None]
    landing = landing_at(system, uu, vv, p1, p2)  # (F, H, W, 2)
    positions = sensor_position(system, landing, ref[0], ref[1])
    if local:
        positions = positions - torch.tensor([u0, v0], dtype=torch.float64)
    return positions


def _reference_phases(phases: np.ndarray, reference_index: int) -> np.ndarray:
    if not 0 <= int(reference_index) < phases.shape[0]:
        raise HbisInputError(f"reference index {reference_index} is not a frame index (0..{phases.shape[0] - 1})")
    return phases[int(reference_index)]


class NodePositions(NamedTuple):
    """Exact sample positions on a coarse grid of nodes, from which
    :func:`interpolate_positions` gives every pixel's.

    Attributes
    ----------
    values : Tensor, shape (F, n_v, n_u, 2), float64
        (u, v) on the reference grid of the samples at the nodes (coordinates as the pixels').
    u, v : np.ndarray, shape (n_u,), (n_v,)
        The nodes' columns and rows, in the same coordinates (fractional, evenly spaced).
    width, height : int
        The pixel grid the nodes span: columns ``u[0] .. u[0] + width - 1``, rows likewise.
    """

    values: Tensor
    u: np.ndarray
    v: np.ndarray
    width: int
    height: int


def node_positions(
    system: FoveaSystem,
    phases_deg,
    reference_index: int,
    roi: Roi | None = None,
    node_step: float = 32.0,
    local: bool = True,
) -> NodePositions:
    """The exact sample positions (:func:`sample_positions` with ``exact=True``) on nodes about
    ``node_step`` px apart, spanning the ROI (at least 4 per axis, the ROI's first and last pixels
    among them). Maps that are smooth over the frame can be applied to ``values`` before
    :func:`interpolate_positions` (a homography correction, for example), so that every pixel is
    computed once."""
    phases = check_phases(phases_deg)
    ref = _reference_phases(phases, reference_index)
    u0, v0, width, height = check_roi(system.camera, roi)
    nu, nv = _nodes(u0, u0 + width - 1, node_step), _nodes(v0, v0 + height - 1, node_step)
    grid_u, grid_v = torch.from_numpy(nu)[None, :], torch.from_numpy(nv)[:, None]
    p1, p2 = phases[:, 0, None, None], phases[:, 1, None, None]
    landing = landing_at(system, grid_u, grid_v, p1, p2)  # (F, n_v, n_u, 2)
    values = sensor_position(system, landing, ref[0], ref[1])
    if local:
        values = values - torch.tensor([u0, v0], dtype=torch.float64)
        nu, nv = nu - u0, nv - v0
    return NodePositions(values, nu, nv, width, height)


def interpolate_positions(nodes: NodePositions, rows=None, cols=None) -> Tensor:
    """Every pixel's position from the nodes': separable not-a-knot cubic splines of the
    displacement (position minus the pixel's own coordinates), which is smooth: its variation
    about each frame's mean is interpolated in float32 (rounding about 1e-7 of that variation),
    the mean and the pixel grid are added in float64.

    Parameters
    ----------
    nodes : NodePositions
    rows, cols : array of int, optional
        Only these rows and columns of the pixel grid (0-based, within ``height`` and ``width``).

    Returns
    -------
    Tensor, shape (F, len(rows), len(cols), 2), float64
        (default: every row and column, (F, height, width, 2)).
    """
    shift, mean = interpolate_displacements(nodes, rows, cols)
    cols = np.arange(nodes.width) if cols is None else np.asarray(cols)
    rows = np.arange(nodes.height) if rows is None else np.asarray(rows)
    uu = torch.from_numpy(nodes.u[0] + cols.astype(np.float64))[None, :]
    vv = torch.from_numpy(nodes.v[0] + rows.astype(np.float64))[:, None]
    out = torch.empty(shift.shape[0], len(rows), len(cols), 2, dtype=torch.float64)
    out[..., 0] = shift[:, 0]
    out[..., 1] = shift[:, 1]
    out[..., 0] += uu + mean[:, 0, None, None]
    out[..., 1] += vv + mean[:, 1, None, None]
    return out


def interpolate_displacements(nodes: NodePositions, rows=None, cols=None) -> tuple[Tensor, Tensor]:
    """:func:`interpolate_positions` before its float64 sum: every pixel's displacement from its
    own coordinates, as each frame's mean (float64) plus the spline of the variation about it
    (float32), for callers that need less than the whole float64 position.

    Parameters
    ----------
    nodes : NodePositions
    rows, cols : array of int, optional
        As :func:`interpolate_positions`'s.

    Returns
    -------
    variation : Tensor, shape (F, 2, len(rows), len(cols)), float32
        (u, v) displacement about the frame's mean, pixels.
    mean : Tensor, shape (F, 2), float64
        Each frame's mean (u, v) displacement, pixels. Pixel (row r, column c) of frame k is at
        ``(nodes.u[0] + c, nodes.v[0] + r) + mean[k] + variation[k, :, r, c]``.
    """
    values, nu, nv = nodes.values, nodes.u, nodes.v
    base_u = torch.from_numpy(nu)[None, :]
    base_v = torch.from_numpy(nv)[:, None]
    base = torch.stack(torch.broadcast_tensors(base_u, base_v), -1)
    shift = (values - base).movedim(-1, 1)  # (F, 2, n_v, n_u), smooth
    # each frame's mean displacement stays in float64 (the splines reproduce constants)
    mean = shift.mean(dim=(2, 3))  # (F, 2)
    shift = (shift - mean[:, :, None, None]).to(torch.float32)
    bu = _regular_basis(nodes.width, len(nu)).to(torch.float32)
    bv = _regular_basis(nodes.height, len(nv)).to(torch.float32)
    if cols is not None:
        bu = bu[torch.from_numpy(np.asarray(cols))]
    if rows is not None:
        bv = bv[torch.from_numpy(np.asarray(rows))]
    # the pass that costs fewer flops first: along u on the n_v node rows for many rows, along v
    # for a few rows (a band of a stack's rows, as the classical splat asks for)
    (rows_out, n_v), (cols_out, n_u) = bv.shape, bu.shape
    if n_v * n_u * cols_out + rows_out * n_v * cols_out <= rows_out * n_v * n_u + rows_out * n_u * cols_out:
        return bv @ (shift @ bu.T), mean
    return (bv @ shift) @ bu.T, mean
