"""``hbis assemble``: captured frames + the scan's phases file -> one hbis-stack/1 stack."""

from __future__ import annotations

import argparse
import math
from pathlib import Path

from hbis_torch.budget import add_force_arg
from hbis_torch.checks import bounded_float, bounded_int
from hbis_torch.cli import examples
from hbis_torch.cli.common import add_overwrite_arg, add_system_args, add_system_file_args, system_for
from hbis_torch.errors import HbisInputError

CFA_PATTERNS = ("RGGB", "BGGR", "GRBG", "GBRG")


def _reference(text: str):
    """``--reference``: a frame index from 0 to 255, or ``sharpest``."""
    from hbis_torch.capture.sharpness import SHARPEST

    if text == SHARPEST:
        return SHARPEST
    try:
        return bounded_int(0, 255)(text)
    except argparse.ArgumentTypeError:
        raise argparse.ArgumentTypeError(f"expected a frame index from 0 to 255 or '{SHARPEST}', "
                                         f"got {text[:40]!r}") from None


def _roi(text: str):
    try:
        values = tuple(int(t) for t in text.replace(" ", "").split(","))
    except ValueError:
        values = ()
    if len(values) != 4:
        raise argparse.ArgumentTypeError(f"--roi: expected four integers U0,V0,WIDTH,HEIGHT, got {text!r}")
    return values


def add_calibration_args(parser) -> None:
    """--dark, --flat, --bad-pixels (shared with ``hbis reconstruct``)."""
    g = parser.add_argument_group("sensor calibration (raw units of the frames; frame or sensor size)")
    g.add_argument("--dark", metavar="FILE", help="dark frame (lens capped, same exposure); a multi-page TIFF is averaged")
    g.add_argument("--flat", metavar="FILE", help="flat field (uniform white target); a multi-page TIFF is averaged")
    g.add_argument("--bad-pixels", metavar="FILE", help="bad-pixel map: an image, nonzero at defective pixels")


def register(sub) -> None:
    p = sub.add_parser(
        "assemble",
        help="build an hbis-stack/1 file from captured frames and the phases file of 'hbis motors scan --out', "
        "or (--burst) from a burst of frames with unknown motion",
        description="Assemble the frames of one captured scan (in scan order) and the phases file that "
        "'hbis motors scan --out' wrote into an hbis-stack/1 TIFF: the read-back phases become the "
        "stack's phases_deg and the scan's reference_index is kept. FRAME is several image files (or a "
        "folder of them, or a wildcard), one pattern with {index} (e.g. 'cap_{index:03d}.png', replaced by "
        "0..h*h-1), one multi-page TIFF, or one video file (PyAV). Every frame's size is checked from its "
        "header before any is decoded. Everything is checked before anything is written. With --burst, no phases: "
        "the frames are a burst from a freely moving camera (any number >= 2); each frame's motion to the "
        "reference is measured (phase correlation or matched features, then Lucas-Kanade, the simplest motion "
        "model that explains it, frame by frame), with its brightness (gain, offset) and a confidence; frames that "
        "cannot be registered (another scene, no texture) are named and marked untrusted.",
        epilog=examples("hbis assemble --phases phases.json --roi 608,456,64,48 --bit-depth 12 --out stack.tif "
                        "'frames/cap_{index:03d}.tif'", "hbis assemble --burst --scale 3 --out burst.tif clip.avi"),
    )
    p.add_argument("frames", nargs="+", metavar="FRAME",
                   help="frames in scan order: files, a folder of them (name order, f2 before f10), a wildcard "
                   "('frames/*.png'), an {index} pattern, one multi-page TIFF or one video")
    p.add_argument("--phases", help="the phases file of 'hbis motors scan --out' (required unless --burst)")
    b = p.add_argument_group("bursts (frames with unknown motion, no phases)")
    b.add_argument("--burst", action="store_true", help="the frames are a burst: measure each frame's motion")
    b.add_argument("--scale", type=bounded_int(1, 16), help="with --burst: the output scale S (the reconstruction "
                   "refines the reference frame's grid S times; required)")
    b.add_argument("--reference", type=_reference, default=0,
                   help="with --burst: the frame whose grid the output refines (default 0; a reference clearly "
                   "blurrier than the burst's sharpest frame is named), or 'sharpest': the sharpest frame")
    b.add_argument("--motion", choices=("auto", "translation", "similarity", "affine", "homography"), default="auto",
                   help="with --burst: the motion model; 'auto' (default) picks, frame by frame, the simplest model "
                   "whose residual is at the noise level")
    p.add_argument("--out", required=True, type=Path, help="output stack (hbis-stack/1 TIFF)")
    p.add_argument("--roi", type=_roi, help="where the frames sit on the sensor, U0,V0,WIDTH,HEIGHT (default: "
                   "the whole sensor); full-sensor frames are cut to it; with --burst: the part of the frames to keep "
                   "(default: the whole frames less any still black bands at their edges, a letterbox)")
    p.add_argument("--bit-depth", type=bounded_int(1, 16), help="significant bits of integer frames (default: 8 or 16 from the dtype)")
    p.add_argument("--black-level", type=bounded_float(0.0, 65535.0), help="digital number of black (default 0)")
    p.add_argument("--cfa", type=str.upper, choices=CFA_PATTERNS,
                   help="raw Bayer frames: the colour filter pattern of the top-left 2 x 2 pixels")
    p.add_argument("--threads", type=bounded_int(1, 1024), default=None,
                   help="threads for torch (default: every CPU this process may use); where other jobs hold "
                   "the cores, one runs faster, as idle threads no longer wait on busy ones (docs/real-bursts.md)")
    add_calibration_args(p)
    add_system_args(p)
    add_system_file_args(p)
    add_force_arg(p)
    add_overwrite_arg(p)
    from hbis_torch.cli.many import add_scheduler_argument

    add_scheduler_argument(p, many="frames")  # --burst --out-dir DIR: many bursts (hbis_torch.cluster)
    p.set_defaults(func=run)


def run(args) -> int:
    from hbis_torch.cli.many import run_many

    if args.threads is not None and args.out_dir is not None:
        raise HbisInputError("--threads is for one input: with --out-dir each burst runs on one thread")
    if (code := run_many(args, "assemble")) is not None:  # many bursts, --out-dir (hbis_torch.cluster)
        return code
    import torch

    before = torch.get_num_threads()
    if args.threads is not None:
        torch.set_num_threads(args.threads)
    try:
        return run_burst(args) if args.burst else run_scan(args)
    finally:
        torch.set_num_threads(before)


def run_scan(args) -> int:
    """``hbis assemble --phases``: a Risley scan's frames -> a scan stack."""
    from hbis_torch.capture import (
        assemble_stack,
        frames_roi,
        load_calibration,
        read_frames,
        read_phases,
    )
    from hbis_torch.capture.frames import bit_depth_hint, expand_sources, probe_frames
    from hbis_torch.cli.common import tell
    from hbis_torch.io_utils import check_distinct_paths, check_output_path
    from hbis_torch.stack_io import write_stack

    if args.phases is None:
        raise HbisInputError("--phases is required (the phases file of 'hbis motors scan --out'), "
                         "unless the frames are a burst (--burst --scale S)")
    for flag, given in (("--scale", args.scale), ("--reference", args.reference), ("--motion", args.motion != "auto")):
        if given:
            raise HbisInputError(f"{flag} is for bursts: give --burst as well")
    args.frames = expand_sources(args.frames)  # a folder, or a wildcard the shell left
    inputs = {"--phases": args.phases, "--dark": args.dark, "--flat": args.flat, "--bad-pixels": args.bad_pixels,
              "--system": getattr(args, "system", None), "--calibration": getattr(args, "calibration", None)}
    inputs.update({f"FRAME {k + 1}": f for k, f in enumerate(args.frames) if Path(f).exists()})
    check_distinct_paths(inputs, {"--out": args.out})  # first: "is an input" says more than "exists"
    check_output_path(args.out, overwrite=args.overwrite)
    system = system_for(args)
    scan = read_phases(args.phases)
    calibration = load_calibration(args.dark, args.flat, args.bad_pixels)
    declared, _, _ = probe_frames(args.frames, count=scan.frames)  # headers only: size refused before decoding
    frames_roi(system, declared.shape, args.roi)
    from hbis_torch.budget import check_budget, estimate_assemble

    count = declared.count or scan.frames
    check_budget(estimate_assemble(count * declared.frame_bytes, count * math.prod(declared.shape),
                                   bool(calibration)), args.force)
    frames, _ = read_frames(args.frames, count=scan.frames)
    stack = assemble_stack(frames, scan, system, roi=args.roi, bit_depth=args.bit_depth,
                           black_level=args.black_level, calibration=calibration, cfa=args.cfa)
    write_stack(args.out, stack)
    hint = bit_depth_hint(frames) if args.bit_depth is None else None
    tell("assemble", [hint] if hint is not None else [])
    f = stack.frames
    print(f"wrote {args.out}: {f.shape[0]} frames of {f.shape[2]} x {f.shape[1]} px ({f.dtype}"
          f"{', RGB' if f.ndim == 4 else ''}), h = {stack.h}, roi {list(stack.roi)}, reference frame "
          f"{stack.reference_index}{', calibrated' if calibration else ''}")
    return 0


def run_burst(args) -> int:
    """``hbis assemble --burst``: frames with unknown motion -> a burst stack."""
    from hbis_torch.capture import load_calibration, read_frames
    from hbis_torch.capture.calibration import check_calibration_size
    from hbis_torch.capture.frames import expand_sources
    from hbis_torch.cli.common import tell
    from hbis_torch.capture.burst import assemble_burst
    from hbis_torch.io_utils import check_distinct_paths, check_output_path
    from hbis_torch.stack_io import write_stack

    if args.scale is None:
        raise HbisInputError("--burst needs --scale S (the output scale: 2, 3, 4, ...)")
    args.frames = expand_sources(args.frames)  # a folder, or a wildcard the shell left
    refused = [flag for flag, value in (("--phases", args.phases), ("--cfa", args.cfa),
                                        ("--black-level", args.black_level),
                                        ("--system", getattr(args, "system", None)),
                                        ("--calibration", getattr(args, "calibration", None))) if value is not None]
    if refused:
        raise HbisInputError(f"{', '.join(refused)} do(es) not apply to a burst (--burst)")
    inputs = {"--dark": args.dark, "--flat": args.flat, "--bad-pixels": args.bad_pixels}
    inputs.update({f"FRAME {k + 1}": f for k, f in enumerate(args.frames) if Path(f).exists()})
    check_distinct_paths(inputs, {"--out": args.out})
    check_output_path(args.out, overwrite=args.overwrite)
    from hbis_torch.budget import check_budget, estimate_assemble_burst
    from hbis_torch.capture.raw import assemble_raw_burst, is_raw_burst
    from hbis_torch.cli import map_large_arrays

    calibration = load_calibration(args.dark, args.flat, args.bad_pixels)
    if is_raw_burst(args.frames):  # DNG and LibRaw's formats: the [raw] extra (docs/raw-bursts.md)
        if calibration:
            raise HbisInputError("--dark, --flat and --bad-pixels are for frames that are images; a raw burst is "
                                 "read with its own black level, white level and noise profile")
        from hbis_torch.capture.raw import raw_size

        size = raw_size(args.frames[0])  # the header: too large is refused before decoding
        if size is not None:  # (unreadable: the reading's own line says why)
            pixels = len(args.frames) * math.prod(size)
            check_budget(estimate_assemble_burst(2 * pixels, pixels), args.force)
            map_large_arrays(pixels)
        stack, messages = assemble_raw_burst(args.frames, args.scale, args.reference, args.motion, roi=args.roi,
                                             bit_depth=args.bit_depth)
    else:
        from hbis_torch.capture.frames import probe_frames

        declared, _, _ = probe_frames(args.frames)  # headers only: too large is refused before decoding
        check_calibration_size(calibration, declared.shape, args.roi)
        count = declared.count or 1  # (a video that does not say how many: its first frame's worth at least)
        corrected = 4 * count * math.prod(declared.shape) if calibration else 0  # the float32 frames
        check_budget(estimate_assemble_burst(count * declared.frame_bytes + corrected,
                                             count * math.prod(declared.shape[:2])), args.force)
        map_large_arrays(count * math.prod(declared.shape))  # as hbis reconstruct does
        frames, names = read_frames(args.frames)
        stack, messages = assemble_burst(frames, args.scale, args.reference, args.motion, roi=args.roi,
                                         bit_depth=args.bit_depth, names=names, calibration=calibration)
    write_stack(args.out, stack)
    tell("assemble", messages)
    models = stack.meta["motion_models"]
    counts = ", ".join(f"{models.count(m)} {m}" for m in dict.fromkeys(models))
    trusted = int((stack.confidence >= 0.5).sum())
    f = stack.frames
    print(f"wrote {args.out}: burst of {f.shape[0]} frames of {f.shape[2]} x {f.shape[1]} px ({f.dtype}"
          f"{', RGB' if f.ndim == 4 else ''}{', raw ' + stack.meta['cfa'] if 'raw' in stack.meta else ''}), "
          f"scale S = {stack.h}, reference frame {stack.reference_index}, "
          f"{trusted} frame(s) trusted; motion models: {counts}")
    return 0
