"""Exact (non-paraxial) vector ray tracing through a Risley prism pair.

Conventions (docs/design.md section 1): rays travel along +z; prism 1 has a flat face then a tilted
face, prism 2 a tilted face then a flat face, with the normals of the paper's eq. 4::

    n11 = (0, 0, 1)
    n12 = (-sin a cos phi1, -sin a sin phi1, cos a)
    n21 = ( sin a cos phi2,  sin a sin phi2, cos a)
    n22 = (0, 0, 1)

Phases are in degrees, measured from +x toward +y. With phi1 = phi2 = phi the axis ray is
deviated toward (cos phi, sin phi); this is the paper's frame with the sign of eq. 5 flipped.

Everything broadcasts: rays of shape ``(*R, 3)`` and phases of shape ``(*P)`` give outputs of shape
``broadcast(*P, *R)``. For example phases (P, 1, 1) with rays (H, W, 3) trace a whole scan at once.
Works in float32 and float64 on any device; float64 is the reference for analysis (float32 costs
about 1e-5 pixel on the landing map, see tests/test_optics.py).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from hbis_torch.config import Prisms
from hbis_torch.errors import HbisInputError
from hbis_torch.optics.snell import refract_components


def _as_tensor(x, like: Tensor | None = None, name: str = "value") -> Tensor:
    if isinstance(x, Tensor):
        t = x
        if like is not None:
            t = t.to(dtype=like.dtype, device=like.device)
    else:
        dtype = like.dtype if like is not None else torch.float64
        device = like.device if like is not None else None
        t = torch.as_tensor(x, dtype=dtype, device=device)
    if not torch.isfinite(t).all():
        raise HbisInputError(f"{name} contains non-finite values (NaN or inf)")
    return t


def _check_rays(rays: Tensor) -> Tensor:
    if not isinstance(rays, Tensor):
        rays = torch.as_tensor(rays, dtype=torch.float64)
    if rays.ndim == 0 or rays.shape[-1] != 3:
        raise HbisInputError(f"rays must have shape (..., 3), got {tuple(rays.shape)}")
    if rays.numel() == 0:
        raise HbisInputError("the ray set is empty")
    if not rays.is_floating_point():
        rays = rays.to(torch.float64)
    if not torch.isfinite(rays).all():
        raise HbisInputError("rays contain non-finite values (NaN or inf)")
    return rays


@dataclass
class RisleyTrace:
    """Result of a trace.

    Attributes
    ----------
    directions : Tensor, shape (..., 3)
        Unit exit directions R22 (for rays with TIR: a finite but meaningless direction).
    valid : Tensor of bool, shape (...)
        False where total internal reflection stopped the ray at some face.
    """

    directions: Tensor
    valid: Tensor

    def require_valid(self) -> Tensor:
        """The directions, or a clear error if any ray was totally internally reflected."""
        if not bool(self.valid.all()):
            bad = int((~self.valid).sum())
            raise HbisInputError(
                f"{bad} ray(s) are totally internally reflected inside the prisms; "
                "the geometry (wedge angle, index, field angle) cannot pass them"
            )
        return self.directions


def _refract_tilted(x, y, z, nx, ny, nz, eta):
    """Branch-free Snell refraction at a tilted face whose normal points along the ray."""
    cos_i = x * nx + y * ny + z * nz
    k = 1.0 - eta * eta * (1.0 - cos_i * cos_i)
    scale = torch.sqrt(torch.clamp(k, min=0.0)) - eta * cos_i
    return eta * x + scale * nx, eta * y + scale * ny, eta * z + scale * nz, k < 0


def _risley_kernel(x, y, z, p1, p2, sin_a: float, cos_a: float, n: float):
    """The four refractions as one elementwise expression (no data-dependent branches).

    Inputs are broadcastable tensors: ray components and phases in radians. Returns the exit
    components and a TIR mask. Being branch-free, it runs as is in eager mode and compiles to a
    single fused loop under torch.compile (``fast=True``).
    """
    # Face 11 (air -> glass, normal +z): the transverse part scales by 1/n.
    x, y = x / n, y / n
    z = torch.sqrt(torch.clamp(1.0 - (x * x + y * y), min=0.0))
    x, y, z, tir12 = _refract_tilted(
        x, y, z, -sin_a * torch.cos(p1), -sin_a * torch.sin(p1), cos_a, n
    )
    x, y, z, tir21 = _refract_tilted(
        x, y, z, sin_a * torch.cos(p2), sin_a * torch.sin(p2), cos_a, 1.0 / n
    )
    # Face 22 (glass -> air, normal +z): transverse part scales by n; TIR if it exceeds 1.
    x, y = x * n, y * n
    s2 = x * x + y * y
    z = torch.sqrt(torch.clamp(1.0 - s2, min=0.0))
    return x, y, z, tir12 | tir21 | (s2 > 1.0)


_compiled_kernel = None


def _fast_kernel():
    """torch.compile'd kernel, or the eager one where no compiler is available."""
    global _compiled_kernel
    if _compiled_kernel is None:
        try:
            compiled = torch.compile(_risley_kernel, dynamic=True)
            one = torch.ones(2, dtype=torch.float64)
            compiled(one * 0, one * 0, one, one, one, 0.1, 0.99, 1.5)  # fail here, not later
            _compiled_kernel = compiled
        except Exception:  # noqa: BLE001 - no C++ compiler or an unsupported backend
            _compiled_kernel = _risley_kernel
    return _compiled_kernel


def trace_risley(
    rays: Tensor, phi1_deg, phi2_deg, prisms: Prisms = Prisms(), fast: bool = False
) -> RisleyTrace:
    """Trace unit rays through the pair at phases (phi1, phi2).

    Parameters
    ----------
    rays : Tensor, shape ``(*R, 3)``
        Unit incident directions travelling toward +z.
    phi1_deg, phi2_deg : float or Tensor, shape ``(*P)``
        Prism phases in degrees.
    prisms : Prisms
        Wedge angle and refractive index.
    fast : bool
        Use a torch.compile'd kernel (one fused loop; several times faster on large ray sets,
        about 10 s to compile once per process). Results are identical to rounding.

    Returns
    -------
    RisleyTrace with directions of shape ``broadcast(*P, *R) + (3,)``.
    """
    rays = _check_rays(rays)
    if bool((rays[..., 2] <= 0).any()):
        raise HbisInputError("rays must travel toward the prisms (direction z > 0)")
    p1 = torch.deg2rad(_as_tensor(phi1_deg, rays, "phi1"))
    p2 = torch.deg2rad(_as_tensor(phi2_deg, rays, "phi2"))
    a = math.radians(prisms.wedge_angle_deg)
    kernel = _fast_kernel() if fast else _risley_kernel
    x, y, z, tir = kernel(*rays.unbind(-1), p1, p2, math.sin(a), math.cos(a), prisms.refractive_index)
    directions = torch.stack(torch.broadcast_tensors(x, y, z), dim=-1)
    valid = ~tir.expand(directions.shape[:-1])
    if not bool(valid.all()):
        # Keep the result finite and unit length where the ray never left the glass.
        norm = directions.norm(dim=-1, keepdim=True).clamp_min(1e-300)
        directions = torch.where(valid[..., None], directions, directions / norm)
    return RisleyTrace(directions, valid)


def trace_back(directions: Tensor, phi1_deg, phi2_deg, prisms: Prisms = Prisms()) -> RisleyTrace:
    """Invert the pair: the incident directions whose exit directions are ``directions``.

    Reversing a ray and mirroring z turns the pair into itself with the two phases swapped
    (the tilted faces trade places), so the forward kernel does the work. Shapes as in
    :func:`trace_risley`.
    """
    directions = _check_rays(directions)
    x, y, z = directions.unbind(-1)
    back = trace_risley(torch.stack((-x, -y, z), -1), phi2_deg, phi1_deg, prisms)
    bx, by, bz = back.directions.unbind(-1)
    return RisleyTrace(torch.stack((-bx, -by, bz), -1), back.valid)


def trace_faces(rays: Tensor, normals: list[Tensor], indices: list[float]) -> RisleyTrace:
    """Trace rays through any sequence of plane faces (used to check reversibility).

    ``normals[i]`` (shape broadcastable to rays) separates media ``indices[i]`` and
    ``indices[i + 1]``.
    """
    rays = _check_rays(rays)
    if len(indices) != len(normals) + 1:
        raise HbisInputError("need one more refractive index than faces")
    x, y, z = rays.unbind(-1)
    valid = torch.ones_like(x, dtype=torch.bool)
    for normal, n_in, n_out in zip(normals, indices[:-1], indices[1:]):
        nx, ny, nz = torch.as_tensor(normal, dtype=rays.dtype, device=rays.device).unbind(-1)
        x, y, z, tir = refract_components(x, y, z, nx, ny, nz, n_in / n_out)
        valid = valid & ~tir
    return RisleyTrace(torch.stack(torch.broadcast_tensors(x, y, z), dim=-1), valid)


def risley_normals(phi1_deg, phi2_deg, prisms: Prisms, dtype=torch.float64) -> list[Tensor]:
    """The four face normals of eq. 4 as (..., 3) tensors, in the order the ray meets them."""
    a = math.radians(prisms.wedge_angle_deg)
    p1 = torch.deg2rad(torch.as_tensor(phi1_deg, dtype=dtype))
    p2 = torch.deg2rad(torch.as_tensor(phi2_deg, dtype=dtype))
    sa = math.sin(a)
    cz1 = torch.full_like(p1, math.cos(a))
    cz2 = torch.full_like(p2, math.cos(a))
    n12 = torch.stack((-sa * torch.cos(p1), -sa * torch.sin(p1), cz1), -1)
    n21 = torch.stack((sa * torch.cos(p2), sa * torch.sin(p2), cz2), -1)
    flat = torch.tensor([0.0, 0.0, 1.0], dtype=dtype)
    return [flat, n12, n21, flat]


def exit_directions(rays: Tensor, phi1_deg, phi2_deg, prisms: Prisms = Prisms()) -> Tensor:
    """Exit directions ``(*P, *R, 3)``; raises HbisInputError if any ray is totally reflected.

    Examples
    --------
    Phases of shape (2,) and one ray give two unit directions:

    >>> import torch
    >>> from hbis_torch.optics.risley import exit_directions
    >>> axis = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    >>> d = exit_directions(axis, torch.tensor([0.0, 90.0]), torch.tensor([0.0, 90.0]))
    >>> tuple(d.shape)
    (2, 3)
    >>> torch.allclose(d.norm(dim=-1), torch.ones(2, dtype=torch.float64))
    True
    """
    return trace_risley(rays, phi1_deg, phi2_deg, prisms).require_valid()


def deviation_azimuth(directions: Tensor) -> tuple[Tensor, Tensor]:
    """Deviation Phi (angle from +z) and azimuth Theta (from +x toward +y), in degrees.

    Uses atan2 rather than acos so that small deviations keep full precision in float32.
    """
    x, y, z = directions.unbind(-1)
    phi = torch.rad2deg(torch.atan2(torch.hypot(x, y), z))
    theta = torch.rad2deg(torch.atan2(y, x))
    return phi, theta


def axis_deviation(phi1_deg, phi2_deg, prisms: Prisms = Prisms(), dtype=torch.float64):
    """Deviation and azimuth (degrees) of the optical axis (0, 0, 1) at the given phases.

    Examples
    --------
    Aligned prisms deviate the axis most; opposed prisms (180 deg apart) act as a glass slab:

    >>> from hbis_torch.optics.risley import axis_deviation
    >>> deviation, azimuth = axis_deviation(0.0, 0.0)
    >>> round(float(deviation), 4), round(float(azimuth), 4)
    (4.0082, 0.0)
    >>> deviation, _ = axis_deviation(0.0, 180.0)
    >>> abs(float(deviation)) < 1e-12
    True
    """
    axis = torch.tensor([0.0, 0.0, 1.0], dtype=dtype)
    return deviation_azimuth(exit_directions(axis, phi1_deg, phi2_deg, prisms))


def land_on_plane(directions: Tensor, distance_mm: float) -> Tensor:
    """Where rays from the pupil land on the plane z = distance: distance * (Rx/Rz, Ry/Rz).

    Returns shape (..., 2) in mm. Rays that do not travel toward the plane raise an error.
    """
    if not math.isfinite(distance_mm) or distance_mm <= 0:
        raise HbisInputError(f"object distance must be positive, got {distance_mm!r}")
    z = directions[..., 2:3]
    if bool((z <= 0).any()):
        raise HbisInputError("some rays never reach the object plane (direction z <= 0)")
    return distance_mm * directions[..., :2] / z
