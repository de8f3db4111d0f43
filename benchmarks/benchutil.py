"""Shared pieces of the single-core benchmarks (classical, registration, adaptive h).

Import this module before numpy, scipy or torch: it pins their thread pools to one thread, so
that a comparison is single-core on both sides and other jobs on the machine do not tilt it
(idle BLAS threads spinning on busy cores).
"""

from __future__ import annotations

import os
import statistics
import time

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")


def cpu_timed(fn, repeats: int):
    """(result, median CPU seconds of this process over ``repeats`` calls): on cores shared with
    other jobs the CPU time of a single-threaded run is steadier than the wall clock."""
    times, result = [], None
    for _ in range(repeats):
        t = time.process_time()
        result = fn()
        times.append(time.process_time() - t)
    return result, statistics.median(times)


def finish(args, rows: list, summary: dict, argv=None) -> dict:
    """The benchmark's result (settings, rows, summary), also written atomically to ``args.json``
    with its provenance (:func:`hbis_torch.provenance.write_results`; ``argv`` the arguments parsed,
    ``sys.argv[1:]`` by default)."""
    result = {"settings": {k: v for k, v in vars(args).items() if k != "json"}, "rows": rows,
              "summary": summary}
    if args.json:
        from hbis_torch.provenance import write_results

        result = {"provenance": write_results(args.json, result, argv=argv), **result}
    return result
