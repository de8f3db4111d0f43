"""``hbis reconstruct``: super-resolve a stack onto the h-times grid of its reference frame."""

from __future__ import annotations

from pathlib import Path

from hbis_torch.checks import bounded_int
from hbis_torch.cli import examples
from hbis_torch.cli.method_options import add_method_options, method_keywords
from hbis_torch.errors import HbisInputError


def register(sub) -> None:
    from hbis_torch.reconstruct.registry import METHODS

    methods = "; ".join(f"{name}: {method.summary}" for name, method in METHODS.items())
    p = sub.add_parser(
        "reconstruct",
        help="super-resolve an hbis-stack/1 file (h times its size, float32 in [0, 1]; RGB for colour stacks)",
        description="Reconstruct the super-resolved image of a stack: h times the frames' size in "
        f"each direction, covering the reference frame's ROI, written as a float32 TIFF in [0, 1]. Methods: {methods}. "
        "A burst stack ('hbis assemble --burst') goes through the same methods onto its reference frame's grid refined "
        "S times, samples its motion does not explain down-weighted (docs/real-bursts.md).",
        epilog=examples("hbis reconstruct stack.tif --method learned --out sr.tif",
                        "hbis reconstruct 'scans/*.tif' --method classical --out-dir sr/"),
    )
    p.add_argument("stack", type=Path, nargs="+", metavar="STACK",
                   help="input stack (hbis-stack/1 TIFF); with --out-dir, any number of them, a glob pattern "
                   "(quoted: 'scans/*.tif') or @LIST, a text file naming one stack a line")
    p.add_argument("--method", choices=tuple(METHODS), default="classical",
                   help="reconstruction method (default: classical)")
    outputs = p.add_mutually_exclusive_group(required=True)
    outputs.add_argument("--out", type=Path, help="output TIFF (one stack)")
    outputs.add_argument("--out-dir", type=Path, metavar="DIR",
                         help="many stacks in one process (the model is opened once, stacks run side by side "
                         "where cores are free): each to DIR/STEM.METHOD.tif; a stack whose output exists is skipped (a rerun "
                         "finishes the rest; --overwrite replaces them); a stack that fails is named in one line and the "
                         "others go on; exit 1 if one failed")
    p.add_argument("--jobs", type=bounded_int(1, 256), default=None,
                   help="with --out-dir: stacks reconstructed at once, each on one thread (default: the CPUs "
                   "this process may use, at most the number of stacks; 1 where --threads is given)")
    p.add_argument("--registration", choices=("auto", "optics", "data"), default="auto",
                   help="sample positions from the tracer ('optics'), the tracer corrected by "
                   "registering the frames ('data'), or that correction where the data is "
                   "trusted (default 'auto')")
    p.add_argument("--threads", type=bounded_int(1, 1024), default=None,
                   help="threads for torch and a method's own runtime (the learned one's) (default: every CPU this "
                   "process may use); where other jobs hold some of the cores, fewer run faster, as "
                   "idle threads no longer wait on busy ones")
    p.add_argument("--colour", choices=("luma", "channels"),
                   help="colour stacks: super-resolve each of R, G, B ('channels', the default) or only the "
                   "luminance, interpolating the chroma ('luma', a third of the work); not for raw Bayer stacks, which "
                   "a method with its own raw path (classical, learned) demosaicks jointly, each colour at full "
                   "resolution, and not for grey stacks")
    p.add_argument("--keep-blurred", action="store_true",
                   help="bursts: use every trusted frame, however blurred (by default a frame whose sharpness is "
                   "under 70 %% of the sharpest frame's, shaken or out of focus, is left out and named)")
    from hbis_torch.cli.cmd_assemble import add_calibration_args

    add_calibration_args(p)
    from hbis_torch.budget import add_force_arg

    add_force_arg(p)
    from hbis_torch.cli.common import add_overwrite_arg

    add_overwrite_arg(p)
    from hbis_torch.cli.many import add_scheduler_argument

    add_scheduler_argument(p)
    add_method_options(p, METHODS)  # last: the general options come first in --help
    p.set_defaults(func=run)


def run(args) -> int:
    if args.scheduler is not None:  # many stacks on a Dask cluster (hbis_torch.cluster)
        from hbis_torch.cli.many import run_reconstruct

        return run_reconstruct(args, prepare, reconstruct_one)
    if args.out_dir is not None:
        from hbis_torch.cli.reconstruct_batch import run_batch

        return run_batch(args, prepare, reconstruct_one)
    if args.jobs is not None:
        raise HbisInputError("--jobs is for --out-dir (many stacks); one stack uses --threads")
    if len(args.stack) != 1:
        raise HbisInputError(f"--out writes one stack and {len(args.stack)} are given; use --out-dir DIR for many")
    args.stack = args.stack[0]
    from hbis_torch.io_utils import check_distinct_paths, check_output_path

    check_distinct_paths({"STACK": args.stack}, {"--out": args.out})  # first: "is the input" says more
    check_output_path(args.out, overwrite=args.overwrite)
    from hbis_torch.reconstruct.raw_output import check_raw_outputs

    check_raw_outputs(args.stack, args.out, args.overwrite)  # a raw burst's preview (and DNG) too
    prepared = prepare(args)
    image, messages, meta, pixel_um = reconstruct_one(args, args.stack, prepared)
    from hbis_torch.cli.common import tell
    from hbis_torch.stack_io import write_image

    tell("reconstruct", messages)
    if "raw" in meta:  # a raw burst: linear 16-bit TIFF (or DNG) and an sRGB preview (docs/raw-bursts.md)
        from hbis_torch.reconstruct.raw_output import write_raw_outputs

        written = write_raw_outputs(args.out, image, meta)
        print(f"wrote {', '.join(map(str, written))} ({image.shape[1]} x {image.shape[0]} px, linear 16-bit)")
        return 0
    write_image(args.out, image, meta, pixel_size_um=pixel_um)
    print(f"wrote {args.out} ({image.shape[1]} x {image.shape[0]} px, float32{', RGB' if image.ndim == 3 else ''})")
    return 0


def prepare(args) -> tuple:
    """What every stack of one command shares, checked before any work: the method's keywords
    and the calibration frames."""
    from hbis_torch.reconstruct.registry import METHODS

    method = METHODS[args.method]
    kw = method_keywords(args, method, METHODS)
    if method.threads and args.threads is not None:
        kw["threads"] = args.threads
    if args.colour is not None:
        kw["colour"] = args.colour
    if args.keep_blurred:
        kw["keep_blurred"] = True
    from hbis_torch.capture.calibration import load_calibration

    return kw, load_calibration(args.dark, args.flat, args.bad_pixels)


def reconstruct_one(args, path: Path, prepared: tuple, threads: int | None = None) -> tuple:
    """Read and reconstruct one stack: (image, messages, the output's metadata, its pixel size in um).

    ``threads``: torch's threads for this stack (default ``--threads``, else torch's own)."""
    from hbis_torch.reconstruct.registry import reconstruct
    from hbis_torch.stack_io import object_pixel_um, read_stack

    kw, calibration = prepared
    stack = read_stack(path)
    if calibration and stack.kind == "burst":
        raise HbisInputError(f"{path.name} is a burst: give --dark, --flat and --bad-pixels to 'hbis assemble "
                             "--burst', which measures the motion on the corrected frames")
    from hbis_torch.budget import check_budget, estimate_reconstruct, estimate_reconstruct_burst

    f = stack.frames
    channels = f.shape[3] if f.ndim == 4 else 1
    if stack.kind == "burst":
        estimate = estimate_reconstruct_burst(f.shape[0], f.shape[2], f.shape[1], channels, stack.h, args.method,
                                              raw=isinstance(stack.meta.get("raw"), dict))
    else:
        estimate = estimate_reconstruct(f.shape[0], f.shape[2], f.shape[1], channels)
    check_budget(estimate, args.force)
    from hbis_torch.cli import map_large_arrays

    map_large_arrays(f.size)
    if calibration:
        from hbis_torch.capture.calibration import calibrate_stack

        stack = calibrate_stack(stack, calibration)
    messages: list[str] = []
    import torch

    before = torch.get_num_threads()
    threads = threads or args.threads
    if threads is not None:
        torch.set_num_threads(threads)
    try:
        image = reconstruct(stack, method=args.method, registration=args.registration, messages=messages, **kw)
    finally:
        torch.set_num_threads(before)
    meta = {"format": "hbis-sr/1", "source": path.name, "method": args.method,
            "registration": args.registration, "h": stack.h, "roi": list(stack.roi),
            "reference_index": stack.reference_index}
    if isinstance(stack.meta.get("raw"), dict):
        meta.update(raw=stack.meta["raw"], cfa=stack.meta.get("cfa"))
    pixel_um = None if stack.kind == "burst" else object_pixel_um(stack.system, stack.h)  # a burst has no optics
    return image, messages, meta, pixel_um
