"""Vector Snell's law at one refracting surface.

The normal may point either way; it is turned to point along the ray before use. Total internal
reflection (TIR) is returned as a boolean mask and the transmitted direction is then set to the
mirror reflection, so no NaN ever leaves this function.
"""

from __future__ import annotations

import torch
from torch import Tensor


def refract_components(
    ix: Tensor, iy: Tensor, iz: Tensor, nx, ny, nz, eta: float
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Refract unit rays (ix, iy, iz) at a surface of unit normal (nx, ny, nz).

    Components are broadcastable tensors (or Python floats for the normal). ``eta`` is
    n_incident / n_transmitted. Returns the transmitted unit direction and a TIR mask.
    Working on components keeps every step an elementwise op (no (..., 3) reductions), which is
    what makes the full-sensor trace fast.
    """
    cos_i = ix * nx + iy * ny + iz * nz
    sign = 1.0
    if bool((cos_i < 0).any()):  # the normal faces the ray: turn it round where it does
        sign = torch.where(cos_i < 0, -1.0, 1.0).to(ix.dtype)
        cos_i = cos_i * sign
    k = 1.0 - eta * eta * (1.0 - cos_i * cos_i)
    tir = k < 0
    cos_t = torch.sqrt(torch.clamp(k, min=0.0))
    # Transmitted: eta*I + (cos_t - eta*cos_i)*N; on TIR fall back to the reflection I - 2 cos_i N.
    scale = torch.where(tir, -2.0 * cos_i, cos_t - eta * cos_i) * sign
    gain = torch.where(tir, 1.0, eta) if bool(tir.any()) else eta
    return gain * ix + scale * nx, gain * iy + scale * ny, gain * iz + scale * nz, tir


def refract(incident: Tensor, normal: Tensor, eta: float) -> tuple[Tensor, Tensor]:
    """Vector Snell's law.

    Parameters
    ----------
    incident : Tensor, shape (..., 3)
        Unit ray directions.
    normal : Tensor, shape (..., 3)
        Unit surface normals, broadcastable to ``incident``.
    eta : float
        Ratio of refractive indices n_incident / n_transmitted.

    Returns
    -------
    transmitted : Tensor, shape (..., 3)
        Unit transmitted directions (the reflection where TIR occurs).
    tir : Tensor of bool, shape (...)
        True where total internal reflection occurred.
    """
    incident, normal = torch.broadcast_tensors(incident, normal.to(incident.dtype))
    tx, ty, tz, tir = refract_components(*incident.unbind(-1), *normal.unbind(-1), eta)
    return torch.stack((tx, ty, tz), dim=-1), tir
