"""Development matrix for the lattice fit's share (issue 49): how much of the burst lattice takes
the fit to the samples (:data:`hbis_torch.reconstruct.classical.lattice_fit.HOLE_SHARE`), with
the lens undone at its estimate, at the truth and over-estimated.

    python training/dev_hole_share.py --out benchmarks/results/dev_hole_share.json
        [--shares 0.5 2 1e9] [--lenses est 0.3 0.42] [--renderers sim third]

Development data only, from two renderers with a lens of 0.3 LR px: ``sim``, the training
simulator's bursts of training/dev_wiener_fit.py (:func:`dev_wiener_fit.make_burst`: collaged
training photographs, seeds 1 and 2; a shift at S = 2 with 8 frames, turns at S = 2 with 16 and at
S = 3 with 8, a moving object at S = 2 with 16, turns at S = 4 with 16), and ``third``, the third
renderer's with the training photographs (training/eval_third_renderer.py's :func:`render`,
seeds 12 to 14; similarity and homography at S = 2 with 8 frames, similarity at S = 2 with 16, at
S = 3 with 8 and at S = 4 with 16). 640 x 480 frames.

Each burst is assembled once with the defaults; the classical method then runs with each share
(``--shares``; 1e9 fits every node) and each lens (``--lenses``: ``est``, the burst's own
estimate, the default; a number, that sigma in LR px given as ``--psf-sigma`` would). PSNR as
each renderer's own evaluation scores it (4 LR px of border left out). The summary gives, per
renderer and lens, each share's difference from the default share (mean, worst, best); the
committed benchmarks/results/dev_hole_share.json was made when the default was 0.5 (it is 2 since
that run). Each burst is written to ``--out`` when done; a run that stops resumes at the next.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

BURSTS = {
    "sim": [(kind, scale, frames, seed) for seed in (1, 2)
            for kind, scale, frames in (("shift", 2, 8), ("rot", 2, 16), ("rot", 3, 8), ("object", 2, 16),
                                        ("rot", 4, 16))],
    "third": [(motion, scale, frames, seed) for seed in (12, 13, 14)
              for motion, scale, frames in (("similarity", 2, 8), ("homography", 2, 8), ("similarity", 2, 16),
                                            ("similarity", 3, 8), ("similarity", 4, 16))],
}


def burst_and_score(renderer: str, kind: str, scale: int, frames: int, seed: int):
    """(frames, a function image -> PSNR against the burst's truth)."""
    if renderer == "sim":
        from dev_wiener_fit import make_burst, score

        truth, burst = make_burst(kind, scale, frames, seed)
        return burst, lambda image: score(image, truth, scale)
    from eval_handheld import psnr
    from eval_third_renderer import render

    from hbis_torch.training.data import TRAIN_PHOTOS

    burst, truth, _ = render(kind, scale, frames, 640, 480, seed, TRAIN_PHOTOS)
    return burst, lambda image: psnr(image, truth, 4, scale)


def sweep_burst(renderer: str, kind: str, scale: int, frames: int, seed: int, module, name: str, values,
                lenses) -> dict:
    """One burst's PSNR with ``module.name`` set to each of ``values`` and each lens,
    ``"{lens}|{value:g}"`` -> dB (the setting restored after)."""
    from hbis_torch.capture.burst import assemble_burst
    from hbis_torch.reconstruct import reconstruct

    burst, score = burst_and_score(renderer, kind, scale, frames, seed)
    stack, _ = assemble_burst(burst, scale)
    default, out = getattr(module, name), {}
    try:
        for lens in lenses:
            for value in values:
                setattr(module, name, value)
                options = {} if lens == "est" else {"lens_sigma": float(lens)}
                out[f"{lens}|{value:g}"] = score(reconstruct(stack, "classical", **options))
    finally:
        setattr(module, name, default)
    return out


def sweep_summary(cells: dict, values, lenses, baseline: float, label: str) -> dict:
    """Per renderer and lens, each value's difference from ``baseline``'s: ``minus_{label}_mean_db``,
    ``_worst_db``, ``_best_db`` and the bursts counted."""
    out = {}
    for renderer in sorted({key.split("|")[0] for key in cells}):
        rows = [c for key, c in cells.items() if key.split("|")[0] == renderer]
        for lens in lenses:
            base = [c[f"{lens}|{baseline:g}"] for c in rows]
            for value in values:
                if value == baseline:
                    continue
                gains = np.array([c[f"{lens}|{value:g}"] for c in rows]) - base
                out[f"{renderer}|{lens}|{value:g}"] = {f"minus_{label}_mean_db": float(gains.mean()),
                                                       f"minus_{label}_worst_db": float(gains.min()),
                                                       f"minus_{label}_best_db": float(gains.max()),
                                                       "bursts": len(rows)}
    return out


def run_burst(renderer: str, kind: str, scale: int, frames: int, seed: int, shares, lenses) -> dict:
    """One burst's PSNR for every share and lens, ``"{lens}|{share}"`` -> dB."""
    import hbis_torch.reconstruct.classical.lattice_fit as lattice_fit

    return sweep_burst(renderer, kind, scale, frames, seed, lattice_fit, "HOLE_SHARE", shares, lenses)


def summary(cells: dict, shares, lenses) -> dict:
    """Per renderer and lens, each share's difference from the default share: mean, worst, best (dB)."""
    from hbis_torch.reconstruct.classical.lattice_fit import HOLE_SHARE

    return sweep_summary(cells, shares, lenses, HOLE_SHARE, "default")


def main(argv=None) -> int:
    from hbis_torch.provenance import write_results

    argv = sys.argv[1:] if argv is None else list(argv)
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0], epilog=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", type=Path, required=True, help="results JSON")
    p.add_argument("--shares", nargs="+", type=float, default=[0.5, 2.0, 1e9])
    p.add_argument("--lenses", nargs="+", default=["est", "0.3", "0.42"],
                   help="'est' (the burst's own estimate) or a sigma in LR px")
    p.add_argument("--renderers", nargs="+", choices=sorted(BURSTS), default=sorted(BURSTS))
    args = p.parse_args(argv)
    from hbis_torch.reconstruct.classical.lattice_fit import HOLE_SHARE

    bad = [x for x in args.lenses if x != "est" and not x.replace(".", "", 1).isdigit()]
    if bad or HOLE_SHARE not in args.shares or any(s <= 0 for s in args.shares):
        print(f"dev_hole_share: --lenses takes 'est' or sigmas (got {bad}); --shares must be above 0 and hold "
              f"the default {HOLE_SHARE:g}", file=sys.stderr)
        return 2
    cells = {}
    if args.out.exists():  # resume
        cells = json.loads(args.out.read_text()).get("cells", {})
    for renderer in args.renderers:
        for kind, scale, frames, seed in BURSTS[renderer]:
            key = f"{renderer}|{kind}|S={scale}|F={frames}|seed {seed}"
            if key in cells:
                continue
            cells[key] = run_burst(renderer, kind, scale, frames, seed, args.shares, args.lenses)
            print(key, {k: round(v, 2) for k, v in cells[key].items()}, flush=True)
            write_results(args.out, {"settings": vars(args) | {"out": str(args.out)}, "cells": cells}, argv=argv)
    results = {"settings": vars(args) | {"out": str(args.out)}, "cells": cells,
               "summary": summary(cells, args.shares, args.lenses)}
    write_results(args.out, results, argv=argv)
    for key, value in results["summary"].items():
        print(key, {k: round(v, 2) if isinstance(v, float) else v for k, v in value.items()})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
