"""Figures 3 and 5 of the paper: the sub-pixel scan patterns, and the maximum alignment error of
the optical axis (the paper's inverse, eqs. 8-9) against the initial phases, the wedge angle and
the refractive index. Also a map of the pixel alignment error over the sensor."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure
from tqdm import tqdm

from hbis_torch.config import FoveaSystem
from hbis_torch.errors import HbisInputError
from hbis_torch.io_utils import atomic_path
from hbis_torch.scan import axis_alignment_error, pixel_alignment_error, plan_scan, scan_offsets

EXAMPLES = ((5.0, 70.0), (45.0, 130.0), (80.0, 20.0))
PHI1_CURVES = (5.0, 45.0, 80.0)
ALPHAS = np.arange(1.0, 15.01, 0.5)
INDICES = np.arange(1.3, 2.501, 0.05)


def max_axis_ae(system: FoveaSystem, h: int, initial, method: str = "paper") -> float | None:
    """Largest axis AE of a plan (fractions of SL), or None where the plan is impossible (the
    scan would leave the reachable disc, or eq. 8 breaks down)."""
    try:
        plan = plan_scan(system, h, initial, method)
    except HbisInputError:
        return None
    return float(axis_alignment_error(system, plan).max())


def _gaps(values) -> np.ndarray:
    """Curve values with the impossible points (None) as gaps for matplotlib."""
    return np.array([np.nan if v is None else v for v in values], dtype=float)


def _save(fig, path: Path) -> Path:
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    return path


def figure_3(path: Path) -> Path:
    """Scan patterns for h = 5 (odd) and h = 4 (even): points numbered in scan order."""
    fig = Figure(figsize=(10, 4.8))
    axes = fig.subplots(1, 2)
    for ax, h, tag in zip(axes, (5, 4), "ab"):
        offsets, ref = scan_offsets(h)
        xy = offsets.numpy()
        ax.plot(xy[:, 0], xy[:, 1], color="0.7", lw=0.8, zorder=1)
        colours = ["tab:purple"] * len(xy)
        colours[ref] = "tab:green"
        ax.scatter(xy[:, 0], xy[:, 1], s=420, c=colours, zorder=2)
        for i, (x, y) in enumerate(xy):
            ax.text(x, y, str(i), ha="center", va="center", color="white", fontsize=9)
        ax.set_aspect("equal")
        ax.set_xlabel("x offset [SL]")
        ax.set_ylabel("y offset [SL]")
        ax.set_title(f"({tag}) h = {h}: frame {ref} at the initial phases")
        ax.grid(alpha=0.3)
    fig.suptitle("Fig. 3: sub-pixel scan patterns (raster, x fastest; frames numbered from 0, as in hbis scan and the stack)")
    fig.tight_layout()
    return _save(fig, path)


def figure_5(system: FoveaSystem, path: Path, h: int = 7, progress: bool = True) -> Path:
    """Maximum axis AE of the paper's inverse vs (a) phi2 for three phi1, (b) the wedge angle,
    (c) the refractive index; the exact inverse's largest value is quoted on each panel."""
    phi2 = np.arange(0.0, 360.0, 1.0)
    bar = tqdm(total=len(PHI1_CURVES) * len(phi2) + 2 * len(EXAMPLES) * (len(ALPHAS) + len(INDICES)),
               desc="Fig. 5 scans", disable=not progress)
    fig = Figure(figsize=(16, 4.6))
    axes = fig.subplots(1, 3)
    exact_worst = 0.0

    ax = axes[0]
    for phi1 in PHI1_CURVES:
        values = []
        for p2 in phi2:
            singular = np.isclose((p2 - phi1) % 180.0, 0.0)
            values.append(None if singular else max_axis_ae(system, h, (phi1, p2)))
            bar.update()
        line, = ax.plot(phi2, _gaps(values), label=f"$\\phi_1$ = {phi1:g}°")
        for p2 in ((phi1 % 360), (phi1 + 180) % 360):  # avoided, as in the paper: circles
            ax.plot([p2], [0.0], "o", mfc="none", ms=9, color=line.get_color())
        exact_worst = max(exact_worst, max_axis_ae(system, h, (phi1, phi1 + 65.0), "exact") or 0.0)
    ax.set_xlabel(r"$\phi_2$ [deg]")
    ax.set_ylabel("maximum axis AE [SL]")
    ax.set_title("(a) initial phases (a = %g deg, n = %g)"
                 % (system.prisms.wedge_angle_deg, system.prisms.refractive_index))

    for ax, param, values, label, title in (
        (axes[1], "wedge_angle_deg", ALPHAS, "wedge angle a [deg]", "(b) wedge angle (n = %g)"
         % system.prisms.refractive_index),
        (axes[2], "refractive_index", INDICES, "refractive index n", "(c) refractive index "
         "(a = %g deg)" % system.prisms.wedge_angle_deg),
    ):
        # Distinct line styles and widths, widest first: curves that coincide stay visible.
        styles = (("-", "o", 3.2), ("--", "s", 2.0), (":", "^", 1.2))
        for initial, (style, mark, width) in zip(EXAMPLES, styles):
            ys = []
            for value in values:
                s = replace(system, prisms=replace(system.prisms, **{param: float(value)}))
                ys.append(max_axis_ae(s, h, initial))
                exact_worst = max(exact_worst, max_axis_ae(s, h, initial, "exact") or 0.0)
                bar.update(2)
            ax.plot(values, _gaps(ys), linestyle=style, lw=width, marker=mark, ms=3.5, markevery=4,
                    label=f"initial ({initial[0]:g}, {initial[1]:g})")
        ax.set_xlabel(label)
        ax.set_ylabel("maximum axis AE [SL]")
        ax.set_title(title)
    bar.close()
    for ax in axes:
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
        ax.text(0.02, 0.97, f"exact inverse: max AE {exact_worst:.1e}", transform=ax.transAxes,
                va="top", fontsize=8, color="0.3")
    fig.suptitle(f"Fig. 5: maximum alignment error of the optical axis, paper's inverse, h = {h}")
    fig.tight_layout()
    return _save(fig, path)


def figure_pixel_map(system: FoveaSystem, path: Path, h: int = 7, stride: int = 8) -> Path:
    """Each pixel's largest AE over the scan (sensor convention), for the three examples."""
    fig = Figure(figsize=(16, 4.2))
    axes = fig.subplots(1, len(EXAMPLES))
    for ax, initial in zip(axes, EXAMPLES):
        plan = plan_scan(system, h, initial, method="paper")
        result = pixel_alignment_error(system, plan, stride=stride)
        u, v = result["u"].numpy(), result["v"].numpy()
        im = ax.pcolormesh(u, v, result["worst_map"].numpy(), shading="nearest", cmap="magma")
        ax.invert_yaxis()
        ax.set_aspect("equal")
        ax.set_title(f"({initial[0]:g}, {initial[1]:g}): max {result['max']:.2f}, "
                     f"mean {result['mean']:.3f}")
        ax.set_xlabel("column u [px]")
        ax.set_ylabel("row v [px]")
        fig.colorbar(im, ax=ax, label="AE [SL]")
    fig.suptitle(f"Pixel alignment error, worst over the {h}x{h} scan (every {stride}th pixel)")
    fig.tight_layout()
    return _save(fig, path)


def make_figures(out_dir, system: FoveaSystem = FoveaSystem(), progress: bool = True) -> list[Path]:
    """Write fig3_scan_patterns.png, fig5_max_ae.png and scan_pixel_ae.png into ``out_dir``."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    return [
        figure_3(out / "fig3_scan_patterns.png"),
        figure_5(system, out / "fig5_max_ae.png", progress=progress),
        figure_pixel_map(system, out / "scan_pixel_ae.png"),
    ]


