"""The learned method against the classical one on stacks the training never saw.

    python training/eval_matrix.py [--h 2 4 7] [--tier fast|best | --models DIR] [--ensemble 8] [--out matrix.json] [--md matrix.md]
    python training/eval_matrix.py --bursts [--h 2 3 4] [--models DIR] [--no-adapt] [--out bursts.json] [--md bursts.md]

Held out from training on every axis at once:

* **Scenes**: photographs from scikit-image (:data:`PHOTOS`,
  ``hbis_torch.simulate.rasters.HELD_OUT_PHOTOS``); the training pool has procedural scenes,
  procedural natural-image rasters and scikit-image's other photographs (brick, grass, gravel,
  moon, ...), never these.
* **Forward models** the training never used: a Gaussian lens PSF in place of the Airy one, and
  vignetting with fixed-pattern noise (pixel gain and dark offsets, the same in every frame).
* **Settings outside the training ranges**: F 11 (training: F 1 to 8) and a 300,000 e- full well
  (training: 1,000 to 100,000).
* **A second forward model** (:mod:`hbis_torch.training.independent_render`, rows marked "[independent
  renderer]"): frames and truth rendered apart from the project's simulator, every pixel of every
  frame averaging the lens-blurred scene over its own footprint traced at its own phases, the
  noise drawn with numpy; only the metadata (system, scan, where the scene sits) comes from the
  simulator's stack.
* **Captured-like metadata**: the stacks do not carry their noise model (as a stack assembled from
  a camera does not), so the noise is measured (on the classical step's lattice,
  :func:`~hbis_torch.reconstruct.learned.method.classical_and_noise`); one row keeps it, to compare.

With ``--bursts`` the rows are bursts of a freely moving camera instead, from a renderer of their
own (:mod:`hbis_torch.training.heldout_burst`: pixel footprints traced through each frame's
homography, Poisson-Gaussian noise, a disc defocus, a moving object, brightness changes, few or
many frames, rotation and zoom), assembled as a user's burst is (``hbis assemble --burst``,
motion measured) and reconstructed by ``hbis reconstruct``'s full burst path; h is then the
burst's scale S.

The conditions, photographs and stacks are :mod:`hbis_torch.training.heldout`'s (shared with
training/variants_ab.py and benchmarks/bench_ensemble.py).
Every cell is one stack (a condition of :data:`CONDITIONS` x a photograph x h), reconstructed by
both methods from the same stack with ``registration="optics"`` (the learned method as
``reconstruct(stack, "learned")`` computes it: the classical image, refined; the classical image
is computed once and the model loaded once per h); the score is the PSNR against
the simulator's ground truth without a border of 2 LR pixels. The table printed per h holds
learned minus classical for every cell, its row means, and the classical PSNR for scale.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from hbis_torch.provenance import record_printed, write_results
from hbis_torch.reconstruct.classical import optics_cutoff
from hbis_torch.reconstruct.learned import LearnedSR, estimate_noise_params
from hbis_torch.reconstruct.learned.inputs import check_ensemble
from hbis_torch.reconstruct.learned.method import classical_and_noise
from hbis_torch.reconstruct.learned.runtime import TIERS
from hbis_torch.training.data import TRAIN_PHOTOS
from hbis_torch.training.heldout import CONDITIONS, PHOTOS, make_stack, noise_ratio, score


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                     formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("--h", type=int, nargs="+", default=None, choices=[2, 3, 4, 7],
                        help="h of the scans (default 2 4 7), or the bursts' scales S (default 2 3 4)")
    parser.add_argument("--bursts", action="store_true", help="the burst rows (hbis_torch.training.heldout_burst)")
    parser.add_argument("--no-adapt", dest="adapt", action="store_false",
                        help="bursts: the network as shipped, not adapted to each burst's own frames first")
    parser.add_argument("--validate", action="store_true",
                        help="bursts: also score each cell as hbis validate does, without the truth (3 frames held "
                        "out), to compare its learned - classical with the truth's")
    models = parser.add_mutually_exclusive_group()
    models.add_argument("--tier", choices=tuple(TIERS), default="fast",
                        help="the shipped models of this tier (hbis reconstruct --model)")
    models.add_argument("--models", type=Path, default=None, help="a folder of hbis_sr_h{h}.onnx instead")
    parser.add_argument("--size", type=int, default=72, help="LR side of each stack (h = 7: 2/3 of it)")
    parser.add_argument("--photos", nargs="+", default=list(PHOTOS), choices=PHOTOS + TRAIN_PHOTOS,
                        help="the held-out photographs (default: all five); training photographs instead "
                        "(grass, gravel, ...) make a validation matrix, to choose between models without "
                        "looking at the held-out ones")
    parser.add_argument("--ensemble", type=int, default=None, choices=(1, 2, 4, 8),
                        help="the learned method's geometric self-ensemble (hbis reconstruct --ensemble; "
                        "default: the tier's, as hbis reconstruct's; a --models folder as the fast tier)")
    parser.add_argument("--out", type=Path, default=None,
                        help="write every cell as JSON ({'provenance': ..., 'cells': [...]})")
    parser.add_argument("--md", type=Path, default=None,
                        help="also write the printed tables as markdown, with their provenance")
    argv = sys.argv[1:] if argv is None else list(argv)
    args = parser.parse_args(argv)
    args.argv = argv
    for path, flag in ((args.out, "--out"), (args.md, "--md")):
        if path is not None and path.exists():
            print(f"eval_matrix: {path} exists; choose another {flag}", file=sys.stderr)
            return 2
    with record_printed(args.md, argv=args.argv):
        return burst_matrix(args) if args.bursts else scan_matrix(args)


def scan_matrix(args) -> int:
    """The scan rows: every condition x photograph x h, the shipped models against the classical image."""
    args.h = args.h or [2, 4, 7]
    cells = []
    jobs = [(h, c, p) for h in args.h for c in range(len(CONDITIONS)) for p in args.photos]
    started = time.monotonic()
    # a tier by name, so that its default self-ensemble applies; a folder's files as the fast tier
    tier = args.tier if args.models is None else None
    runners = {h: LearnedSR(tier or args.models / f"hbis_sr_h{h}.onnx", h=h) for h in args.h}
    for h, c, photo in tqdm(jobs, desc="cells", disable=not sys.stderr.isatty()):
        size = args.size if h < 7 else (2 * args.size) // 3
        stack, truth = make_stack(CONDITIONS[c], photo, h, size, seed=1000 + c)
        classical_image, noise_params = classical_and_noise(stack, "optics")
        args_ = (classical_image, noise_params, optics_cutoff(stack.system))
        notes: list[str] = []
        learned_image = runners[h](*args_, messages=notes, ensemble=args.ensemble)
        classical, learned = score(classical_image, truth, h), score(learned_image, truth, h)
        cell = {"h": h, "condition": CONDITIONS[c].name, "photo": photo, "ensemble": check_ensemble(args.ensemble, h, tier),
                "classical_db": classical,
                "learned_db": learned, "delta_db": learned - classical,
                "classical_returned": notes[0] if notes else None,  # and why
                # the noise the network was told, and a single frame's estimate, over the sensor's
                "noise_ratio": noise_ratio(noise_params, CONDITIONS[c]),
                "frames_noise_ratio": noise_ratio(estimate_noise_params(stack.to_float().numpy()), CONDITIONS[c])}
        if notes:  # what the network would have done there
            cell["extrapolated_delta_db"] = score(runners[h](*args_, extrapolate=True, ensemble=args.ensemble), truth, h) - classical
        cells.append(cell)
    ensembles = ", ".join(f"{check_ensemble(args.ensemble, h, tier)} at h = {h}" for h in args.h)
    which = f"models in {args.models}" if args.models is not None else f"the shipped {args.tier} models"
    print(f"# learned ({which}) - classical, dB (PSNR vs truth, border {2} LR px), self-ensemble of {ensembles}; "
          f"{time.monotonic() - started:.0f} s")
    for h in args.h:
        rows = [x for x in cells if x["h"] == h]
        print(f"\n## h = {h}\n")
        print_rows(rows, CONDITIONS, args.photos)
        ratios = np.array([x["noise_ratio"] for x in rows if not x["condition"].startswith("noise in the metadata")])
        frames = np.array([x["frames_noise_ratio"] for x in rows])
        print(f"\nMeasured noise over the sensor's at mid grey (stacks without a sensor model): on the "
              f"lattice {np.median(ratios):.2f} (median; {ratios.min():.2f} to {ratios.max():.2f}); from a "
              f"single frame {np.median(frames):.2f} ({frames.min():.2f} to {frames.max():.2f})")
        deltas = np.array([x["delta_db"] for x in rows])
        print(f"\nh = {h}: mean {deltas.mean():+.2f} dB, worst cell {deltas.min():+.2f} dB, "
              f"{int((deltas < -0.3).sum())} of {deltas.size} cells below -0.3 dB")
        returned = [x for x in rows if x["classical_returned"]]
        if returned:
            reasons = sorted({x["classical_returned"].split(":")[0] for x in returned})
            by_row = {}
            for x in returned:
                by_row.setdefault(x["condition"], []).append(x["extrapolated_delta_db"])
            print("\n\\* the classical image is returned, because " + "; or ".join(reasons) + ". The network run "
                  "anyway (extrapolate=True) gives there, row means: "
                  + ", ".join(f"{name} {np.mean(v):+.2f}" for name, v in by_row.items())
                  + f" (worst cell {min(x['extrapolated_delta_db'] for x in returned):+.2f} dB).")
    if args.out is not None:
        write_results(args.out, {"cells": cells}, argv=args.argv)
    return 0


def print_rows(rows: list[dict], conditions, photos) -> None:
    """One table row per condition: learned - classical per photograph (* where the classical
    image was returned), the row's mean and its mean classical PSNR."""
    print("| condition | " + " | ".join(photos) + " | mean | classical |")
    print("|---" * (len(photos) + 3) + "|")
    for cond in conditions:
        row = [x for x in rows if x["condition"] == cond.name]
        text = [f"{x['delta_db']:+.2f}" + "*" * bool(x["classical_returned"]) for x in row]
        print(f"| {cond.name} | " + " | ".join(text) + f" | {np.mean([x['delta_db'] for x in row]):+.2f} | "
              f"{np.mean([x['classical_db'] for x in row]):.2f} |")


def burst_matrix(args) -> int:
    """The burst rows: every condition x photograph x scale, both methods through ``reconstruct``."""
    from hbis_torch.capture.burst import assemble_burst
    from hbis_torch.reconstruct import reconstruct
    from hbis_torch.training.heldout_burst import BURST_CONDITIONS, make_burst

    scales = args.h or [2, 3, 4]
    size = args.size * 2 // 3
    cells, started = [], time.monotonic()
    jobs = [(s, c, p) for s in scales for c in range(len(BURST_CONDITIONS)) for p in args.photos]
    for scale, c, photo in tqdm(jobs, desc="burst cells", disable=not sys.stderr.isatty()):
        frames, truth, bits = make_burst(BURST_CONDITIONS[c], photo, scale, size, seed=2000 + c)
        stack, _ = assemble_burst(frames, scale, bit_depth=bits)
        model = args.tier if args.models is None else str(args.models / f"hbis_sr_h{scale}.onnx")
        notes: list[str] = []
        classical = score(reconstruct(stack, "classical"), truth, scale)
        learned = score(reconstruct(stack, "learned", model=model, messages=notes, ensemble=args.ensemble,
                                    adapt=args.adapt), truth, scale)
        returned = [n for n in notes if "returns the classical image" in n]
        cells.append({"scale": scale, "condition": BURST_CONDITIONS[c].name, "photo": photo,
                      "classical_db": classical, "learned_db": learned, "delta_db": learned - classical,
                      "classical_returned": returned[0] if returned else None})
        if args.validate:
            from hbis_torch.validate import cross_validate

            scored = cross_validate(stack, ["classical", "learned"],
                                    method_options={"learned": {"model": str(model), "adapt": args.adapt}})
            cells[-1]["validate_delta_db"] = scored.gain("learned", "classical")
    which = f"models in {args.models}" if args.models is not None else f"the shipped {args.tier} models"
    which += ", adapted to each burst" if args.adapt else ", not adapted"
    print(f"# bursts: learned ({which}) - classical, dB (PSNR vs truth, border 2 LR px); "
          f"{time.monotonic() - started:.0f} s")
    for scale in scales:
        rows = [x for x in cells if x["scale"] == scale]
        print(f"\n## S = {scale}, {size} x {size} px frames\n")
        print_rows(rows, BURST_CONDITIONS, args.photos)
        deltas = np.array([x["delta_db"] for x in rows])
        print(f"\nS = {scale}: mean {deltas.mean():+.2f} dB, worst cell {deltas.min():+.2f} dB, "
              f"{int((deltas < -0.3).sum())} of {deltas.size} cells below -0.3 dB"
              + (" (* the classical image returned)" if any(x["classical_returned"] for x in rows) else ""))
        if args.validate:
            seen = np.array([x["validate_delta_db"] for x in rows])
            slope = float(np.polyfit(deltas, seen, 1)[0]) if deltas.std() > 0 else float("nan")
            print(f"hbis validate's learned - classical on the same cells (no truth): mean {seen.mean():+.2f} dB, "
                  f"worst {seen.min():+.2f} dB; it moves {slope:.2f} dB per dB of the truth's "
                  f"(correlation {np.corrcoef(deltas, seen)[0, 1]:.2f})")
    if args.out is not None:
        write_results(args.out, {"cells": cells}, argv=args.argv)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
