"""``hbis design``: the design calculator."""

from __future__ import annotations

import json

from hbis_torch.checks import bounded_float
from hbis_torch.cli import examples
from hbis_torch.cli.common import H_ARG, add_system_args, system_from_args


def register(sub) -> None:
    p = sub.add_parser(
        "design",
        help="FOV extension, FER, varphi limits, varphi_c, H, h_max and BSR of an HBIS",
        description="Compute the design numbers of an HBIS (paper sections 2.1-3.3). Without "
        "--varphi-h-deg/--varphi-v-deg the largest inclinations with no blind zone are used.",
        epilog=examples("hbis design", "hbis design --json --varphi-h-deg 15 --varphi-v-deg 10 --h 4"),
    )
    add_system_args(p)
    p.add_argument("--varphi-h-deg", type=bounded_float(0.0, 90.0, hi_open=True), help="inclination of the left/right cameras [deg]")
    p.add_argument("--varphi-v-deg", type=bounded_float(0.0, 90.0, hi_open=True), help="inclination of the upper/lower cameras [deg]")
    p.add_argument("--h", type=H_ARG, help="resolution improvement factor (default: h_max)")
    p.add_argument("--json", action="store_true", help="print one JSON object instead of a table")
    p.set_defaults(func=run)


def run(args) -> int:
    from hbis_torch.design import design

    report = design(system_from_args(args), args.varphi_h_deg, args.varphi_v_deg, args.h)
    data = report.to_dict()
    if args.json:
        print(json.dumps(data, indent=2))
        return 0
    for key, value in data.items():
        if key == "bsr":
            value = ", ".join(f"h={h}: {v:.3f}" for h, v in value.items())
        elif isinstance(value, float):
            value = f"{value:.4f}"
        print(f"{key:24s} {value}")
    return 0
