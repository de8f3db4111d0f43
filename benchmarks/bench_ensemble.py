"""The learned method's self-ensemble: time against error, each size side by side in one run.

    python benchmarks/bench_ensemble.py                       # h = 2 and 4, 256 x 256 sensor ROI
    python benchmarks/bench_ensemble.py --hs 4 --size 128 --repeats 9

``hbis reconstruct --method learned --ensemble N`` averages the network over N of the square's
8 symmetries (:func:`hbis_torch.reconstruct.learned.self_ensemble`). For each h this simulates
one stack per scikit-image photograph, the first condition of the held-out matrix
(:mod:`hbis_torch.training.heldout`, which ``training/eval_matrix.py`` scores: never in
training; Airy F 1.4, 10,000 e-, reference frame 0, the noise measured on the lattice as for a captured stack), computes the classical image and its
noise once, then times :class:`~hbis_torch.reconstruct.learned.LearnedSR` (the network, tiled,
and its glue) at every ensemble size in turn, ``--repeats`` rounds after a warm-up, and scores
each against the simulator's truth. The end-to-end column adds the classical step's median
time, measured in the same rounds. Prints one table per h (medians) with the time and the PSNR
gain over the classical image and over an ensemble of 1; ``--json`` writes the rows.
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import numpy as np
import torch

from hbis_torch.metrics import psnr
from hbis_torch.reconstruct.classical import optics_cutoff
from hbis_torch.reconstruct.learned import LearnedSR
from hbis_torch.reconstruct.learned.inputs import ENSEMBLE_SIZES
from hbis_torch.reconstruct.learned.method import classical_and_noise
from hbis_torch.training.heldout import CONDITIONS, PHOTOS, make_stack  # the held-out stacks


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--hs", type=int, nargs="+", default=[2, 4], choices=[2, 3, 4, 7])
    parser.add_argument("--size", type=int, default=256, help="sensor ROI side, LR pixels")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    rows = []
    for h in args.hs:
        runner = LearnedSR(h=h, threads=args.threads)
        times = {n: [] for n in ENSEMBLE_SIZES}
        classical_times, scores = [], {n: [] for n in ENSEMBLE_SIZES}
        classical_scores = []
        for index, name in enumerate(PHOTOS):
            stack, truth = make_stack(CONDITIONS[0], name, h, args.size, seed=1000 + index)
            cutoff = optics_cutoff(stack.system)
            for round_ in range(args.repeats + 1):  # the first round warms up
                t = time.perf_counter()
                image, noise = classical_and_noise(stack, "optics")
                elapsed = time.perf_counter() - t
                if round_:
                    classical_times.append(elapsed)
                for n in ENSEMBLE_SIZES:
                    t = time.perf_counter()
                    out = runner(image, noise, cutoff, ensemble=n, extrapolate=True)
                    if round_:
                        times[n].append(time.perf_counter() - t)
                    if round_ == 1:
                        scores[n].append(psnr(out, truth))
                if round_ == 1:
                    classical_scores.append(psnr(np.clip(image, 0, 1), truth))
        classical_s = statistics.median(classical_times)
        print(f"\n## h = {h}, {args.size} x {args.size} sensor ROI, {len(PHOTOS)} photographs\n")
        print(f"classical step (image and noise): {classical_s:.3f} s (median); classical PSNR "
              f"{np.mean(classical_scores):.2f} dB (mean)\n")
        print("| ensemble | network and glue [s] | end to end [s] | x ensemble 1, end to end | "
              "PSNR [dB] | over classical [dB] | over ensemble 1 [dB] |")
        print("| ---: | ---: | ---: | ---: | ---: | ---: | ---: |")
        base_total = classical_s + statistics.median(times[1])
        for n in ENSEMBLE_SIZES:
            network_s = statistics.median(times[n])
            total = classical_s + network_s
            gain = np.mean(scores[n]) - np.mean(classical_scores)
            over_one = np.mean(scores[n]) - np.mean(scores[1])
            print(f"| {n} | {network_s:.3f} | {total:.3f} | {total / base_total:.2f} | "
                  f"{np.mean(scores[n]):.2f} | {gain:+.2f} | {over_one:+.2f} |")
            rows.append({"h": h, "size": args.size, "ensemble": n, "network_s": network_s,
                         "classical_s": classical_s, "psnr_db": float(np.mean(scores[n])),
                         "classical_psnr_db": float(np.mean(classical_scores))})
    if args.json is not None:
        from hbis_torch.provenance import write_results

        write_results(args.json, {"rows": rows}, argv=argv)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
