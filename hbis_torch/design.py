"""The HBIS design calculator (paper sections 2.1, 2.2, 3.1 and 3.3).

All angles in degrees. The periphery cameras sit at (+-varphi_h, 0) and (0, +-varphi_v) from the
fovea's original axis, the corner ones at varphi_c. Names follow the paper:

- theta_h, theta_v: half FOV of one camera (to the sensor's outer edge).
- Phi_hmin, Phi_vmin: with both prisms aligned so that the fovea is deviated as far as it goes
  away from a periphery camera, the smallest angle between the fovea's near FOV edge and the
  original axis (traced exactly over that whole edge column or row, as the paper does).
- varphi_max: the largest inclination with no blind zone. Eq. (2) gives Phi_min + theta; once
  Phi_min <= 0 (the inflection: the fovea's scan field covers the middle) only the overlap of the
  two opposite periphery cameras binds, varphi <= theta, so FER = 2. Eq. (1) caps it at 2 theta.
- FOV = 2 (varphi + theta), FER = FOV / (2 theta), varphi_c = atan(sqrt(tan^2 varphi_v + tan^2
  varphi_h)), H = v_o / v_p with v_o = D / (1.22 lambda f') and v_p = 1 / (2 p), h_max = floor(H),
  BSR(h) = (1 - 1/h^2)(1 - 1/(FER_v FER_h)) (eq. 10), foveal ratio = h.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, replace

import torch

from hbis_torch.config import Camera, Prisms, FoveaSystem
from hbis_torch.checks import MAX_H, check_h
from hbis_torch.errors import HbisInputError
from hbis_torch.optics.risley import exit_directions


def half_fov_deg(camera: Camera) -> tuple[float, float]:
    """(theta_h, theta_v): half FOV of one camera to the sensor's outer edge, degrees."""
    return camera.half_fov_h_deg, camera.half_fov_v_deg


def phi_min_deg(system: FoveaSystem, direction: str) -> float:
    """Phi_hmin (direction 'h') or Phi_vmin ('v'), by exact tracing of a whole sensor edge.

    The prisms are aligned at 180 deg (deviating toward -x) or 270 deg (toward -y); the near edge
    is then the +x column or the +y row, and the result is the smallest projected angle
    atan(R_x / R_z) (or R_y / R_z) over that edge's pixel centres. Negative once the fovea's near
    edge has crossed the original axis (past the inflection).
    """
    cam = system.camera
    p, f = cam.pitch_mm, cam.focal_length_mm
    if direction == "h":
        across = (torch.arange(cam.rows, dtype=torch.float64) - (cam.rows - 1) / 2) * p
        edge = torch.full_like(across, (cam.cols - 1) / 2 * p)
        rays = torch.stack((edge, across, torch.full_like(edge, f)), dim=-1)
        phase, component = 180.0, 0
    elif direction == "v":
        across = (torch.arange(cam.cols, dtype=torch.float64) - (cam.cols - 1) / 2) * p
        edge = torch.full_like(across, (cam.rows - 1) / 2 * p)
        rays = torch.stack((across, edge, torch.full_like(edge, f)), dim=-1)
        phase, component = 270.0, 1
    else:
        raise HbisInputError(f"direction must be 'h' or 'v', got {direction!r}")
    rays = rays / rays.norm(dim=-1, keepdim=True)
    out = exit_directions(rays, phase, phase, system.prisms)
    angle = torch.rad2deg(torch.atan2(out[:, component], out[:, 2]))
    return float(angle.min())


def varphi_limit_deg(phi_min: float, theta: float) -> float:
    """Largest periphery inclination with no blind zone (eqs. 1, 2 and the inflection)."""
    return min(max(phi_min + theta, theta), 2.0 * theta)


def varphi_c_deg(varphi_h: float, varphi_v: float) -> float:
    """Inclination of the corner cameras' axes."""
    th, tv = math.tan(math.radians(varphi_h)), math.tan(math.radians(varphi_v))
    return math.degrees(math.atan(math.hypot(th, tv)))


def diffraction_ratio(camera: Camera) -> float:
    """H = v_o / v_p: how many times the optics' cutoff exceeds the pixel Nyquist frequency."""
    v_o = camera.pupil_diameter_mm / (1.22 * camera.wavelength_nm * 1e-6 * camera.focal_length_mm)
    v_p = 1.0 / (2.0 * camera.pitch_mm)
    return v_o / v_p


def bsr(h: int, fer_h: float, fer_v: float) -> float:
    """Bandwidth saving ratio of eq. (10)."""
    h = check_h(h)
    return (1.0 - 1.0 / h**2) * (1.0 - 1.0 / (fer_v * fer_h))


@dataclass
class DesignReport:
    """Every design number of the paper for one system (angles in degrees).

    ``diffraction_ratio`` is the paper's H (the largest useful resolution improvement before
    diffraction takes over); ``h`` is the factor chosen (default ``h_max`` = floor(H)).
    """

    theta_h_deg: float
    theta_v_deg: float
    single_fov_h_deg: float
    single_fov_v_deg: float
    max_axis_deviation_deg: float
    phi_min_h_deg: float
    phi_min_v_deg: float
    varphi_h_max_deg: float
    varphi_v_max_deg: float
    inflection_h: bool
    inflection_v: bool
    varphi_h_deg: float
    varphi_v_deg: float
    blind_zone_h: bool
    blind_zone_v: bool
    fov_h_deg: float
    fov_v_deg: float
    fer_h: float
    fer_v: float
    varphi_c_deg: float
    diffraction_ratio: float
    h_max: int
    h: int
    foveal_ratio: int
    bsr: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        """The numbers by the paper's names: the diffraction ratio is ``"H"`` (docs/design.md
        section 2)."""
        out = asdict(self)
        out["H"] = out.pop("diffraction_ratio")
        return out


def design(
    system: FoveaSystem = FoveaSystem(),
    varphi_h_deg: float | None = None,
    varphi_v_deg: float | None = None,
    h: int | None = None,
) -> DesignReport:
    """Compute the design numbers; without varphi the maxima (no blind zone) are used.

    ``h`` (default h_max) sets the foveal ratio. A varphi above its maximum is allowed but
    flagged as ``blind_zone_h/v``: the fovea can then leave a gap beside that periphery camera.

    Examples
    --------
    The paper's Table 1 system (the defaults):

    >>> from hbis_torch import FoveaSystem
    >>> from hbis_torch.design import design
    >>> report = design(FoveaSystem())
    >>> round(report.diffraction_ratio, 2), report.h_max
    (7.98, 7)
    >>> round(report.max_axis_deviation_deg, 3)
    4.008
    >>> design(FoveaSystem(), h=4).foveal_ratio
    4
    """
    for name, value in (("varphi_h", varphi_h_deg), ("varphi_v", varphi_v_deg)):
        if value is not None and (not math.isfinite(value) or not 0 <= value < 90):
            raise HbisInputError(f"{name} must lie in [0, 90) degrees, got {value!r}")
    theta_h, theta_v = half_fov_deg(system.camera)
    phi_h, phi_v = phi_min_deg(system, "h"), phi_min_deg(system, "v")
    lim_h, lim_v = varphi_limit_deg(phi_h, theta_h), varphi_limit_deg(phi_v, theta_v)
    vh = lim_h if varphi_h_deg is None else float(varphi_h_deg)
    vv = lim_v if varphi_v_deg is None else float(varphi_v_deg)
    fer_h, fer_v = (vh + theta_h) / theta_h, (vv + theta_v) / theta_v
    big_h = diffraction_ratio(system.camera)
    h_max = max(1, math.floor(big_h))
    h = min(h_max, MAX_H) if h is None else check_h(h)
    axis = exit_directions(torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64), 0.0, 0.0, system.prisms)
    max_dev = math.degrees(math.atan2(math.hypot(axis[0], axis[1]), axis[2]))
    return DesignReport(
        theta_h_deg=theta_h,
        theta_v_deg=theta_v,
        single_fov_h_deg=2 * theta_h,
        single_fov_v_deg=2 * theta_v,
        max_axis_deviation_deg=max_dev,
        phi_min_h_deg=phi_h,
        phi_min_v_deg=phi_v,
        varphi_h_max_deg=lim_h,
        varphi_v_max_deg=lim_v,
        inflection_h=phi_h <= 0,
        inflection_v=phi_v <= 0,
        varphi_h_deg=vh,
        varphi_v_deg=vv,
        blind_zone_h=vh > lim_h + 1e-12,
        blind_zone_v=vv > lim_v + 1e-12,
        fov_h_deg=2 * (vh + theta_h),
        fov_v_deg=2 * (vv + theta_v),
        fer_h=fer_h,
        fer_v=fer_v,
        varphi_c_deg=varphi_c_deg(vh, vv),
        diffraction_ratio=big_h,
        h_max=h_max,
        h=h,
        foveal_ratio=h,
        bsr={str(k): bsr(k, fer_h, fer_v) for k in range(1, min(h_max, MAX_H) + 1)},
    )


def with_prisms(system: FoveaSystem, **changes) -> FoveaSystem:
    """A copy of ``system`` with prism parameters changed (used by the sweeps)."""
    return replace(system, prisms=replace(system.prisms, **changes))


def limit_sweep(system: FoveaSystem, parameter: str, values) -> dict[str, list[float]]:
    """varphi maxima, whole FOV and FER (at the maxima) against 'wedge_angle_deg' or
    'refractive_index'; each list matches ``values``."""
    if parameter not in ("wedge_angle_deg", "refractive_index"):
        raise HbisInputError(f"cannot sweep {parameter!r}")
    theta_h, theta_v = half_fov_deg(system.camera)
    out: dict[str, list[float]] = {k: [] for k in ("varphi_h", "varphi_v", "fov_h", "fov_v", "fer_h", "fer_v")}
    for value in values:
        s = with_prisms(system, **{parameter: float(value)})
        for d, theta in (("h", theta_h), ("v", theta_v)):
            lim = varphi_limit_deg(phi_min_deg(s, d), theta)
            out[f"varphi_{d}"].append(lim)
            out[f"fov_{d}"].append(2 * (lim + theta))
            out[f"fer_{d}"].append((lim + theta) / theta)
    return out


__all__ = [
    "DesignReport",
    "Prisms",
    "bsr",
    "design",
    "diffraction_ratio",
    "half_fov_deg",
    "limit_sweep",
    "phi_min_deg",
    "varphi_c_deg",
    "varphi_limit_deg",
    "with_prisms",
]
