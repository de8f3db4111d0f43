"""``hbis simulate``: a synthetic stack (and its ground truth) through the Risley model."""

from __future__ import annotations

import argparse
import textwrap
from pathlib import Path

from hbis_torch.budget import add_force_arg
from hbis_torch.checks import bounded_float, bounded_int
from hbis_torch.cli import examples
from hbis_torch.cli.common import H_ARG, SEED_ARG, add_overwrite_arg, add_system_args, system_from_args
from hbis_torch.cli.many import add_scheduler_argument
from hbis_torch.errors import HbisInputError

DEFAULT_CROP = 256
SUMMARY = "synthesise a stack (and its ground truth) through the Risley model"

# hbis_torch.simulate's scene names and SensorModel's defaults, written out so that --help does not
# import torch (hbis_torch.simulate does; tests/test_cli_polish.py checks that they agree).
SCENES = ("astronaut", "bars", "brick", "camera", "cell", "chelsea", "clock", "coffee", "coins", "edges", "flat",
          "gradient", "grass", "gravel", "hubble_deep_field", "immunohistochemistry", "moon", "page", "rocket",
          "siemens-star", "slanted-edge", "text", "texture", "words")
SENSOR_DEFAULTS = {"fill_factor": 1.0, "defocus_um": 0.0, "full_well_e": 10000.0, "read_noise_e": 2.0,
                   "black_level_dn": 0.0, "bit_depth": 12}


def _numbers(text: str, count: tuple[int, ...], kind=float, name: str = "value"):
    try:
        values = tuple(kind(t) for t in text.replace(" ", "").split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{name}: expected {' or '.join(map(str, count))} comma-separated numbers, got {text!r}") from None
    if len(values) not in count:
        raise argparse.ArgumentTypeError(f"{name}: expected {' or '.join(map(str, count))} numbers, got {text!r}")
    return values


def _roi(text: str):
    if text.strip().lower() in ("full", "all"):
        return "full"
    return _numbers(text, (4,), int, "--roi")


def _bit_depth(text: str):
    if text.strip().lower() == "float":
        return None
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"--bit-depth: expected 1..16 or 'float', got {text!r}") from None


def register(sub) -> None:
    defaults = argparse.Namespace(**SENSOR_DEFAULTS)
    p = sub.add_parser(
        "simulate",
        help=SUMMARY,
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description=(
            "Simulate the frames a sub-pixel scan of h x h prism positions records, through the\n"
            "exact per-pixel landing map of every frame, the lens's diffraction-limited PSF, the\n"
            "pixel aperture and sensor noise, and write them as an hbis-stack/1 TIFF. --truth also\n"
            "writes what an ideal sensor of pitch p/h sees at the reference (initial) phases,\n"
            "float32 (h*H, h*W), the image a reconstruction should produce (docs/data.md).\n\n"
            "Scenes: an image file (PNG, JPEG, TIFF, ...) or a built-in name:\n"
            + textwrap.fill(", ".join(SCENES), 88, initial_indent="  ", subsequent_indent="  ")
            + "\nBy default a scene is scaled to cover the view of the frame region (--roi)."
        ),
        epilog=examples("hbis simulate --scene siemens-star --h 4 --out star.tif --truth star_truth.tif"),
    )
    p.add_argument("--scene", required=True, nargs="+", help="built-in scene name or image path; several (or several "
                   "--seed values) with --out-dir: one stack each")
    p.add_argument("--h", type=H_ARG, required=True, help="resolution improvement factor (h x h frames)")
    p.add_argument("--out", help="output stack (hbis-stack/1 TIFF); or --out-dir for many")
    p.add_argument("--truth", help="also write the ground truth here (float32 TIFF); with --out-dir: --with-truth")
    p.add_argument("--out-dir", type=Path, metavar="DIR",
                   help="one stack per scene and seed, DIR/SCENE.seedN.tif, side by side on threads of this process "
                   "or on --scheduler; stacks that exist are skipped (--overwrite replaces them), so a rerun resumes")
    p.add_argument("--with-truth", action="store_true", help="with --out-dir: each stack's truth beside it, "
                   "DIR/SCENE.seedN.truth.tif")
    g = p.add_argument_group("scan and scene")
    g.add_argument("--roi", type=_roi, default=None,
                   help=f"frame region U0,V0,WIDTH,HEIGHT in sensor pixels, or 'full' "
                   f"(default: {DEFAULT_CROP} x {DEFAULT_CROP} at the sensor's centre)")
    g.add_argument("--phases-deg", type=lambda t: _numbers(t, (2,), float, "--phases-deg"), default=(5.0, 70.0),
                   help="initial prism phases PHI1,PHI2 [deg] of the scan (default 5,70)")
    g.add_argument("--method", choices=("exact", "paper"), default="exact",
                   help="scan-plan inverse: exact (default) or the paper's eqs. 8-9")
    g.add_argument("--scene-size-mm", type=lambda t: _numbers(t, (1, 2), float, "--scene-size-mm"),
                   help="scene size on the object plane WIDTH[,HEIGHT] in mm (default: cover the view)")
    g.add_argument("--seed", type=SEED_ARG, nargs="+", default=[0],
                   help="seed of the noise and of random scenes (default 0); several with --out-dir")
    g.add_argument("--phase-error-deg", type=bounded_float(0.0, 10.0), default=0.0,
                   help="std. dev. of random prism phase errors [deg]; frames are rendered at the "
                   "erroneous phases, the stack records the planned ones (default 0)")
    s = p.add_argument_group("sensor")
    s.add_argument("--bit-depth", type=_bit_depth, default=defaults.bit_depth,
                   help=f"ADC bits 1..16 (uint8/uint16 frames) or 'float' (default {defaults.bit_depth})")
    s.add_argument("--full-well", type=bounded_float(0.0, 1e9, lo_open=True), default=defaults.full_well_e,
                   help=f"full well [electrons] (shot noise; default {defaults.full_well_e:g})")
    s.add_argument("--read-noise", type=bounded_float(0.0, 1e6), default=defaults.read_noise_e,
                   help=f"read noise [electrons] (default {defaults.read_noise_e:g})")
    s.add_argument("--black-level", type=bounded_float(0.0, 65535.0), default=defaults.black_level_dn,
                   help=f"black level [DN] (default {defaults.black_level_dn:g})")
    s.add_argument("--fill-factor", type=bounded_float(0.0, 1.0, lo_open=True), default=defaults.fill_factor,
                   help=f"light-sensitive fraction of the pixel area (default {defaults.fill_factor:g})")
    s.add_argument("--defocus-um", type=bounded_float(-1e4, 1e4), default=defaults.defocus_um,
                   help=f"sensor distance from best focus [um] (default {defaults.defocus_um:g})")
    s.add_argument("--no-noise", action="store_true", help="noise-free frames (still quantised)")
    a = p.add_argument_group("forward model (advanced)")
    a.add_argument("--oversample", type=bounded_int(1, 64), default=8,
                   help="fine-grid points per sensor pixel, at least (default 8)")
    a.add_argument("--margin-px", type=bounded_float(0.0, 1000.0), default=8.0,
                   help="grid margin [pixels] around the frames (default 8; see docs/data.md)")
    add_system_args(p)
    add_force_arg(p)
    add_overwrite_arg(p)
    add_scheduler_argument(p)
    p.set_defaults(func=run)


def default_roi(camera) -> tuple[int, int, int, int]:
    """A DEFAULT_CROP square (or the whole sensor if smaller) at the sensor's centre."""
    width, height = min(DEFAULT_CROP, camera.cols), min(DEFAULT_CROP, camera.rows)
    return ((camera.cols - width) // 2, (camera.rows - height) // 2, width, height)


def run(args) -> int:
    if args.out_dir is not None:
        from hbis_torch.cli.many import run_simulations

        return run_simulations(args, simulate_one, check_common, SCENES)
    if args.scheduler is not None:
        raise HbisInputError("--scheduler needs --out-dir DIR (one stack per scene and seed)")
    if len(args.scene) > 1 or len(args.seed) > 1:
        raise HbisInputError(f"{len(args.scene)} scene(s) and {len(args.seed)} seed(s) given: give --out-dir DIR for "
                             "one stack each")
    if args.out is None:
        raise HbisInputError("--out is required (or --out-dir DIR for many scenes or seeds)")
    if args.with_truth:
        raise HbisInputError("--with-truth is for --out-dir; with --out, name the truth with --truth PATH")
    from hbis_torch.io_utils import check_distinct_paths, check_output_path

    check_output_path(args.out, overwrite=args.overwrite)
    if args.truth is not None:
        check_output_path(args.truth, "--truth", overwrite=args.overwrite)
    scene = args.scene[0]
    scene_file = scene if Path(scene).exists() else None
    check_distinct_paths({"--scene": scene_file}, {"--out": args.out, "--truth": args.truth})
    print(f"wrote {args.out}: " + simulate_one(args, scene, args.seed[0], Path(args.out), args.truth))
    return 0


def check_common(args):
    """What every scene of a run shares, checked before any work: (system, roi)."""
    from hbis_torch.budget import check_budget, estimate_simulate
    from hbis_torch.checks import check_h, check_roi

    system = system_from_args(args)
    check_h(args.h)
    if args.roi is None:
        roi = default_roi(system.camera)
    elif args.roi == "full":
        roi = check_roi(system.camera, None)
    else:
        roi = check_roi(system.camera, args.roi)
    check_budget(estimate_simulate(args.h**2, roi[2], roi[3]), args.force)
    return system, roi


def simulate_one(args, scene_name: str, seed: int, out: Path, truth_path=None, stack_name: str | None = None) -> str:
    """Simulate one scene at one seed into ``out`` (and its truth into ``truth_path``, which names
    its stack ``stack_name``, default ``out``'s name); what was written, in words."""
    from hbis_torch.scan import plan_scan
    from hbis_torch.simulate import SensorModel, simulate_stack
    from hbis_torch.simulate.stacks import scene_for_roi
    from hbis_torch.stack_io import object_pixel_um, write_image, write_stack

    system, roi = check_common(args)
    sensor = SensorModel(
        fill_factor=args.fill_factor,
        defocus_um=args.defocus_um,
        full_well_e=args.full_well,
        read_noise_e=args.read_noise,
        black_level_dn=args.black_level,
        bit_depth=args.bit_depth,
        noise=not args.no_noise,
    )
    plan = plan_scan(system, args.h, args.phases_deg, method=args.method)
    size = args.scene_size_mm
    if size is not None and len(size) == 1:
        size = size[0]
    scene = scene_for_roi(scene_name, system, roi, args.h, seed, size, args.margin_px, args.oversample)
    stack, truth = simulate_stack(scene, system, plan, roi, sensor, seed=seed,
                                  phase_error_deg=args.phase_error_deg, oversample=args.oversample,
                                  margin_px=args.margin_px)
    if truth_path:
        write_image(truth_path, truth, {"format": "hbis-truth/1", "h": args.h, "roi": list(roi),
                                        "reference_index": stack.reference_index,
                                        "stack": stack_name or Path(out).name},
                    pixel_size_um=object_pixel_um(system, args.h))
    write_stack(out, stack)
    said = (f"{stack.frames.shape[0]} frames of {roi[2]} x {roi[3]} px ({stack.frames.dtype}), h = {args.h}, roi "
            f"{list(roi)}, scene {scene.name} {scene.size_mm[0]:.3f} x {scene.size_mm[1]:.3f} mm")
    if truth_path:
        said += "; truth " + (f"{truth_path}: " if stack_name is None else "") + f"{truth.shape[1]} x {truth.shape[0]} px float32"
    return said
