"""Reproduce the numbers of the paper's section 3.2 (h = 7, a = 4 deg) as a markdown table.

    python3 -m hbis_torch.scan.reproduce [--stride 1] [--out table.md]
    python3 -m hbis_torch.scan.reproduce --conventions --stride 8   # pixel AE conventions

Each configuration is one column: the paper's inverse with the stated n = 1.5, the same with
n = 1.5168 (N-BK7, which reproduces the paper's axis numbers), the exact inverse, and the
object-plane pixel convention for comparison. ``--stride 1`` evaluates every pixel of the
960 x 1280 sensor (a few minutes); larger strides use a dense subset that keeps the corners.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace

import torch

from hbis_torch.checks import bounded_int
from hbis_torch.config import FoveaSystem
from hbis_torch.errors import HbisInputError
from hbis_torch.io_utils import check_output_path
from hbis_torch.optics import exit_directions, land_on_plane, rays_at
from hbis_torch.optics.inverse import axis_landing
from hbis_torch.scan.alignment import axis_alignment_error, pixel_alignment_error, pixel_grid
from hbis_torch.scan.plan import phase_range_deg, plan_scan

EXAMPLES = ((5.0, 70.0), (45.0, 130.0), (80.0, 20.0))
PAPER = {  # section 3.2: phase range, axis AE max, pixel AE max, pixel AE mean
    (5.0, 70.0): (0.60, 0.0085, 0.56, 0.071),
    (45.0, 130.0): (0.60, 0.0061, 0.53, 0.070),
    (80.0, 20.0): (0.63, 0.0086, 0.49, 0.072),
}
CONFIGS = (  # label, method, refractive index, pixel convention
    ("paper inverse, n = 1.5", "paper", 1.5, "sensor"),
    ("paper inverse, n = 1.5168", "paper", 1.5168, "sensor"),
    ("exact inverse, n = 1.5", "exact", 1.5, "sensor"),
    ("paper inverse, n = 1.5, object-plane pixel AE", "paper", 1.5, "object"),
)
QUANTITIES = ("phase range [deg]", "axis AE max", "pixel AE max", "pixel AE mean")


def section_3_2(system: FoveaSystem, initial, method: str, convention: str, stride: int) -> tuple:
    """(largest phase range of the two prisms, axis AE max, pixel AE max, pixel AE mean)."""
    plan = plan_scan(system, 7, initial, method)
    pixel = pixel_alignment_error(system, plan, stride=stride, convention=convention)
    return (
        float(phase_range_deg(plan.phases_deg).max()),
        float(axis_alignment_error(system, plan).max()),
        pixel["max"],
        pixel["mean"],
    )


def table(system: FoveaSystem = FoveaSystem(), stride: int = 1, progress: bool = True) -> str:
    """The markdown table: one row per (example, quantity), one column per configuration."""
    results = {}
    for label, method, n, convention in CONFIGS:
        s = replace(system, prisms=replace(system.prisms, refractive_index=n))
        for initial in EXAMPLES:
            if progress:
                print(f"{label}: {initial}", file=sys.stderr, flush=True)
            results[label, initial] = section_3_2(s, initial, method, convention, stride)
    header = "| initial phases | quantity | paper | " + " | ".join(c[0] for c in CONFIGS) + " |"
    lines = [header, "|" + "---|" * (3 + len(CONFIGS))]
    for initial in EXAMPLES:
        for q, name in enumerate(QUANTITIES):
            fmt = "{:.2f}" if q in (0, 2) else "{:.4f}"
            cells = [fmt.format(results[c[0], initial][q]) for c in CONFIGS]
            if q == 1:
                cells = [f"{results[c[0], initial][q]:.2g}" if c[1] == "exact" else cell
                         for c, cell in zip(CONFIGS, cells)]
            paper = ("{:.2f}" if q in (0, 2) else "{:.4f}" if q == 1 else "{:.3f}").format(
                PAPER[initial][q])
            lines.append(f"| ({initial[0]:g}, {initial[1]:g}) | {name} | {paper} | "
                         + " | ".join(cells) + " |")
    grid = "every pixel" if stride == 1 else f"every {stride}th row and column plus the last"
    lines.append(f"\nh = 7, a = 4 deg; pixel AE over the 960 x 1280 sensor, {grid}.")
    return "\n".join(lines) + "\n"


def _pixel_variants(system: FoveaSystem, initial, stride: int) -> dict:
    """Pixel AE (max, mean) of the paper's plan under each candidate convention."""
    plan = plan_scan(system, 7, initial, "paper")
    phases, ref = plan.phases_deg, plan.reference_index
    u, v = pixel_grid(system, stride)
    rays = rays_at(system.camera, u[None, :], v[:, None])
    exits = exit_directions(rays, phases[:, 0, None, None], phases[:, 1, None, None],
                            system.prisms)  # (F, H', W', 3)
    landing = land_on_plane(exits, system.object_distance_mm)
    shift = landing - landing[ref]
    planned = plan.step_mm * plan.offsets[:, None, None, :]
    axis = axis_landing(system, phases[:, 0], phases[:, 1])
    angles = torch.atan2(exits[..., :2], exits[..., 2:])  # x and y angles of each exit ray
    step_rad = plan.step_mm / system.object_distance_mm
    errors = {
        "object plane, planned shift SL * offset": (shift - planned).norm(dim=-1) / plan.step_mm,
        "object plane, the axis's actual shift": (
            shift - (axis - axis[ref])[:, None, None, :]).norm(dim=-1) / plan.step_mm,
        "object plane, shift length only": (
            shift.norm(dim=-1) - planned.norm(dim=-1)).abs() / plan.step_mm,
        "exit-ray angles, planned angular step": (
            angles - angles[ref] - step_rad * plan.offsets[:, None, None, :]).norm(dim=-1)
        / step_rad,
    }
    out = {name: (float(e.max()), float(e.mean())) for name, e in errors.items()}
    sensor = pixel_alignment_error(system, plan, stride=stride, convention="sensor")
    out["sensor, exact back-trace (ours)"] = (sensor["max"], sensor["mean"])
    return out


def convention_study(system: FoveaSystem = FoveaSystem(), stride: int = 8) -> str:
    """Markdown table of the pixel AE under each candidate convention (and two layouts)."""
    cases = [("as docs/design.md", system, EXAMPLES)]
    transposed = replace(system, camera=replace(system.camera, rows=system.camera.cols,
                                                cols=system.camera.rows))
    cases.append(("sensor transposed (1280 x 960)", transposed, EXAMPLES))
    cases.append(("prisms swapped (phi1 <-> phi2)", system,
                  tuple((b, a) for a, b in EXAMPLES)))
    lines = ["| layout | convention | " + " | ".join(
        f"({a:g}, {b:g}) max / mean" for a, b in EXAMPLES) + " |", "|---|---|---|---|---|"]
    paper = " | ".join(f"{PAPER[e][2]:.2f} / {PAPER[e][3]:.3f}" for e in EXAMPLES)
    lines.append(f"| paper | - | {paper} |")
    for layout, s, examples in cases:
        rows = [_pixel_variants(s, e, stride) for e in examples]
        names = rows[0] if layout == "as docs/design.md" else ["sensor, exact back-trace (ours)"]
        for name in names:
            cells = " | ".join(f"{r[name][0]:.2f} / {r[name][1]:.3f}" for r in rows)
            lines.append(f"| {layout} | {name} | {cells} |")
    lines.append(f"\nPaper's inverse, n = 1.5, h = 7; every {stride}th pixel plus the last row "
                 "and column (the last row and column weigh a little more than on the full sensor).")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--stride", type=bounded_int(1, 65536), default=1, help="pixel stride (1: every pixel)")
    parser.add_argument("--conventions", action="store_true",
                        help="instead, compare the candidate pixel AE conventions")
    parser.add_argument("--out", help="also write the table to this file, with its provenance (command, commit, "
                        "date, machine)")
    argv = sys.argv[1:] if argv is None else list(argv)
    args = parser.parse_args(argv)
    if args.out:
        try:
            check_output_path(args.out)
        except HbisInputError as exc:
            parser.error(str(exc))
    if args.conventions:
        text = convention_study(stride=args.stride)
    else:
        text = table(stride=args.stride)
    print(text)
    if args.out:
        from hbis_torch.provenance import write_results

        write_results(args.out, text + "\n", argv=argv)
    return 0


if __name__ == "__main__":
    sys.exit(main())
