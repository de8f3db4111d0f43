"""Inverse solutions of the Risley pair: from a wanted landing point of the optical axis to phases.

Three solvers, all vectorised over any number of targets (shape (F, 2), mm on the object plane):

* :func:`paper_inverse` - the paper's closed form (eqs. 5-9 of [1]_). Each prism is a fixed-length
  vector on the object plane, DV = k1 e(phi1) + k2 e(phi2) with e(phi) = (cos phi, sin phi).
  This is the paper's eq. 5 with the sign flipped: in our frame (docs/design.md section 1) phi1 = phi2
  = phi deviates the axis *toward* (cos phi, sin phi), the paper's frame deviates it away. The
  norms k1, k2 come from the initial point (eq. 8, :func:`paper_norms`).
* :func:`exact_inverse` - the non-paraxial model, exact to rounding. It uses the rotational
  symmetry of the pair: turning both prisms by the same angle c turns the deviated axis by c,
  so the landing radius depends only on the relative angle delta = phi2 - phi1. The radius is a
  monotone, nearly linear function of cos(delta / 2) (largest with the prisms aligned, zero with
  them opposed), so one safeguarded Newton root-find over all targets gives delta, and the
  common rotation then follows from the target's azimuth.
* :func:`paraxial_inverse` - the first-order model of section 2.3 (each prism deviates by
  (n - 1) a), for coarse pointing.

Every solver returns, for each target, the one of its two solution branches (delta and -delta)
that is nearest the given current phases, with each phase moved by a whole turn to lie nearest
its current value: the shortest rotation. Singular and hard cases:

* opposed prisms, abs(phi1 - phi2) = 180 deg: the two tilted faces are then parallel (a glass slab)
  and the axis is not deviated at all, so the azimuth of a target at the centre is undefined.
  The solvers keep the common rotation of the current phases there (no 180 deg jump).
* targets at the rim of the reachable disc (prisms aligned): the two branches merge and the
  Jacobian loses rank; the root-find works in cos(delta / 2), where the radius keeps a non-zero
  slope.
* targets beyond the maximum deviation raise :class:`~hbis_torch.errors.HbisInputError`, naming
  that maximum; targets past the rim by rounding only (relative 1e-9) are put on the rim.
* arccos arguments pushed past +-1 by rounding are clamped. No NaN ever leaves this module.

References
----------
.. [1] Q. Hao, Z. Wang, J. Cao and F. Zhang, "A Hybrid Bionic Image Sensor Achieving FOV
   Extension and Foveated Imaging" (the paper this project implements; ``CITATION.cff``):
   section 2.3 and eqs. 5-9, the Risley pair's forward model and its closed-form inverse.

Angles are in degrees, lengths in mm, all work is float64.
"""

from __future__ import annotations

import functools
import math

import torch
from torch import Tensor

from hbis_torch.config import Prisms, FoveaSystem
from hbis_torch.errors import HbisInputError
from hbis_torch.optics.risley import exit_directions, land_on_plane

# Targets this far (relative) beyond the reachable rim are rounding, and are put on the rim.
RIM_TOLERANCE = 1e-9
# Below this radius (relative to the largest) a target's azimuth is treated as undefined.
CENTRE_TOLERANCE = 1e-12

_AXIS = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)


def axis_landing(system: FoveaSystem, phi1_deg, phi2_deg) -> Tensor:
    """Exact landing point of the optical axis on the object plane; shape ``(*P, 2)``, mm."""
    p1 = torch.as_tensor(phi1_deg, dtype=torch.float64)
    p2 = torch.as_tensor(phi2_deg, dtype=torch.float64)
    directions = exit_directions(_AXIS, p1[..., None], p2[..., None], system.prisms)[..., 0, :]
    return land_on_plane(directions, system.object_distance_mm)


def max_deviation_deg(prisms: Prisms) -> float:
    """Largest deviation of the axis (prisms aligned), degrees; the rim of the reachable disc."""
    d = exit_directions(_AXIS, torch.zeros(1, dtype=torch.float64), 0.0, prisms)
    return math.degrees(math.atan2(math.hypot(float(d[0, 0]), float(d[0, 1])), float(d[0, 2])))


def max_landing_radius_mm(system: FoveaSystem) -> float:
    """Largest distance of the axis landing from the centre of the object plane, mm."""
    return system.object_distance_mm * math.tan(math.radians(max_deviation_deg(system.prisms)))


# --------------------------------------------------------------------------------------------
# Input checks and the shortest rotation
# --------------------------------------------------------------------------------------------


def _check_targets(targets_mm) -> Tensor:
    t = torch.as_tensor(targets_mm, dtype=torch.float64)
    if t.ndim != 2 or t.shape[-1] != 2:
        raise HbisInputError(f"targets must have shape (F, 2) in mm, got {tuple(t.shape)}")
    if t.shape[0] == 0:
        raise HbisInputError("no targets given")
    if not torch.isfinite(t).all():
        raise HbisInputError("targets contain non-finite values (NaN or inf)")
    return t


def _check_current(current_deg, count: int) -> Tensor:
    c = torch.as_tensor(current_deg, dtype=torch.float64)
    if c.shape == (2,):
        c = c.expand(count, 2)
    if c.shape != (count, 2):
        raise HbisInputError(
            f"current phases must have shape (2,) or ({count}, 2) in degrees, got {tuple(c.shape)}"
        )
    if not torch.isfinite(c).all():
        raise HbisInputError("current phases contain non-finite values (NaN or inf)")
    return c


def wrap_deg(angle: Tensor) -> Tensor:
    """Angles wrapped into [-180, 180) degrees."""
    return torch.remainder(angle + 180.0, 360.0) - 180.0


def nearest_turn(phases_deg: Tensor, current_deg: Tensor) -> Tensor:
    """Each phase moved by whole turns to lie within 180 deg of its current value."""
    return current_deg + wrap_deg(phases_deg - current_deg)


def common_rotation_deg(current_deg: Tensor) -> Tensor:
    """Common rotation of a phase pair, (..., 2) -> (...): the mid-angle along the shorter arc
    from phi1 to phi2 (for opposed prisms the arc from phi1 counter-clockwise)."""
    return current_deg[..., 0] + wrap_deg(current_deg[..., 1] - current_deg[..., 0]) / 2


def _choose_branch(branch_a: Tensor, branch_b: Tensor, current: Tensor) -> Tensor:
    """Per target, the branch (each (F, 2)) with the smaller rotation from ``current``."""
    a = nearest_turn(branch_a, current)
    b = nearest_turn(branch_b, current)
    cost_a = ((a - current) ** 2).sum(-1)
    cost_b = ((b - current) ** 2).sum(-1)
    return torch.where((cost_b < cost_a)[:, None], b, a)


def _radius_check(radius: Tensor, r_max: float, limit: str) -> Tensor:
    """Raise if a target lies beyond the reachable rim; put rounding-level excess on the rim."""
    worst = float(radius.max())
    if worst > r_max * (1.0 + RIM_TOLERANCE):
        raise HbisInputError(f"target at {worst:.6g} mm from the centre is beyond {limit}")
    return radius.clamp(max=r_max)


def _phases_from_relative(
    azimuth_deg: Tensor, delta_deg: Tensor, twist_deg: Tensor, centre: Tensor, current: Tensor
) -> Tensor:
    """Both branches from the relative angle, then the nearest; (F, 2) degrees.

    With phi1 = c - delta/2 and phi2 = c + delta/2 the axis lands at azimuth c + twist(delta), and
    twist(-delta) = -twist(delta) (mirror symmetry of the pair about a plane through z). Where the
    target azimuth is undefined (``centre``) the common rotation stays at the current one.
    """
    keep = common_rotation_deg(current)
    c_a = torch.where(centre, keep, azimuth_deg - twist_deg)
    c_b = torch.where(centre, keep, azimuth_deg + twist_deg)
    branch_a = torch.stack((c_a - delta_deg / 2, c_a + delta_deg / 2), -1)
    branch_b = torch.stack((c_b + delta_deg / 2, c_b - delta_deg / 2), -1)
    return _choose_branch(branch_a, branch_b, current)


# --------------------------------------------------------------------------------------------
# The paper's closed form (eqs. 8-9)
# --------------------------------------------------------------------------------------------


def paper_norms(system: FoveaSystem, initial_phases_deg) -> tuple[float, float]:
    """k1 and k2 (mm) of eq. 8 from the exact landing DV^0 of the axis at the initial phases.

    Case 1 (phi1 != phi2): solve DV^0 = k1 e(phi1) + k2 e(phi2) (our sign of eq. 5).
    Case 2 (phi1 == phi2): k1 = k2 = abs(DV^0) / 2.
    The paper leaves out opposed prisms (abs(phi1 - phi2) = 180 deg), where the 2 x 2 system is
    singular too; there DV^0 = 0 and we take k1 = k2 = half the largest landing radius (the
    aligned value of case 2 at the same phases).
    """
    p = torch.as_tensor(initial_phases_deg, dtype=torch.float64)
    if p.shape != (2,) or not torch.isfinite(p).all():
        raise HbisInputError(f"initial phases must be two finite angles in degrees, got {p.tolist()}")
    dv0 = axis_landing(system, p[0], p[1])
    rad = torch.deg2rad(p)
    sin_rel = math.sin(float(rad[1] - rad[0]))
    if abs(sin_rel) < 1e-9:
        if math.cos(float(rad[1] - rad[0])) > 0:  # case 2: aligned
            k = float(dv0.norm()) / 2
        else:  # opposed: the centre, where eq. 8 says nothing
            k = max_landing_radius_mm(system) / 2
        return k, k
    basis = torch.stack((torch.cos(rad), torch.sin(rad)))  # columns e(phi1), e(phi2)
    k1, k2 = torch.linalg.solve(basis, dv0).tolist()
    if k1 <= 0 or k2 <= 0:
        raise HbisInputError(
            f"eq. 8 gives non-positive prism norms (k1={k1:.4g}, k2={k2:.4g} mm) at initial "
            f"phases {p.tolist()}; choose phases further from the opposed position"
        )
    return k1, k2


def paper_inverse(targets_mm, k1: float, k2: float, current_deg) -> Tensor:
    """The paper's eq. 9: phases that put k1 e(phi1) + k2 e(phi2) on each target.

    Parameters
    ----------
    targets_mm : Tensor, shape (F, 2)
        DV^i, wanted landing points of the axis on the object plane, mm.
    k1, k2 : float
        Norms of the two prisms' deviation vectors, mm (:func:`paper_norms`).
    current_deg : Tensor, shape (2,) or (F, 2)
        Phases to stay near (the paper: the initial phases); picks the branch and the turn.

    Returns
    -------
    Tensor, shape (F, 2)
        [phi1, phi2] per target, degrees.

    References
    ----------
    .. [1] Q. Hao, Z. Wang, J. Cao and F. Zhang, "A Hybrid Bionic Image Sensor Achieving FOV
       Extension and Foveated Imaging" (``CITATION.cff``), eqs. 5-9.
    """
    t = _check_targets(targets_mm)
    current = _check_current(current_deg, t.shape[0])
    if not (math.isfinite(k1) and math.isfinite(k2) and k1 > 0 and k2 > 0):
        raise HbisInputError(f"prism norms must be finite and positive, got k1={k1}, k2={k2}")
    k0 = t.norm(dim=-1)
    k0 = _radius_check(k0, k1 + k2, f"the paper model's reach k1 + k2 = {k1 + k2:.6g} mm")
    inner = abs(k1 - k2)
    if float(k0.min()) < inner * (1.0 - RIM_TOLERANCE) - CENTRE_TOLERANCE * (k1 + k2):
        raise HbisInputError(
            f"target at {float(k0.min()):.6g} mm from the centre lies inside the paper model's "
            f"unreachable hole of radius |k1 - k2| = {inner:.6g} mm"
        )
    centre = k0 <= CENTRE_TOLERANCE * (k1 + k2)
    safe_k0 = torch.where(centre, torch.ones_like(k0), k0)
    arg1 = ((safe_k0**2 + k1**2 - k2**2) / (2 * safe_k0 * k1)).clamp(-1.0, 1.0)
    arg2 = ((safe_k0**2 + k2**2 - k1**2) / (2 * safe_k0 * k2)).clamp(-1.0, 1.0)
    # At the centre (only reachable when k1 == k2) the prisms are opposed: both angles are 90.
    a1 = torch.where(centre, torch.full_like(k0, 90.0), torch.rad2deg(torch.arccos(arg1)))
    a2 = torch.where(centre, torch.full_like(k0, 90.0), torch.rad2deg(torch.arccos(arg2)))
    phi0 = torch.rad2deg(torch.atan2(t[:, 1], t[:, 0]))
    keep = common_rotation_deg(current)
    phi0 = torch.where(centre, keep, phi0)
    branch_a = torch.stack((phi0 + a1, phi0 - a2), -1)
    branch_b = torch.stack((phi0 - a1, phi0 + a2), -1)
    return _choose_branch(branch_a, branch_b, current)


# --------------------------------------------------------------------------------------------
# The exact inverse
# --------------------------------------------------------------------------------------------


_TABLE_NODES = 4097


@functools.lru_cache(maxsize=64)
def _radius_table(prisms: Prisms) -> tuple[Tensor, Tensor]:
    """w = cos(delta / 2) on a fine grid and tan(deviation) of the axis there; both (N,).

    tan(deviation) is the landing radius per mm of object distance. It increases with w.
    """
    w = torch.linspace(0.0, 1.0, _TABLE_NODES, dtype=torch.float64)
    delta = 2 * torch.rad2deg(torch.arccos(w))
    d = exit_directions(_AXIS, (-delta / 2)[:, None], (delta / 2)[:, None], prisms)[:, 0]
    tan = d[:, :2].norm(dim=-1) / d[:, 2]
    if not bool((tan.diff() > 0).all()):
        raise HbisInputError(
            f"the axis deviation of {prisms} does not grow monotonically from opposed to "
            "aligned prisms; the exact inverse does not apply"
        )
    return w, tan


def _interp(x: Tensor, xp: Tensor, fp: Tensor) -> Tensor:
    """Linear interpolation of increasing samples (xp, fp) at x (clamped to the ends)."""
    i = torch.searchsorted(xp, x).clamp(1, xp.numel() - 1)
    x0, x1, f0, f1 = xp[i - 1], xp[i], fp[i - 1], fp[i]
    return (f0 + (x - x0) / (x1 - x0) * (f1 - f0)).clamp(float(fp[0]), float(fp[-1]))


def _relative_trace(system: FoveaSystem, half_cos: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Landing radius (mm), twist (deg) and delta (deg) at phi1 = -delta/2, phi2 = +delta/2,
    for w = cos(delta / 2) in [0, 1]."""
    delta = 2 * torch.rad2deg(torch.arccos(half_cos.clamp(0.0, 1.0)))
    xy = axis_landing(system, -delta / 2, delta / 2)
    radius = xy.norm(dim=-1)
    twist = torch.rad2deg(torch.atan2(xy[..., 1], xy[..., 0]))
    return radius, twist, delta


def exact_inverse(
    system: FoveaSystem, targets_mm, current_deg, tol_mm: float | None = None, max_iter: int = 40
) -> Tensor:
    """Phases that land the optical axis exactly on each target (non-paraxial model).

    Parameters
    ----------
    system : FoveaSystem
        Prisms and object distance.
    targets_mm : Tensor, shape (F, 2)
        Wanted landing points of the axis on the object plane, mm.
    current_deg : Tensor, shape (2,) or (F, 2)
        Phases to stay near: picks the branch and the turn (shortest rotation), and keeps the
        common rotation for a target at the centre.
    tol_mm : float, optional
        Radial tolerance of the root-find; default 1e-13 of the largest landing radius.
    max_iter : int
        Iteration cap of the safeguarded Newton root-find (it typically needs one step).

    Returns
    -------
    Tensor, shape (F, 2)
        [phi1, phi2] per target, degrees, float64.
    """
    t = _check_targets(targets_mm)
    current = _check_current(current_deg, t.shape[0])
    table_w, table_tan = _radius_table(system.prisms)
    v = system.object_distance_mm
    r_max = v * float(table_tan[-1])
    r_target = _radius_check(
        t.norm(dim=-1),
        r_max,
        f"the maximum deviation {math.degrees(math.atan(float(table_tan[-1]))):.6g} deg of the "
        f"prisms ({r_max:.6g} mm on the object plane at {v:g} mm)",
    )
    tol = 1e-13 * r_max if tol_mm is None else float(tol_mm)

    # Solve radius(w) = r_target for w = cos(delta / 2) in [0, 1]. The radius increases with w
    # and is nearly proportional to it (exactly so in the first-order model, r = 2 k w), which
    # makes w the right variable: the slope stays finite at the rim (w = 1), where it vanishes
    # in delta, and w keeps full precision at the centre (w = 0), where cos(delta) would not.
    # Start from the tabulated radius (linear interpolation, error ~1e-8 in w): then one
    # Newton step finishes, and one more trace gives the twist there.
    w = _interp(r_target / v, table_tan, table_w)
    lo, hi = torch.zeros_like(w), torch.ones_like(w)
    step = 1e-7
    for _ in range(max_iter):
        # One-sided difference toward the interior, so the probe stays within [0, 1].
        probe = w - step * torch.where(w > 0.5, 1.0, -1.0)
        radius, twist, _ = _relative_trace(system, torch.stack((w, probe)))
        f = radius[0] - r_target
        done = f.abs() <= tol
        if bool(done.all()):
            radius, twist = radius[0], twist[0]
            break
        lo = torch.where(f < 0, w, lo)
        hi = torch.where(f > 0, w, hi)
        slope = (radius[0] - radius[1]) / (w - probe)
        newton = w - f / torch.where(slope > 0, slope, torch.ones_like(slope))
        inside = (slope > 0) & (newton >= lo) & (newton <= hi)
        w_next = torch.where(done, w, torch.where(inside, newton, (lo + hi) / 2))
        converged = bool((inside | done).all()) and float((w_next - w).abs().max()) <= 1e-7
        w = w_next
        if converged:
            # Newton converges quadratically: after a step this small the radius is off by
            # ~|r''| dw^2 < 1e-14 r_max, so only the twist at the new w is still needed.
            radius, twist, _ = _relative_trace(system, w)
            break
    else:  # out of iterations: report the state of the last update, not the last probe
        radius, twist, _ = _relative_trace(system, w)
    delta = 2 * torch.rad2deg(torch.arccos(w.clamp(0.0, 1.0)))

    centre = r_target <= CENTRE_TOLERANCE * r_max
    azimuth = torch.rad2deg(torch.atan2(t[:, 1], t[:, 0]))
    # Near the centre the twist is the azimuth of a vanishing vector; it is bounded (below
    # 0.05 deg for a = 4 deg) and continuous until exactly zero radius, handled by ``centre``.
    twist = torch.where(radius > 0, twist, torch.zeros_like(twist))
    return _phases_from_relative(azimuth, delta, twist, centre, current)


# --------------------------------------------------------------------------------------------
# The paraxial model (coarse pointing, section 2.3)
# --------------------------------------------------------------------------------------------


def paraxial_inverse(prisms: Prisms, deviation_deg, azimuth_deg, current_deg) -> Tensor:
    """First-order pointing: each prism deviates by (n - 1) a toward its phase.

    Parameters
    ----------
    deviation_deg, azimuth_deg : Tensor, shape (F,)
        Wanted deviation Phi and azimuth Theta of the axis, degrees.
    current_deg : Tensor, shape (2,) or (F, 2)
        Phases to stay near (shortest rotation).

    Returns
    -------
    Tensor, shape (F, 2), degrees. Deviations beyond the exact maximum raise; those between the
    first-order maximum 2 (n - 1) a and the exact one are put on the first-order rim (the exact
    refinement then reaches them).
    """
    dev = torch.as_tensor(deviation_deg, dtype=torch.float64).reshape(-1)
    az = torch.as_tensor(azimuth_deg, dtype=torch.float64).reshape(-1)
    if dev.shape != az.shape or not (torch.isfinite(dev).all() and torch.isfinite(az).all()):
        raise HbisInputError("deviation and azimuth must be finite and of the same length")
    if bool((dev < 0).any()):
        raise HbisInputError("a deviation angle must not be negative")
    current = _check_current(current_deg, dev.shape[0])
    exact_max = max_deviation_deg(prisms)
    if float(dev.max()) > exact_max * (1.0 + RIM_TOLERANCE):
        raise HbisInputError(
            f"deviation {float(dev.max()):.6g} deg is beyond the maximum deviation "
            f"{exact_max:.6g} deg of the prisms"
        )
    per_prism = (prisms.refractive_index - 1.0) * prisms.wedge_angle_deg
    cos_half = (dev / (2 * per_prism)).clamp(max=1.0)
    delta = 2 * torch.rad2deg(torch.arccos(cos_half))
    centre = dev <= CENTRE_TOLERANCE * exact_max
    return _phases_from_relative(az, delta, torch.zeros_like(delta), centre, current)
