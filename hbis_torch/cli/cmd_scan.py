"""``hbis scan``: a sub-pixel scan plan and its alignment error (paper sections 2.2 and 3.2)."""

from __future__ import annotations

import json

from hbis_torch.errors import HbisInputError
from hbis_torch.checks import bounded_float, bounded_int
from hbis_torch.cli import examples
from hbis_torch.cli.common import H_ARG, add_system_args, system_from_args

# hbis_torch.scan's METHODS and CONVENTIONS, written out so that --help does not import torch
# (tests/test_cli_conventions.py checks that they agree).
METHODS = ("paper", "exact")
CONVENTIONS = ("sensor", "object")


def _pair(text: str, what: str) -> tuple[float, float]:
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        values = []
    if len(values) != 2:
        raise HbisInputError(f"{what} must be two numbers separated by a comma, got {text!r}")
    return values[0], values[1]


def register(sub) -> None:
    p = sub.add_parser(
        "scan",
        help="phases of an h x h sub-pixel scan and its alignment error (AE, fractions of SL)",
        description="Plan the h x h sub-pixel scan of the optical axis around the initial phases "
        "(raster order, x fastest) and report the phases, each prism's phase range, and the "
        "alignment error of the axis and of the pixels (paper section 3.2).",
        epilog=examples("hbis scan --h 7 --phases-deg 5,70", "hbis scan --h 4 --phases-deg 5,70 --steps-per-deg 80,80 --json"),
    )
    add_system_args(p)
    p.add_argument("--h", type=H_ARG, required=True, help="resolution improvement factor h (>= 1)")
    p.add_argument("--phases-deg", required=True, metavar="PHI1,PHI2",
                   help="initial phases of the two prisms in degrees, e.g. 5,70")
    p.add_argument("--method", choices=METHODS, default="exact",
                   help="inverse solution: the paper's eqs. 8-9 or the exact one (default)")
    p.add_argument("--pixel-stride", type=bounded_int(1, 65536), default=4,
                   help="pixel AE on every k-th row and column plus the last ones "
                   "(1: every pixel of the sensor, slower; default 4)")
    p.add_argument("--pixel-convention", choices=CONVENTIONS, default="sensor",
                   help="pixel AE measured as the sample's shift on the sensor (default, as the "
                   "paper) or on the object plane")
    p.add_argument("--steps-per-deg", metavar="S1,S2",
                   help="also report the axis AE with phases rounded to these motor steps/deg")
    p.add_argument("--ae-bound", type=bounded_float(0.0, 1000.0, lo_open=True),
                   help="also report the motor steps/deg that keep the axis AE under this bound")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(func=run)


def run(args) -> int:
    from hbis_torch.scan import plan_scan, scan_report, step_alignment_error
    from hbis_torch.scan.motor_steps import required_steps_per_deg

    system = system_from_args(args)
    initial = _pair(args.phases_deg, "--phases-deg")
    plan = plan_scan(system, args.h, initial, args.method)
    report = scan_report(system, plan, stride=args.pixel_stride, convention=args.pixel_convention)
    if args.steps_per_deg:
        steps = step_alignment_error(system, plan, _pair(args.steps_per_deg, "--steps-per-deg"))
        report["steps_per_deg"] = steps["steps_per_deg"]
        report["ae_axis_max_quantised"] = steps["ae_axis_max"]
        report["ae_axis_mean_quantised"] = steps["ae_axis_mean"]
        report["quantised_phases_deg"] = steps["quantised_phases_deg"].tolist()
    if args.ae_bound is not None:
        report["ae_bound"] = args.ae_bound
        report["required_steps_per_deg"] = required_steps_per_deg(
            system, args.h, initial, args.ae_bound, args.method
        )
    if args.json:
        print(json.dumps(report, indent=2))
        return 0
    print(f"h = {plan.h}, {plan.frames} frames, step SL = {plan.step_mm * 1e3:.4f} um, "
          f"initial phases {initial}, method {plan.method}")
    for i, (p1, p2) in enumerate(report["phases_deg"]):
        off = plan.offsets[i].tolist()
        print(f"  frame {i:3d}  offset ({off[0]:+.0f}, {off[1]:+.0f})  phases {p1:10.5f} {p2:10.5f}")
    for key, value in report.items():
        if key in ("phases_deg", "quantised_phases_deg", "initial_phases_deg", "h", "method"):
            continue
        if isinstance(value, float):
            value = f"{value:.6g}"
        elif isinstance(value, list) and value and isinstance(value[0], float):
            value = ", ".join(f"{v:.6g}" for v in value)
        print(f"{key:28s} {value}")
    return 0
