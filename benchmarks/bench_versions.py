"""One method's end-to-end time in this checkout and in another version of the project, side by side.

    git worktree add /tmp/hbis-previous <commit>          # the version to compare with
    python benchmarks/bench_versions.py --previous /tmp/hbis-previous [--method learned] [--h 4] [--size 256]

Simulates one stack (``words`` at the sensor's centre, 12-bit), writes it to a temporary file,
and times ``reconstruct(read_stack(path), method, registration="optics")`` in two worker
processes, one importing this checkout and one the other (``PYTHONPATH``), in turn: one call
each to warm up, then ``--repeats`` calls each, alternating, so that other load on the cores
slows both alike. Prints the medians and the new/previous ratio, and the PSNR of each against
the truth. Each worker uses the same threads (``--threads``, default 2).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from hbis_torch.provenance import run_recorded

REPO = Path(__file__).resolve().parents[1]

WORKER = r"""
import json, sys, time
import numpy as np
import torch
torch.set_num_threads({threads})
from hbis_torch.metrics import psnr
from hbis_torch.reconstruct import reconstruct
from hbis_torch.stack_io import read_stack
stack = read_stack({stack!r})
truth = np.load({truth!r})
for line in sys.stdin:
    t0 = time.perf_counter()
    image = reconstruct(stack, {method!r}, registration="optics")
    seconds = time.perf_counter() - t0
    print(json.dumps({{"seconds": seconds, "psnr": psnr(truth, image)}}), flush=True)
"""


def start_worker(checkout: Path, script: str) -> subprocess.Popen:
    env = dict(os.environ, PYTHONPATH=str(checkout))
    return subprocess.Popen([sys.executable, "-c", script], cwd=checkout, env=env, text=True,
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE)


def call(worker: subprocess.Popen) -> dict:
    worker.stdin.write("go\n")
    worker.stdin.flush()
    line = worker.stdout.readline()
    if not line:
        raise SystemExit(f"a worker stopped (exit {worker.wait()})")
    return json.loads(line)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                     formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("--previous", type=Path, required=True, help="checkout of the other version")
    parser.add_argument("--method", default="learned", choices=["learned", "classical"])
    parser.add_argument("--h", type=int, default=4)
    parser.add_argument("--size", type=int, default=256, help="ROI side, LR pixels")
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--out", type=Path, default=None,
                        help="also write what is printed to this file (.txt/.md, or .json), with its provenance")
    args = parser.parse_args(argv)
    if not (args.previous / "hbis_torch").is_dir():
        print(f"bench_versions: {args.previous} is not a checkout of this project", file=sys.stderr)
        return 2
    return run_recorded("bench_versions", measure, args, argv)


def measure(args):
    """Run the benchmark and print its result."""
    from hbis_torch.config import FoveaSystem
    from hbis_torch.simulate import simulate_stack
    from hbis_torch.stack_io import write_stack

    system = FoveaSystem()
    cam = system.camera
    roi = ((cam.cols - args.size) // 2, (cam.rows - args.size) // 2, args.size, args.size)
    with tempfile.TemporaryDirectory() as tmp:
        stack, truth = simulate_stack("words", system, args.h, roi=roi, seed=1)
        stack_path, truth_path = Path(tmp) / "stack.tif", Path(tmp) / "truth.npy"
        write_stack(stack_path, stack)
        np.save(truth_path, truth)
        script = WORKER.format(threads=args.threads, stack=str(stack_path), truth=str(truth_path),
                               method=args.method)
        workers = {"new": start_worker(REPO, script), "previous": start_worker(args.previous.resolve(), script)}
        try:
            results = {name: [] for name in workers}
            for name, worker in workers.items():
                call(worker)  # warm-up: imports, model load, first-call costs
            for _ in range(args.repeats):
                for name, worker in workers.items():
                    results[name].append(call(worker))
        finally:
            for worker in workers.values():
                worker.stdin.close()
                worker.wait()
    median = {name: statistics.median(r["seconds"] for r in rows) for name, rows in results.items()}
    load = os.getloadavg()
    print(f"{args.method}, h = {args.h}, {args.size}^2, {args.threads} threads, {args.repeats} calls each in turn "
          f"(load average {load[0]:.1f} / {load[1]:.1f} / {load[2]:.1f})")
    for name, rows in results.items():
        print(f"  {name:9s} {median[name]:.3f} s median (fastest {min(r['seconds'] for r in rows):.3f} s), "
              f"PSNR {rows[0]['psnr']:.2f} dB")
    print(f"  new / previous: {median['new'] / median['previous']:.2f}x")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
