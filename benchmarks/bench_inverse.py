"""Exact inverse against the paper's closed form (eqs. 8-9) for one 49-point scan (h = 7).

Both run in the same process on the same targets, interleaved, so their ratio is fair on a busy
machine. Goal: the exact inverse within 10x of the closed form and at most 10 ms.

    python3 benchmarks/bench_inverse.py [--repeats 200] [--phases-deg 5,70]
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import torch

from hbis_torch.config import FoveaSystem
from hbis_torch.optics.inverse import exact_inverse, paper_inverse, paper_norms
from hbis_torch.provenance import run_recorded
from hbis_torch.scan import axis_alignment_error, plan_scan


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=200)
    parser.add_argument("--h", type=int, default=7)
    parser.add_argument("--phases-deg", default="5,70")
    parser.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    parser.add_argument("--out", type=Path, default=None,
                        help="also write what is printed to this file (.txt/.md, or .json), with its provenance")
    args = parser.parse_args(argv)
    return run_recorded("bench_inverse", measure, args, argv)


def measure(args):
    """Run the benchmark and print its result."""
    torch.set_num_threads(args.threads)

    system = FoveaSystem()
    initial = tuple(float(v) for v in args.phases_deg.split(","))
    plan = plan_scan(system, args.h, initial)  # targets DV^0 + SL * offsets (shared by both)
    targets = plan.targets_mm
    current = torch.tensor(initial, dtype=torch.float64)

    def closed_form():
        k1, k2 = paper_norms(system, initial)  # eq. 8, with the exact trace of DV^0
        return paper_inverse(targets, k1, k2, current)  # eq. 9

    def exact():
        return exact_inverse(system, targets, current)

    solvers = {"paper closed form": closed_form, "exact inverse": exact}
    times = {name: [] for name in solvers}
    for _ in range(10):  # warm-up
        for fn in solvers.values():
            fn()
    for _ in range(args.repeats):
        for name, fn in solvers.items():
            start = time.perf_counter()
            fn()
            times[name].append(time.perf_counter() - start)

    print(f"{targets.shape[0]} targets (h = {args.h}, initial phases {initial}), "
          f"{args.repeats} interleaved repeats, torch threads {torch.get_num_threads()}")
    medians = {}
    for name, fn in solvers.items():
        phases = fn()
        plan.phases_deg = phases
        ae = float(axis_alignment_error(system, plan).max())
        medians[name] = statistics.median(times[name])
        print(f"  {name:18s} median {medians[name] * 1e3:7.3f} ms   "
              f"min {min(times[name]) * 1e3:7.3f} ms   axis AE max {ae:.3g} SL")
    ratio = medians["exact inverse"] / medians["paper closed form"]
    exact_ms = medians["exact inverse"] * 1e3
    print(f"  ratio exact / closed form: {ratio:.2f}x (goal <= 10x: "
          f"{'met' if ratio <= 10 else 'NOT met'}); exact {exact_ms:.3f} ms (goal <= 10 ms: "
          f"{'met' if exact_ms <= 10 else 'NOT met'})")


if __name__ == "__main__":
    raise SystemExit(main())
