"""``hbis assemble``: captured frames + the scan's phases file -> one hbis-stack/1 stack."""

from __future__ import annotations

import argparse
import math
from pathlib import Path

from hbis_torch.budget import add_force_arg
from hbis_torch.checks import bounded_float, bounded_int
from hbis_torch.cli.common import add_system_args, add_system_file_args, system_for

CFA_PATTERNS = ("RGGB", "BGGR", "GRBG", "GBRG")


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
        help="build an hbis-stack/1 file from captured frames and the phases file of 'hbis motors scan --out'",
        description="Assemble the frames of one captured scan (in scan order) and the phases file that "
        "'hbis motors scan --out' wrote into an hbis-stack/1 TIFF: the read-back phases become the "
        "stack's phases_deg and the scan's reference_index is kept. FRAME is several image files, "
        "one pattern with {index} (e.g. 'cap_{index:03d}.png', replaced by 0..h*h-1), one multi-page "
        "TIFF, or one video file (PyAV). Every frame's size is checked from its header before any is decoded. Everything is checked before anything is written.",
        epilog="example: hbis assemble --phases phases.json --roi 608,456,64,48 --bit-depth 12 "
        "--out stack.tif 'frames/cap_{index:03d}.tif'",
    )
    p.add_argument("frames", nargs="+", metavar="FRAME", help="frames in scan order (files, {index} pattern, TIFF, video)")
    p.add_argument("--phases", required=True, help="the phases file of 'hbis motors scan --out'")
    p.add_argument("--out", required=True, type=Path, help="output stack (hbis-stack/1 TIFF)")
    p.add_argument("--roi", type=_roi, help="where the frames sit on the sensor, U0,V0,WIDTH,HEIGHT (default: "
                   "the whole sensor); full-sensor frames are cut to it")
    p.add_argument("--bit-depth", type=bounded_int(1, 16), help="significant bits of integer frames (default: 8 or 16 from the dtype)")
    p.add_argument("--black-level", type=bounded_float(0.0, 65535.0), help="digital number of black (default 0)")
    p.add_argument("--cfa", type=str.upper, choices=CFA_PATTERNS,
                   help="raw Bayer frames: the colour filter pattern of the top-left 2 x 2 pixels")
    add_calibration_args(p)
    add_system_args(p)
    add_system_file_args(p)
    add_force_arg(p)
    p.set_defaults(func=run)


def run(args) -> int:
    from hbis_torch.capture import (
        assemble_stack,
        frames_roi,
        load_calibration,
        read_frames,
        read_phases,
    )
    from hbis_torch.capture.frames import probe_frames
    from hbis_torch.io_utils import check_distinct_paths, check_output_path
    from hbis_torch.stack_io import write_stack

    check_output_path(args.out)
    inputs = {"--phases": args.phases, "--dark": args.dark, "--flat": args.flat, "--bad-pixels": args.bad_pixels,
              "--system": getattr(args, "system", None), "--calibration": getattr(args, "calibration", None)}
    inputs.update({f"FRAME {k + 1}": f for k, f in enumerate(args.frames) if Path(f).exists()})
    check_distinct_paths(inputs, {"--out": args.out})
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
    f = stack.frames
    print(f"wrote {args.out}: {f.shape[0]} frames of {f.shape[2]} x {f.shape[1]} ({f.dtype}"
          f"{', RGB' if f.ndim == 4 else ''}), h = {stack.h}, roi {list(stack.roi)}, reference frame "
          f"{stack.reference_index}{', calibrated' if calibration else ''}")
    return 0
