"""``hbis validate``: compare reconstruction methods on a stack without ground truth, by
observation-space cross-validation (docs/validate.md)."""

from __future__ import annotations

import json
from pathlib import Path

from hbis_torch.checks import bounded_float, bounded_int
from hbis_torch.cli import examples
from hbis_torch.cli.validate_report import json_report, method_names  # noqa: F401 - the command's own

DESCRIPTION = """\
Score super-resolution methods on a stack that has no ground truth. One frame at a time is held
out (never the reference; N frames spread over the stack); each method super-resolves the other
frames; the forward model predicts the held-out frame from that image (the frame's sample
positions on the reference grid, from the optics and registration of a scan or the motions of a
burst; each pixel's area; a small Gaussian blur; gain and offset fitted by least squares); the
score is the PSNR of the prediction against the frame, in dB, away from a border. The
single-frame baseline (the reference frame enlarged bicubically) goes through the same model.

How to read it: higher means the image explains frames it never saw better. Compare methods (and
settings) on the same stack, by their difference to the single-frame baseline; the absolute
value depends on the scene and the noise. Colour stacks are scored on luminance (BT.601), raw
Bayer stacks on the mosaic.

Limits: it measures consistency with the observations, not closeness to the truth. Detail finer
than the frames' pixels is seen only through its aliasing, so the score under-rates real gains
at those frequencies and can reward an image that is sharpened or textured to fit the aliasing;
noise in the held-out frame caps every score alike; a wrong motion (a moving object, a bad
registration) lowers it for every method. A method's own options (--model, --ensemble, --no-deblur,
...) apply to every scored method that takes them. Idea: Nguyen, Milanfar and Golub, IEEE TIP 2001
(cross-validation for multi-frame super-resolution)."""


def register(sub) -> None:
    from hbis_torch.cli.method_options import add_method_options
    from hbis_torch.reconstruct.registry import METHODS

    p = sub.add_parser(
        "validate",
        help="score reconstruction methods on a stack without ground truth (cross-validation on its frames)",
        description=DESCRIPTION,
        epilog=examples("hbis validate stack.tif", "hbis validate burst.tif --method classical,learned --json"),
    )
    p.add_argument("stack", type=Path, help="input stack (hbis-stack/1 TIFF: an HBIS scan or a burst)")
    p.add_argument("--method", action="append", metavar="NAME[,NAME...]",
                   help="a method to score, repeatable or a comma list: single-frame (alias bicubic), "
                   f"{', '.join(METHODS)} (default: single-frame,classical,learned)")
    p.add_argument("--holdout", type=bounded_int(1, 1 << 16), default=None, metavar="N",
                   help="frames to hold out, one at a time (default: 3, or all but the reference where fewer)")
    p.add_argument("--registration", choices=("auto", "optics", "data"), default="auto",
                   help="scan stacks: where sample positions come from, for the methods and for the forward "
                   "model (as hbis reconstruct; bursts use their motions)")
    p.add_argument("--border", type=bounded_float(0.0, 1e4), default=None, metavar="PX",
                   help="samples this close to the reference frame's edge, in frame pixels, are not scored "
                   "(default 2)")
    p.add_argument("--blur", type=bounded_float(0.0, 10.0), default=None, metavar="PX",
                   help="the forward model's Gaussian blur, standard deviation in frame pixels (default 0.2)")
    p.add_argument("--json", action="store_true", help="print one JSON object instead of the table")
    add_method_options(p, METHODS)
    from hbis_torch.cli.many import add_scheduler_argument

    add_scheduler_argument(p, many="stack")  # --out-dir DIR: many stacks (hbis_torch.cluster)
    p.set_defaults(func=run)


def run(args) -> int:
    from hbis_torch.cli.many import run_many

    if (code := run_many(args, "validate")) is not None:  # many stacks, --out-dir (hbis_torch.cluster)
        return code
    from hbis_torch.cli.method_options import keywords_for_methods
    from hbis_torch.reconstruct.registry import METHODS

    names = method_names(args.method)  # before reading the stack
    options = keywords_for_methods(args, names, METHODS)
    from hbis_torch.progress import progress
    from hbis_torch.stack_io import read_stack
    from hbis_torch.validate.cross import DEFAULT_HOLDOUT, cross_validate
    from hbis_torch.validate.forward import DEFAULT_BLUR_PX
    from hbis_torch.validate.frames import holdout_frames
    from hbis_torch.validate.score import DEFAULT_BORDER_PX

    stack = read_stack(args.stack)
    from hbis_torch.cli import map_large_arrays

    map_large_arrays(stack.frames.size)  # as hbis reconstruct: a large stack's arrays go back when freed
    count = len(stack.frames)
    holdout = min(DEFAULT_HOLDOUT, max(1, count - 1)) if args.holdout is None else args.holdout
    holdout_frames(count, stack.reference_index, holdout)  # a bad count is refused before any work
    runs = len(names) * holdout
    messages: list[str] = []
    with progress(total=runs, desc="validate", unit="run") as bar:
        result = cross_validate(stack, names, holdout, registration=args.registration,
                                border_px=DEFAULT_BORDER_PX if args.border is None else args.border,
                                blur_px=DEFAULT_BLUR_PX if args.blur is None else args.blur,
                                method_options=options, messages=messages, on_step=bar.update)
    from hbis_torch.cli.common import tell

    tell("validate", messages)
    for name, scores in result.methods.items():
        tell("validate", scores.messages, about=name)
    if args.json:
        print(json.dumps(json_report(result, args.stack.name, stack.kind), indent=1))
    else:
        print(table(result, args.stack.name, stack.kind))
    return 0


def table(result, name: str, kind: str) -> str:
    """The text report: a header line and one row per method."""
    from hbis_torch.validate.baseline import SINGLE_FRAME

    held = ", ".join(str(k) for k in result.held_out)
    factor = f"scale S = {result.h}" if kind == "burst" else f"h = {result.h}"
    lines = [f"{name}: {'burst' if kind == 'burst' else 'HBIS scan'} of {result.frames} frames, {factor}, "
             f"reference {result.reference_index}; held out one at a time: {held}; scored on {result.scored_on}",
             f"{'method':<14} {'PSNR dB':>8} {'vs single':>9}  {'per held-out frame (dB)':<28} {'s/run':>7}"]
    base = result.methods.get(SINGLE_FRAME)
    for method, scores in result.methods.items():
        gain = f"{scores.mean_psnr - base.mean_psnr:+9.2f}" if base is not None else f"{'-':>9}"
        per = " ".join(f"{p:.2f}" for p in scores.psnr)
        lines.append(f"{method:<14} {scores.mean_psnr:8.2f} {gain}  {per:<28} {scores.seconds:7.2f}")
    return "\n".join(lines)
