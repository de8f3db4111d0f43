"""``hbis demo``: the whole pipeline on built-in defaults, with a one-page HTML report."""

from __future__ import annotations

import argparse
import json
import logging
import time
from pathlib import Path

from hbis_torch.config import FoveaSystem
from hbis_torch.errors import HbisInputError
from hbis_torch.io_utils import atomic_write_text, check_output_dir
from hbis_torch.checks import bounded_float, bounded_int
from hbis_torch.cli.common import SEED_ARG
from hbis_torch.cli import examples
from hbis_torch.cli.cmd_figures import FIGURE_SET_NAMES, add_figure_sets_arg, figure_set


def _roi_elsewhere(text: str):
    """``hbis demo --roi``: refused, naming --roi-size (--roi is U0,V0,WIDTH,HEIGHT in every command
    that takes it; the demo steers the fovea itself and takes only the ROI's side)."""
    import argparse

    raise argparse.ArgumentTypeError("the demo takes the side of the fovea's ROI as --roi-size PX (--roi is "
                                     "U0,V0,WIDTH,HEIGHT in hbis simulate, assemble and motors scan)")


def register(sub) -> None:
    p = sub.add_parser(
        "demo",
        help="run the whole HBIS chain on built-in defaults and write an HTML report",
        description="Run everything on the paper's Table 1 defaults: the design numbers and figures; a "
        "simulated 3 x 3 array (assembly errors like the prototype's) watching a wall of photographs; "
        "stitching with refinement from the images; the two-stage loop (detect, steer the fovea, scan, "
        "super-resolve); the foveated composite; FER, foveal ratio and BSR from the data. Writes PNGs, "
        "report.json and report.html into --out.",
        epilog=examples("hbis demo --out hbis-out", "hbis demo --design-only --figure-sets design --out hbis-design"),
    )
    p.add_argument("--out", default="hbis-out", help="output folder (default: ./hbis-out)")
    from hbis_torch.reconstruct.registry import METHODS

    p.add_argument("--method", choices=tuple(METHODS), default="learned",
                   help="super-resolution method, as hbis reconstruct's (default: learned, "
                   "the shipped ONNX model run in onnxruntime)")
    p.add_argument("--model", default=None, metavar="fast|best|M.onnx",
                   help="for a method that takes a model (learned), as hbis reconstruct's: 'fast' (the default), "
                   "'best' or an ONNX model file")
    p.add_argument("--h", type=bounded_int(1, 7), default=4, help="resolution improvement factor (default: 4)")
    p.add_argument("--roi-size", type=bounded_int(16, 960), default=160, metavar="PX",
                   help="side of the fovea's square ROI in pixels (default: 160)")
    p.add_argument("--roi", type=_roi_elsewhere, help=argparse.SUPPRESS)
    p.add_argument("--seed", type=SEED_ARG, default=3, help="seed of the assembly errors (default: 3)")
    p.add_argument("--assembly-error-deg", type=bounded_float(0.0, 5.0), default=0.7,
                   help="rms misalignment of the side cameras, deg (default: 0.7; 0 = perfect)")
    p.add_argument("--no-refine", action="store_true", help="stitch with the design angles only")
    p.add_argument("--threads", type=bounded_int(1, 1024), default=1,
                   help="torch threads (default: 1; the chain is many small tensor operations, for which "
                   "thread hand-offs cost more than they save)")
    add_figure_sets_arg(p, "--figure-sets")
    p.add_argument("--no-figures", dest="figure_sets", action="store_const", const=[],
                   help="draw no figure sets (the quickest run: the system chain and its report only)")
    p.add_argument("--design-only", action="store_true", help="only the design report and figures")
    p.set_defaults(func=run)


def _print_design(report: dict, prototype: dict) -> None:
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


def _print_system(s: dict) -> None:
    fer, theory = s["fer"]["measured_refined"]["rectangle"], s["fer"]["theory"]
    print("HBIS system demo:")
    print(f"  FER (stitched)    h = {fer['fer_h']:.2f}, v = {fer['fer_v']:.2f} "
          f"(theory {theory['fer_h']:.2f} / {theory['fer_v']:.2f}; paper's prototype 2.2 / 2.0)")
    print(f"  foveal ratio      {s['foveal_ratio']['measured']:.3f} (h = {s['foveal_ratio']['theory']})")
    print(f"  BSR               {s['bandwidth']['bsr_from_coverage']:.3f} from the data volumes, "
          f"eq. 10 {s['bandwidth']['bsr_eq10_design_fer']:.3f}")
    if "psnr_sr_db" in s["sr"]:
        print(f"  SR fovea          PSNR {s['sr']['psnr_sr_db']:.2f} dB (bicubic {s['sr']['psnr_bicubic_db']:.2f} dB)")
    print(f"  events            {len(s['events'])}, SR scans kept {s['loop']['kept']} of {s['loop']['captures']}")


def _run(args):
    """Design report and figures, then (unless --design-only) the chain and the HTML page."""
    from hbis_torch.design import design
    from hbis_torch.system.pipeline import ChainConfig, run_chain
    from hbis_torch.system.report.report import write_report

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    system = FoveaSystem()
    report = design(system).to_dict()
    prototype = design(system, varphi_h_deg=15.0, varphi_v_deg=10.0, h=4).to_dict()
    sets = FIGURE_SET_NAMES if args.figure_sets is None else list(dict.fromkeys(args.figure_sets))
    from hbis_torch.progress import progress_enabled

    figures = [str(p) for name in sets
               for p in figure_set(name)(out / "figures", system, progress=progress_enabled())]
    summary = {"design_at_limits": report, "prototype_15_10_h4": prototype, "figures": figures}
    _print_design(report, prototype)
    if args.design_only:
        return summary, None
    config = ChainConfig(h=args.h, roi_size=args.roi_size, seed=args.seed, refine=not args.no_refine,
                         assembly_sigma_deg=args.assembly_error_deg, method=args.method, model=args.model)
    system_summary = run_chain(out, system, config, log=logging.getLogger("hbis_torch.system.pipeline").info)
    summary["system"] = system_summary
    relative = [str(Path(f).relative_to(out)) for f in figures]
    from hbis_torch.system.report.report import run_info

    page = write_report(out, system_summary, report, relative, run=run_info(getattr(args, "argv", None)))
    _print_system(system_summary)
    return summary, page


def run(args) -> int:
    from hbis_torch.reconstruct.registry import get_method

    if args.model is not None and "model" not in get_method(args.method).keywords:
        raise HbisInputError(f"--model is for a method that takes a model file; {args.method} does not")
    from hbis_torch.reconstruct.learned.runtime import available_tier, default_model_path, tier_of

    tier = tier_of(args.model)  # None: a file
    if tier is None and not Path(args.model).is_file():
        raise HbisInputError(f"{args.model}: no such model file (--model takes 'fast', 'best' or an ONNX file)")
    if args.method == "learned" and tier is not None and not args.design_only:
        default_model_path(args.h, available_tier(tier, args.h))  # none shipped for this h: say so now
    check_output_dir(args.out)
    import torch

    start = time.perf_counter()
    threads = torch.get_num_threads()
    torch.set_num_threads(args.threads)
    try:
        summary, page = _run(args)
    finally:
        torch.set_num_threads(threads)
    out = Path(args.out)
    summary["elapsed_s"] = round(time.perf_counter() - start, 1)
    atomic_write_text(out / "report.json", json.dumps(summary, indent=2, default=str))
    print(f"wrote {out / 'report.json'} and {len(summary['figures'])} figures under {out / 'figures'}")
    if not args.design_only:
        print(f"wrote the report {page} ({summary['elapsed_s']:.0f} s)")
    return 0
