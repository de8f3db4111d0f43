"""``hbis reconstruct``: super-resolve a stack onto the h-times grid of its reference frame."""

from __future__ import annotations

import sys
from pathlib import Path

from hbis_torch.checks import bounded_int
from hbis_torch.errors import HbisInputError

# Every method the command line knows; the library says which are available in this build.
METHOD_CHOICES = ("classical", "learned")


def register(sub) -> None:
    p = sub.add_parser(
        "reconstruct",
        help="super-resolve an hbis-stack/1 file (h times its size, float32 in [0, 1]; RGB for colour stacks)",
        description="Reconstruct the super-resolved image of a stack: h times the frames' size in "
        "each direction, covering the reference frame's ROI, written as a float32 TIFF in [0, 1].",
    )
    p.add_argument("stack", type=Path, help="input stack (hbis-stack/1 TIFF)")
    p.add_argument("--method", choices=METHOD_CHOICES, default="classical",
                   help="reconstruction method (default: classical)")
    p.add_argument("--model", type=Path, help="ONNX model file (only for --method learned)")
    p.add_argument("--provider", choices=("auto", "openvino", "cpu"),
                   help="learned: what runs the model; 'auto' (the default) takes OpenVINO where "
                   "installed (pip install 'hbis-torch[openvino]'; faster), else onnxruntime's CPU kernels")
    p.add_argument("--extrapolate", action="store_true",
                   help="learned: run the network on a stack outside its training domain too (a lens "
                   "blurrier, or noise far lower or higher, than any it was trained on); by default such "
                   "a stack gets the classical image, with a message")
    p.add_argument("--ensemble", type=int, choices=(1, 2, 4, 8), default=None,
                   help="learned: average the network over this many of the square's 8 flips and "
                   "rotations (geometric self-ensemble; default 2 at h = 7, where the classical step takes "
                   "most of the time, else 1): as many times the network's time, for +0.1 to +0.2 dB on "
                   "held-out photographs at 8")
    p.add_argument("--out", type=Path, required=True, help="output TIFF")
    p.add_argument("--registration", choices=("auto", "optics", "data"), default="auto",
                   help="sample positions from the tracer ('optics'), the tracer corrected by "
                   "registering the frames ('data'), or that correction where the data is "
                   "trusted (default 'auto')")
    p.add_argument("--no-deblur", action="store_true",
                   help="classical: interpolation only, without the Wiener deblurring")
    p.add_argument("--threads", type=bounded_int(1, 1024), default=None,
                   help="threads for torch and the learned method's runtime (default: every CPU this "
                   "process may use); where other jobs hold some of the cores, fewer run faster, as "
                   "idle threads no longer wait on busy ones")
    p.add_argument("--colour", choices=("luma", "channels"),
                   help="colour stacks: super-resolve each of R, G, B ('channels', the default) or only the "
                   "luminance, interpolating the chroma ('luma', a third of the work); raw Bayer stacks are "
                   "demosaicked jointly by the classical method, first by the learned one")
    from hbis_torch.cli.cmd_assemble import add_calibration_args

    add_calibration_args(p)
    p.set_defaults(func=run)


def run(args) -> int:
    from hbis_torch.io_utils import check_distinct_paths, check_output_path
    from hbis_torch.reconstruct.registry import METHODS, reconstruct
    from hbis_torch.stack_io import object_pixel_um, read_stack, write_image

    check_output_path(args.out)
    check_distinct_paths({"STACK": args.stack}, {"--out": args.out})

    if args.method not in METHODS:
        raise HbisInputError(
            f"method {args.method!r} is not available in this build (available: {', '.join(METHODS)})"
        )
    kw = {}
    if args.method == "classical":
        for name in ("model", "provider", "ensemble"):
            if getattr(args, name) is not None:
                raise HbisInputError(f"--{name} is only for --method learned; the classical method runs no network")
        if args.extrapolate:
            raise HbisInputError("--extrapolate is only for --method learned")
        kw["deblur"] = not args.no_deblur
    else:
        kw.update({name: getattr(args, name) for name in ("model", "provider", "threads", "ensemble")
                   if getattr(args, name) is not None})
        kw["extrapolate"] = args.extrapolate
    from hbis_torch.capture.calibration import calibrate_stack, load_calibration

    calibration = load_calibration(args.dark, args.flat, args.bad_pixels)
    stack = read_stack(args.stack)
    if calibration:
        stack = calibrate_stack(stack, calibration)
    if args.colour is not None:
        kw["colour"] = args.colour
    messages: list[str] = []
    import torch

    threads = torch.get_num_threads()
    if args.threads is not None:
        torch.set_num_threads(args.threads)
    try:
        image = reconstruct(stack, method=args.method, registration=args.registration,
                            messages=messages, **kw)
    finally:
        torch.set_num_threads(threads)
    for line in messages:
        print(f"hbis reconstruct: {line}", file=sys.stderr)
    meta = {"format": "hbis-sr/1", "source": args.stack.name, "method": args.method,
            "registration": args.registration, "h": stack.h, "roi": list(stack.roi),
            "reference_index": stack.reference_index}
    write_image(args.out, image, meta, pixel_size_um=object_pixel_um(stack.system, stack.h))
    print(f"wrote {args.out} ({image.shape[0]} x {image.shape[1]} px, float32{', RGB' if image.ndim == 3 else ''})")
    return 0
