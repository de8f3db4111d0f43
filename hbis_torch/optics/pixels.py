"""Per-pixel chief rays and landing maps on the object plane.

Pixel (u, v), 0-based, names the centre of column u and row v. Its chief ray leaves the pupil
along ((u - (cols-1)/2) p, (v - (rows-1)/2) p, f'), normalised (docs/design.md section 1). A
camera with a lens calibration (``Camera.lens``: OpenCV's K and distortion) takes its chief rays
from :mod:`hbis_torch.optics.lens` instead, everywhere below.

A region of interest (ROI) is ``(u0, v0, width, height)`` in pixels, as in the hbis-stack/1
file format; ``None`` means the whole sensor.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

from hbis_torch.config import Camera, FoveaSystem
from hbis_torch.checks import check_roi
from hbis_torch.errors import HbisInputError
from hbis_torch.optics.risley import exit_directions, land_on_plane

Roi = tuple[int, int, int, int]


def pixel_coordinates(camera: Camera, roi: Roi | None = None, dtype=torch.float64, device=None):
    """Sensor-plane coordinates (x, y) in mm of the pixel centres, each of shape (H, W).

    With a lens calibration these are the coordinates an ideal camera of focal length f' would
    need for the same chief rays (the calibrated, undistorted directions times f').
    """
    u0, v0, width, height = check_roi(camera, roi)
    if camera.lens is not None:
        u = torch.arange(u0, u0 + width, dtype=torch.float64, device=device)
        v = torch.arange(v0, v0 + height, dtype=torch.float64, device=device)
        rays = rays_at(camera, u[None, :], v[:, None])
        f = camera.focal_length_mm
        return (rays[..., 0] / rays[..., 2] * f).to(dtype), (rays[..., 1] / rays[..., 2] * f).to(dtype)
    p = camera.pitch_mm
    u = torch.arange(u0, u0 + width, dtype=dtype, device=device) - (camera.cols - 1) / 2
    v = torch.arange(v0, v0 + height, dtype=dtype, device=device) - (camera.rows - 1) / 2
    y, x = torch.meshgrid(v * p, u * p, indexing="ij")
    return x, y


def pixel_rays(camera: Camera, roi: Roi | None = None, dtype=torch.float64, device=None) -> Tensor:
    """Unit chief-ray directions of the pixels, shape (H, W, 3)."""
    x, y = pixel_coordinates(camera, roi, dtype, device)
    f = torch.full_like(x, camera.focal_length_mm)
    rays = torch.stack((x, y, f), dim=-1)
    return rays / rays.norm(dim=-1, keepdim=True)


def rays_at(camera: Camera, u: Tensor, v: Tensor) -> Tensor:
    """Unit chief rays at fractional sensor positions (u, v) in pixels (0-based centres).

    ``u`` and ``v`` are broadcastable tensors; returns shape broadcast(u, v) + (3,).
    """
    u, v = torch.broadcast_tensors(torch.as_tensor(u), torch.as_tensor(v))
    if not u.is_floating_point():
        u, v = u.double(), v.double()
    if camera.lens is not None:  # a real lens: principal point, focal length in pixels, distortion
        from hbis_torch.optics.lens import pixel_rays_through_lens

        return pixel_rays_through_lens(camera.lens, u.double(), v.double()).to(u.dtype)
    p = camera.pitch_mm
    x = (u - (camera.cols - 1) / 2) * p
    y = (v - (camera.rows - 1) / 2) * p
    rays = torch.stack((x, y, torch.full_like(x, camera.focal_length_mm)), dim=-1)
    return rays / rays.norm(dim=-1, keepdim=True)


def sensor_position(system: FoveaSystem, points_mm: Tensor, phi1_deg, phi2_deg) -> Tensor:
    """Where on the sensor an object-plane point is imaged: the exact inverse of the landing map.

    Parameters
    ----------
    points_mm : Tensor, shape (..., 2)
        (x, y) on the object plane z = v, in mm.
    phi1_deg, phi2_deg : float or Tensor broadcastable to points_mm.shape[:-1]
        Prism phases in degrees.

    Returns
    -------
    Tensor, shape (..., 2)
        Fractional pixel coordinates (u, v), 0-based pixel centres (may lie off the sensor).
    """
    from hbis_torch.optics.risley import trace_back

    points_mm = torch.as_tensor(points_mm)
    if points_mm.ndim == 0 or points_mm.shape[-1] != 2:
        raise HbisInputError(f"points must have shape (..., 2), got {tuple(points_mm.shape)}")
    if not points_mm.is_floating_point():
        points_mm = points_mm.double()
    v = torch.full_like(points_mm[..., :1], system.object_distance_mm)
    out = torch.cat((points_mm, v), dim=-1)
    out = out / out.norm(dim=-1, keepdim=True)
    incident = trace_back(out, phi1_deg, phi2_deg, system.prisms).require_valid()
    cam = system.camera
    if cam.lens is not None:
        from hbis_torch.optics.lens import pixels_of_directions

        return pixels_of_directions(cam.lens, incident)
    scale = cam.focal_length_mm / cam.pitch_mm
    u = incident[..., 0] / incident[..., 2] * scale + (cam.cols - 1) / 2
    w = incident[..., 1] / incident[..., 2] * scale + (cam.rows - 1) / 2
    return torch.stack((u, w), dim=-1)


def _phases(phi1_deg, phi2_deg, dtype, device) -> tuple[Tensor, Tensor]:
    p1 = torch.as_tensor(phi1_deg, dtype=dtype, device=device)
    p2 = torch.as_tensor(phi2_deg, dtype=dtype, device=device)
    p1, p2 = torch.broadcast_tensors(p1, p2)
    if not (torch.isfinite(p1).all() and torch.isfinite(p2).all()):
        raise HbisInputError("phases contain non-finite values")
    return p1, p2


def landing_map(
    system: FoveaSystem, phi1_deg, phi2_deg, roi: Roi | None = None, dtype=torch.float64, device=None
) -> Tensor:
    """Exact landing points of every pixel's chief ray on the object plane, in mm.

    Parameters
    ----------
    phi1_deg, phi2_deg : float or Tensor, shape ``(*P)``
        Prism phases in degrees.
    roi : (u0, v0, width, height) or None
        Pixels to trace (None: the whole sensor).

    Returns
    -------
    Tensor, shape ``(*P, H, W, 2)``
        (x, y) on the plane z = v, in mm. Divide by ``system.object_pixel_mm`` for pixel units.

    Examples
    --------
    Two phase pairs, an 8 x 4 pixel ROI:

    >>> import torch
    >>> from hbis_torch import FoveaSystem
    >>> from hbis_torch.optics.pixels import landing_map
    >>> system = FoveaSystem()
    >>> phi1, phi2 = torch.tensor([5.0, 10.0]), torch.tensor([70.0, 75.0])
    >>> maps = landing_map(system, phi1, phi2, roi=(100, 200, 8, 4))
    >>> tuple(maps.shape), maps.dtype
    ((2, 4, 8, 2), torch.float64)

    Neighbouring pixels land about one object pixel (p v / f') apart:

    >>> step = float((maps[0, 0, 1] - maps[0, 0, 0]).norm() / system.object_pixel_mm)
    >>> 0.9 < step < 1.1
    True
    """
    rays = pixel_rays(system.camera, roi, dtype, device)
    p1, p2 = _phases(phi1_deg, phi2_deg, dtype, device)
    p1, p2 = p1[..., None, None], p2[..., None, None]
    directions = exit_directions(rays, p1, p2, system.prisms)
    return land_on_plane(directions, system.object_distance_mm)


def pinhole_landing(system: FoveaSystem, roi: Roi | None = None, dtype=torch.float64, device=None):
    """Landing points without prisms, (H, W, 2) in mm: v / f' * (x, y)."""
    x, y = pixel_coordinates(system.camera, roi, dtype, device)
    scale = system.object_distance_mm / system.camera.focal_length_mm
    return torch.stack((x, y), dim=-1) * scale


def _spline_basis(nodes: int, size: int, dtype, device) -> Tensor:
    """(size, nodes) matrix that evaluates a not-a-knot cubic spline through ``nodes`` equally
    spaced samples (the first at 0, the last at size - 1) at every integer 0..size-1."""
    from hbis_torch.optics.cubic_spline import not_a_knot_basis

    basis = not_a_knot_basis(np.linspace(0.0, size - 1.0, nodes), np.arange(size, dtype=np.float64))
    return torch.as_tensor(basis, dtype=dtype, device=device)


def landing_map_interpolated(
    system: FoveaSystem,
    phi1_deg,
    phi2_deg,
    roi: Roi | None = None,
    grid_step: int = 96,
    dtype=torch.float64,
    device=None,
) -> Tensor:
    """Landing maps from a coarse exact trace and cubic-spline interpolation; ``(*P, H, W, 2)``, mm.

    The landing map is smooth over the sensor (the pinhole part is linear, which the not-a-knot
    spline reproduces exactly; the prisms add a slowly varying distortion), so nodes every
    ``grid_step`` pixels are enough. The spline is separable: each fine map is two small matrix
    products. The result is a channel-last view of a ``(*P, 2, H, W)`` tensor (no extra copy).
    benchmarks/bench_optics.py prints the error against the exact trace (7e-5 pixel in float64,
    3e-4 in float32, for the Table 1 system and the default grid).
    """
    u0, v0, width, height = check_roi(system.camera, roi)
    p1, p2 = _phases(phi1_deg, phi2_deg, dtype, device)
    nu = math.ceil((width - 1) / grid_step) + 1
    nv = math.ceil((height - 1) / grid_step) + 1
    if min(nu, nv) < 4 or nu * nv * 8 >= width * height:  # too small for a spline to pay off
        return landing_map(system, p1, p2, roi, dtype, device)
    cam = system.camera
    us = torch.linspace(u0, u0 + width - 1, nu, dtype=dtype, device=device) - (cam.cols - 1) / 2
    vs = torch.linspace(v0, v0 + height - 1, nv, dtype=dtype, device=device) - (cam.rows - 1) / 2
    y, x = torch.meshgrid(vs * cam.pitch_mm, us * cam.pitch_mm, indexing="ij")
    rays = torch.stack((x, y, torch.full_like(x, cam.focal_length_mm)), dim=-1)
    rays = rays / rays.norm(dim=-1, keepdim=True)
    if cam.lens is not None:
        uu = torch.linspace(u0, u0 + width - 1, nu, dtype=torch.float64, device=device)
        vv = torch.linspace(v0, v0 + height - 1, nv, dtype=torch.float64, device=device)
        rays = rays_at(cam, uu[None, :], vv[:, None]).to(dtype)
    directions = exit_directions(rays, p1[..., None, None], p2[..., None, None], system.prisms)
    coarse = land_on_plane(directions, system.object_distance_mm).movedim(-1, -3)  # (*P, 2, nv, nu)
    basis_v = _spline_basis(nv, height, dtype, device)
    basis_u = _spline_basis(nu, width, dtype, device)
    return (basis_v @ coarse @ basis_u.T).movedim(-3, -1)
