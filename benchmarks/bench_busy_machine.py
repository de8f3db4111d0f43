"""A hand-held burst's assemble + classical on an idle machine and beside another job, with
torch's default threads and with one.

    python benchmarks/bench_busy_machine.py [--size 640x480] [--repeats 3] [--cache DIR]
        [--json benchmarks/results/bench_busy_machine.json]

The burst is bench_handheld.py's (:func:`hbis_torch.training.handheld_render.render_burst`, motion
``all``, 16 frames, S = 2; ``--cache`` shares its files). Each run is a fresh process, as a user's
``hbis assemble`` + ``hbis reconstruct`` would be (bench_handheld.py's child: assemble, then
``reconstruct(stack, "classical")``, timed from the call). Four settings, side by side in one
run: the machine idle or beside the *other job* (a process multiplying 1500 x 1500 float32
matrices with torch's default threads, as another reconstruction or a training would keep the
cores busy, started before those runs and stopped after them), each with torch's default threads
(one a core) and with one (``OMP_NUM_THREADS=1``, as ``--threads 1`` of ``hbis assemble`` and of
``hbis reconstruct`` runs them). The median of ``--repeats`` runs of each; the ratios to the idle machine's
default are printed.

torch's CPU kernels run in OpenMP threads that spin while they wait for each other; beside
another job that keeps the cores busy, a thread that waits is often descheduled, and its partners
spin the longer.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

OTHER_JOB = ("import time, torch\na = torch.rand(1500, 1500)\nt = time.time()\n"
             "while time.time() - t < 3600:\n    a @ a\n")


def timed_runs(path: Path, threads: int | None, repeats: int) -> list[float]:
    """Seconds to the end of classical of ``repeats`` fresh processes (``threads``: OMP_NUM_THREADS)."""
    from bench_handheld import run_child  # benchmarks/ is the script's folder
    if threads is None:
        os.environ.pop("OMP_NUM_THREADS", None)
    else:
        os.environ["OMP_NUM_THREADS"] = str(threads)
    out = []
    for _ in range(repeats):
        run = run_child(path, 2, "full", False, False)
        if "failed" in run:
            raise RuntimeError(f"a run failed: {run['failed']}")
        out.append(run["assemble_s"] + run["classical_s"])
    return out


def problem_with(args) -> str | None:
    """The line that refuses ``args`` (None: they are good), before any work."""
    size = args.size.lower().split("x")
    if len(size) != 2 or not all(v.isdigit() for v in size) or min(int(v) for v in size) < 64:
        return f"--size takes WxH of 64 px or more each way, got {args.size!r}"
    args.width, args.height = (int(v) for v in size)
    if args.repeats < 1:
        return "--repeats must be 1 or more"
    for flag, folder in (("--cache", args.cache), ("--json", args.json and args.json.parent)):
        if folder is not None and not folder.is_dir():
            return f"{flag} {folder}: the folder does not exist"
    return None


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--repeats", type=int, default=3, help="fresh processes per setting, the median kept (default 3)")
    p.add_argument("--size", default="640x480", help="frames' WxH (default 640x480)")
    p.add_argument("--json", type=Path, help="write the results here (atomically)")
    p.add_argument("--cache", type=Path, help="folder of rendered bursts (bench_handheld.py's names), reused")
    args = p.parse_args(argv)
    problem = problem_with(args)
    if problem:
        print(f"bench_busy_machine: {problem}", file=sys.stderr)
        return 2
    w, h = args.width, args.height
    from bench_handheld import ROOT  # benchmarks/ is the script's folder
    folder = args.cache or Path(os.environ.get("TMPDIR", "/tmp"))
    path = folder / f"handheld_all_{w}x{h}_S2_F16_seed0.npy"
    if not path.exists():
        code = ("import sys, numpy as np; from hbis_torch.training.handheld_render import render_burst; "
                f"np.save(sys.argv[1], render_burst('all', 2, 16, {w}, {h}, seed=0).frames)")
        env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])))
        subprocess.run([sys.executable, "-c", code, str(path)], check=True, env=env)
    settings = {"idle, default threads": (False, None), "idle, one thread": (False, 1),
                "beside another job, default threads": (True, None), "beside another job, one thread": (True, 1)}
    rows, load_before = [], os.getloadavg()
    for name, (busy, threads) in settings.items():
        other = subprocess.Popen([sys.executable, "-c", OTHER_JOB]) if busy else None
        try:
            if other is not None:
                time.sleep(2)  # its threads running
            seconds = timed_runs(path, threads, args.repeats)
        finally:
            if other is not None:
                other.kill()
                other.wait()
        rows.append({"setting": name, "other_job": busy, "threads": threads or "default",
                     "seconds": seconds, "median_s": statistics.median(seconds)})
        print(f"{name}: {rows[-1]['median_s']:.2f} s (runs {', '.join(f'{s:.2f}' for s in seconds)})", flush=True)
    base = rows[0]["median_s"]
    for row in rows:
        row["over_idle_default"] = row["median_s"] / base
    print("; ".join(f"{r['setting']} {r['over_idle_default']:.2f} x" for r in rows))
    if args.json is not None:
        from hbis_torch.provenance import write_results

        write_results(args.json, {"size": args.size, "frames": 16, "scale": 2, "rows": rows,
                                  "load_average_1_5_15_min": {"before": load_before, "after": os.getloadavg()}},
                      argv=sys.argv[1:] if argv is None else argv)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
