"""Development matrix for the deblurring's lens spread (issue 49): the Wiener filter made the MMSE
one over a lens blur whose variance is uncertain by a share
(:data:`hbis_torch.reconstruct.classical.transfer.LENS_SPREAD`), with the lens undone at its
estimate, at the truth and over-estimated.

    python training/dev_lens_spread.py --out benchmarks/results/dev_lens_spread.json
        [--spreads 0 0.3 0.6 0.9] [--lenses est 0.3 0.42] [--renderers sim third] [--seeds ...]

Development data only: the bursts of ``training/dev_hole_share.py`` (the training simulator's
and the third renderer's with the training photographs, a lens of 0.3 LR px, 640 x 480), each
assembled once with the defaults, then the classical method with each spread (``--spreads``) and
each lens (``--lenses``: ``est``, the burst's own estimate, the default; a number, that sigma in
LR px given as ``--psf-sigma`` would). PSNR as each renderer's own evaluation scores it (4 LR px
of border left out). The summary gives, per renderer and lens, each spread's difference from no
spread (mean, worst, best). ``--seeds`` keeps the bursts of those seeds only. Each burst is
written to ``--out`` when done; a run that stops resumes at the next.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from dev_hole_share import BURSTS, sweep_burst, sweep_summary


def run_burst(renderer: str, kind: str, scale: int, frames: int, seed: int, spreads, lenses) -> dict:
    """One burst's PSNR for every spread and lens, ``"{lens}|{spread}"`` -> dB."""
    import hbis_torch.reconstruct.classical.transfer as transfer

    return sweep_burst(renderer, kind, scale, frames, seed, transfer, "LENS_SPREAD", spreads, lenses)


def summary(cells: dict, spreads, lenses) -> dict:
    """Per renderer and lens, each spread's difference from none: mean, worst, best (dB)."""
    return sweep_summary(cells, spreads, lenses, 0.0, "none")


def main(argv=None) -> int:
    from hbis_torch.provenance import write_results

    argv = sys.argv[1:] if argv is None else list(argv)
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0], epilog=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", type=Path, required=True, help="results JSON")
    p.add_argument("--spreads", nargs="+", type=float, default=[0.0, 0.3, 0.6, 0.9])
    p.add_argument("--lenses", nargs="+", default=["est", "0.3", "0.42"],
                   help="'est' (the burst's own estimate) or a sigma in LR px")
    p.add_argument("--renderers", nargs="+", choices=sorted(BURSTS), default=sorted(BURSTS))
    p.add_argument("--seeds", nargs="+", type=int, help="only the bursts of these seeds (default: all)")
    args = p.parse_args(argv)
    bad = [x for x in args.lenses if x != "est" and not x.replace(".", "", 1).isdigit()]
    if bad or 0 not in args.spreads or any(not 0 <= s < 1 for s in args.spreads):
        print(f"dev_lens_spread: --lenses takes 'est' or sigmas (got {bad}); --spreads must lie in [0, 1) and "
              "hold 0", file=sys.stderr)
        return 2
    cells = {}
    if args.out.exists():  # resume
        cells = json.loads(args.out.read_text()).get("cells", {})
    for renderer in args.renderers:
        for kind, scale, frames, seed in BURSTS[renderer]:
            if args.seeds and seed not in args.seeds:
                continue
            key = f"{renderer}|{kind}|S={scale}|F={frames}|seed {seed}"
            if key in cells:
                continue
            cells[key] = run_burst(renderer, kind, scale, frames, seed, args.spreads, args.lenses)
            print(key, {k: round(v, 2) for k, v in cells[key].items()}, flush=True)
            write_results(args.out, {"settings": vars(args) | {"out": str(args.out)}, "cells": cells}, argv=argv)
    results = {"settings": vars(args) | {"out": str(args.out)}, "cells": cells,
               "summary": summary(cells, args.spreads, args.lenses)}
    write_results(args.out, results, argv=argv)
    for key, value in results["summary"].items():
        print(key, {k: round(v, 2) if isinstance(v, float) else v for k, v in value.items()})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
