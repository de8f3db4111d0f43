"""Figures 4, 6 and 10 of the paper: FOV/FER and BSR against the prism parameters, and the FOV
layout of the array with the fovea's scan field."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from matplotlib.figure import Figure
from tqdm import tqdm

from hbis_torch.system.array.geometry import array_rotations
from hbis_torch.config import FoveaSystem
from hbis_torch.design import bsr, half_fov_deg, limit_sweep, with_prisms
from hbis_torch.optics.risley import exit_directions

ALPHAS = np.arange(1.0, 15.01, 0.25)
INDICES = np.arange(1.3, 3.001, 0.025)


def _sweeps(system: FoveaSystem, progress: bool) -> dict:
    bar = tqdm(total=2, desc="design sweeps", disable=not progress)
    out = {}
    for key, param, values in (
        ("alpha", "wedge_angle_deg", ALPHAS),
        ("n", "refractive_index", INDICES),
    ):
        base = with_prisms(system, refractive_index=1.5) if key == "alpha" else with_prisms(
            system, wedge_angle_deg=4.0)
        out[key] = (values, limit_sweep(base, param, values))
        bar.update()
    bar.close()
    return out


def figure_4(system: FoveaSystem, sweeps: dict, path: Path) -> Path:
    """Whole FOV and FER (shaded between varphi = theta and the upper limit) vs alpha and n.

    FER = FOV / (2 theta) in each direction, so the two are one curve: it is drawn once (red,
    the FOV on the left axis) and the right axis reads the same curve in FER."""
    theta = dict(zip("hv", half_fov_deg(system.camera)))
    fig = Figure(figsize=(11, 8))
    axes = fig.subplots(2, 2)
    panels = [("alpha", "v", "(a) vertical, n = 1.5"), ("alpha", "h", "(b) horizontal, n = 1.5"),
              ("n", "v", "(c) vertical, a = 4 deg"), ("n", "h", "(d) horizontal, a = 4 deg")]
    for ax, (key, d, title) in zip(axes.flat, panels):
        x, s = sweeps[key]
        fov_hi = np.array(s[f"fov_{d}"])
        fov_lo = np.full_like(fov_hi, 4 * theta[d])
        ax.fill_between(x, fov_lo, fov_hi, color="tab:red", alpha=0.25, label="whole FOV range")
        ax.plot(x, fov_hi, color="tab:red")
        ax.set_xlabel("wedge angle a [deg]" if key == "alpha" else "refractive index n")
        ax.set_ylabel("whole FOV [deg]", color="tab:red")
        ax.tick_params(axis="y", colors="tab:red")
        two_theta = 2 * theta[d]
        ax2 = ax.secondary_yaxis("right", functions=(lambda f, t=two_theta: f / t, lambda r, t=two_theta: r * t))
        ax2.set_ylabel("FER = FOV / 2θ (same curve)")
        ax.legend(fontsize=8, loc="upper left")
        ax.set_title(title)
        ax.grid(alpha=0.3)
    fig.suptitle("Fig. 4: whole FOV and FOV extension ratio")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    return path


def figure_6(sweeps: dict, path: Path, h_values=range(2, 8)) -> Path:
    """BSR (at the FER upper limits) against alpha and n, one curve per h."""
    fig = Figure(figsize=(11, 4.2))
    axes = fig.subplots(1, 2)
    for ax, key, label in ((axes[0], "alpha", "wedge angle a [deg] (n = 1.5)"),
                           (axes[1], "n", "refractive index n (a = 4 deg)")):
        x, s = sweeps[key]
        for h in h_values:
            y = [bsr(h, fh, fv) for fh, fv in zip(s["fer_h"], s["fer_v"])]
            ax.plot(x, y, label=f"h = {h}")
        ax.set_xlabel(label)
        ax.set_ylabel("BSR")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    axes[0].set_title("(a)")
    axes[1].set_title("(b)")
    fig.suptitle("Fig. 6: bandwidth saving ratio")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    return path


def _border_rays(system: FoveaSystem, per_side: int = 40) -> torch.Tensor:
    cam = system.camera
    hw = (cam.cols - 1) / 2 * cam.pitch_mm
    hh = (cam.rows - 1) / 2 * cam.pitch_mm
    t = torch.linspace(-1.0, 1.0, per_side, dtype=torch.float64)
    xs = torch.cat((t * hw, torch.full_like(t, hw), -t * hw, torch.full_like(t, -hw)))
    ys = torch.cat((torch.full_like(t, -hh), t * hh, torch.full_like(t, hh), -t * hh))
    rays = torch.stack((xs, ys, torch.full_like(xs, cam.focal_length_mm)), -1)
    return rays / rays.norm(dim=-1, keepdim=True)


def _to_angles(d: torch.Tensor) -> np.ndarray:
    """Horizontal and vertical projected angles in degrees (vertical positive upward)."""
    h = torch.rad2deg(torch.atan2(d[..., 0], d[..., 2]))
    v = -torch.rad2deg(torch.atan2(d[..., 1], d[..., 2]))
    return torch.stack((h, v), -1).numpy()


def figure_10(system: FoveaSystem, path: Path, cases=((18.4, 12.9, 4.0), (11.3, 8.5, 11.0))) -> Path:
    """FOV of the eight periphery cameras and the scan field of the fovea, per design case."""
    fig = Figure(figsize=(6.2 * len(cases), 5))
    axes = fig.subplots(1, len(cases))
    rays = _border_rays(system)
    for ax, (vh, vv, alpha), tag in zip(np.atleast_1d(axes), cases, "abcdef"):
        s = with_prisms(system, wedge_angle_deg=alpha)
        for (r, c), rot in array_rotations(vh, vv).items():
            if (r, c) == (2, 2):
                continue
            poly = _to_angles(rays @ rot.T)
            ax.fill(poly[:, 0], poly[:, 1], alpha=0.12, color="tab:blue")
            ax.plot(poly[:, 0], poly[:, 1], color="tab:blue", lw=1)
            ax.text(*poly.mean(0), f"C{r}{c}", ha="center", va="center", fontsize=8, zorder=5,
                    bbox={"boxstyle": "round,pad=0.15", "fc": "white", "ec": "none", "alpha": 0.85})
        phases = torch.arange(0.0, 360.0, 7.5, dtype=torch.float64)
        fovea = exit_directions(rays, phases[:, None], phases[:, None], s.prisms)
        for poly in _to_angles(fovea):
            ax.plot(poly[:, 0], poly[:, 1], color="tab:red", lw=0.5, alpha=0.5)
        axis = exit_directions(torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64),
                               phases, phases, s.prisms)
        ring = _to_angles(axis)
        ax.plot(ring[:, 0], ring[:, 1], "k--", lw=1, label="fovea axis at full deviation")
        ax.plot([], [], color="tab:red", lw=1, label="fovea FOV, prisms aligned (scan field)")
        ax.set_aspect("equal")
        ax.set_xlabel("horizontal angle [deg]")
        ax.set_ylabel("vertical angle [deg]")
        ax.set_title(f"({tag}) $\\varphi_h$ = {vh}°, $\\varphi_v$ = {vv}°, a = {alpha}°")
        ax.set_axisbelow(True)
        ax.grid(alpha=0.3, zorder=0)
        ax.legend(fontsize=7, loc="lower right")
    fig.suptitle("Fig. 10: FOV of the periphery cameras and the fovea's scan field")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    return path


def make_figures(out_dir, system: FoveaSystem = FoveaSystem(), progress: bool = True) -> list[Path]:
    """Write fig4.png, fig6.png and fig10.png into ``out_dir``; returns their paths."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    sweeps = _sweeps(system, progress)
    return [
        figure_4(system, sweeps, out / "fig4_fov_fer.png"),
        figure_6(sweeps, out / "fig6_bsr.png"),
        figure_10(system, out / "fig10_fov_layout.png"),
    ]
