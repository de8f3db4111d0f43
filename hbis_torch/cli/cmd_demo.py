"""``hbis demo``: the pipeline on built-in defaults, with a short report."""

from __future__ import annotations

import json
from pathlib import Path

from ..config import System
from ..design import design
from ..io_utils import atomic_write_text
from .cmd_figures import FIGURE_SETS


def register(sub) -> None:
    p = sub.add_parser(
        "demo",
        help="run the pipeline on built-in defaults and write a short report",
        description="Run everything on the paper's Table 1 defaults: the design numbers and the "
        "paper's figures, written to --out with a report.",
    )
    p.add_argument("--out", default="hbis-out", help="output folder (default: ./hbis-out)")
    p.set_defaults(func=run)


def run(args) -> int:
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    system = System()
    report = design(system).to_dict()
    prototype = design(system, varphi_h_deg=15.0, varphi_v_deg=10.0, h=4).to_dict()
    figures = [str(p) for make in FIGURE_SETS.values() for p in make(out / "figures", system)]
    summary = {"design_at_limits": report, "prototype_15_10_h4": prototype, "figures": figures}
    atomic_write_text(out / "report.json", json.dumps(summary, indent=2))
    print("HBIS design, Table 1 defaults (a = 4 deg, n = 1.5):")
    print(f"  one camera sees   {report['single_fov_h_deg']:.1f} x {report['single_fov_v_deg']:.1f} deg")
    print(f"  varphi limits     h <= {report['varphi_h_max_deg']:.2f} deg, v <= {report['varphi_v_max_deg']:.2f} deg")
    print(f"  whole FOV         {report['fov_h_deg']:.1f} x {report['fov_v_deg']:.1f} deg, "
          f"FER_h = {report['fer_h']:.2f}, FER_v = {report['fer_v']:.2f}")
    print(f"  diffraction       H = {report['H']:.2f}, so 1 <= h <= {report['h_max']}")
    print(f"  BSR               h=4: {report['bsr']['4']:.3f}, h={report['h_max']}: "
          f"{report['bsr'][str(report['h_max'])]:.3f}")
    print(f"  prototype (15, 10 deg): varphi_c = {prototype['varphi_c_deg']:.2f} deg, "
          f"FER_h = {prototype['fer_h']:.2f}, FER_v = {prototype['fer_v']:.2f}")
    print(f"wrote {out / 'report.json'} and {len(figures)} figures under {out / 'figures'}")
    return 0
