"""Check int8 models against their float32 files on the held-out matrix, cell by cell.

    python export/check_int8.py [--h 2 4 7] [--models hbis_torch/models] [--name hbis_sr_h{h}]
                                [--photos ...] [--size 72] [--out parity.json]

Every cell of the held-out matrix (:mod:`hbis_torch.training.heldout`: its conditions x its
photographs x h, stacks the training never saw) is reconstructed once by the classical step,
and the network refines it twice, from the float32 file ``NAME.onnx`` and from its int8 file
``NAME.int8.onnx`` (export/quantize_int8.py), both on onnxruntime's CPU kernels, with the
learned method's own settings (its default self-ensemble; a stack outside the training domain
is run anyway, so that every cell compares the two networks). The table per h gives, per cell,
int8 minus float32 PSNR (dB, against the truth); the goal is no cell below -0.05 dB. Exits 1 if
a cell is below ``--tolerance``.

``--bf16`` compares the float32 file run by OpenVINO in bfloat16 (``--precision bf16``; the
``openvino`` package, a CPU with bf16 units) instead of the int8 files. ``--float-activations``
adds, beside each int8 file, its twin without the activations' rounding
(:func:`hbis_torch.training.quantize.float_activations`): what the twin loses comes from the int8
file's weights, the rest of the int8 file's loss from the rounding at run time.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from hbis_torch.provenance import record_printed, write_results
from hbis_torch.reconstruct.classical import optics_cutoff
from hbis_torch.reconstruct.learned import LearnedSR, models_dir
from hbis_torch.reconstruct.learned.method import classical_and_noise
from hbis_torch.training.heldout import CONDITIONS, PHOTOS, make_stack, score
from hbis_torch.training.quantize import float_activations, int8_path


def parse(argv):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                     formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("--h", type=int, nargs="+", default=[2, 3, 4, 7], choices=[2, 3, 4, 7])
    parser.add_argument("--models", type=Path, default=None, help="folder of the models (default: shipped)")
    parser.add_argument("--name", default="hbis_sr_h{h}", help="a model's file name without .onnx, {h} its factor")
    which = parser.add_mutually_exclusive_group()
    which.add_argument("--int8", nargs="+", default=None, metavar="FILE",
                       help="int8 files to compare (each with {h}); default: NAME.int8.onnx beside the model")
    which.add_argument("--bf16", action="store_true",
                       help="compare the float32 file in OpenVINO bf16 (--precision bf16) instead of the int8 files")
    parser.add_argument("--float-activations", action="store_true",
                        help="also compare each int8 file's twin without the activations' rounding")
    parser.add_argument("--size", type=int, default=72, help="LR side of each stack (h = 7: 2/3 of it)")
    parser.add_argument("--photos", nargs="+", default=list(PHOTOS), choices=PHOTOS)
    parser.add_argument("--conditions", type=int, nargs="+", default=None, help="indices of the conditions (default: all)")
    parser.add_argument("--tolerance", type=float, default=0.05, help="largest loss of a cell, dB")
    parser.add_argument("--out", type=Path, default=None,
                        help="write every cell as JSON ({'provenance': ..., 'cells': [...]})")
    parser.add_argument("--md", type=Path, default=None,
                        help="also write the printed tables as markdown, with their provenance")
    return parser.parse_args(argv)


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    args = parse(argv)
    args.argv = argv
    for path, flag in ((args.out, "--out"), (args.md, "--md")):
        if path is not None and path.exists():
            print(f"check_int8: {path} exists; choose another {flag}", file=sys.stderr)
            return 2
    if args.bf16 and args.float_activations:
        print("check_int8: --float-activations is for the int8 files, not --bf16", file=sys.stderr)
        return 2
    folder = args.models or models_dir()
    with tempfile.TemporaryDirectory() as twins, record_printed(args.md, argv=argv):
        return compare(args, folder, Path(twins))


def compare(args, folder: Path, twins: Path) -> int:
    """Every cell of every h (main's), the float-activation twins written into ``twins``."""
    conditions = args.conditions if args.conditions is not None else range(len(CONDITIONS))
    cells, started, failed = [], time.monotonic(), False
    for h in args.h:
        model = folder / (args.name.format(h=h) + ".onnx")
        fp32 = LearnedSR(model, provider="cpu")
        if args.bf16:
            candidates = [model.with_name(model.stem + " in bf16")]
            lower = [LearnedSR(model, precision="bf16")]
            if lower[0].precision != "bf16":
                print(f"check_int8: {lower[0].note}", file=sys.stderr)
                return 2
        else:
            candidates = [Path(p.format(h=h)) for p in args.int8] if args.int8 else [int8_path(model)]
            if args.float_activations:
                candidates += [float_activations(p, twins / f"{k}" / f"{p.stem} float activations.onnx")
                               for k, p in enumerate(candidates)]
            lower = [LearnedSR(p, provider="cpu") for p in candidates]
        for c in conditions:
            for photo in args.photos:
                size = args.size if h < 7 else (2 * args.size) // 3
                stack, truth = make_stack(CONDITIONS[c], photo, h, size, seed=1000 + c)
                image, noise = classical_and_noise(stack, "optics")
                inputs = (image, noise, optics_cutoff(stack.system))
                reference = score(fp32(*inputs, extrapolate=True), truth, h)
                deltas = [score(run(*inputs, extrapolate=True), truth, h) - reference for run in lower]
                cells.append({"h": h, "condition": CONDITIONS[c].name, "photo": photo, "fp32_db": reference,
                              "classical_db": score(image, truth, h), "low_minus_fp32_db": deltas})
        failed |= print_table(h, [x for x in cells if x["h"] == h], candidates, args)
    print(f"\n{time.monotonic() - started:.0f} s")
    if args.out is not None:
        write_results(args.out, {"cells": cells}, argv=args.argv)
    return 1 if failed else 0


def print_table(h: int, rows: list[dict], candidates: list[Path], args) -> bool:
    """Print one h's cells (int8 minus fp32, dB) per candidate; True if a cell loses more than the tolerance."""
    failed = False
    for k, path in enumerate(candidates):
        print(f"\n## h = {h}: {path.name} minus {args.name.format(h=h)}.onnx, dB\n")
        print("| condition | " + " | ".join(args.photos) + " | fp32 mean |")
        print("|---" * (len(args.photos) + 2) + "|")
        for name in dict.fromkeys(x["condition"] for x in rows):
            row = [x for x in rows if x["condition"] == name]
            print(f"| {name} | " + " | ".join(f"{x['low_minus_fp32_db'][k]:+.3f}" for x in row)
                  + f" | {np.mean([x['fp32_db'] for x in row]):.2f} |")
        deltas = np.array([x["low_minus_fp32_db"][k] for x in rows])
        print(f"\nh = {h}, {path.name}: mean {deltas.mean():+.3f} dB, worst cell {deltas.min():+.3f} dB, "
              f"{int((deltas < -args.tolerance).sum())} of {deltas.size} cells below -{args.tolerance} dB")
        failed |= bool((deltas < -args.tolerance).any())
    return failed


if __name__ == "__main__":
    raise SystemExit(main())
