"""Time and peak memory of the raw burst path beside the grey burst path at the same size.

    python benchmarks/bench_raw_burst.py [--side 512] [--frames 16] [--scales 1 2] [--json FILE]

A simulated raw burst (hbis_torch.training.heldout_raw, astronaut, RGGB, indoor light, shifts to
1.5 px) of ``--frames`` frames of ``--side`` x ``--side`` px. Each case runs in a fresh process
(single-threaded: benchutil), so that its peak resident memory is its own:

* ``raw assemble``: registering the raw frames (their 2 x 2-cell luminance,
  hbis_torch.capture.raw.raw_burst_stack);
* ``raw joint``: the joint demosaicking and SR of that stack (reconstruct_raw_burst);
* ``grey assemble`` / ``grey burst``: the same frames as a grey burst (the normalised mosaic taken
  as grey), registered at full resolution (hbis_torch.capture.burst.assemble_burst) and
  reconstructed by the classical method's burst path ([handheld]'s grey path).

Reported: CPU seconds of the step, and the process's peak resident memory before and after it
(MiB; the difference is what the step added). CPU time on 2 shared cores is steadier than the
wall clock, but still noisy.
"""

from __future__ import annotations

import benchutil  # noqa: F401  (first: one thread for numpy and torch)

import argparse
import json
import resource
import subprocess
import sys
import time
from pathlib import Path


def _peak_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def run_case(case: str, side: int, frames: int, scale: int) -> dict:
    import numpy as np
    import torch

    torch.set_num_threads(1)
    from hbis_torch.capture.burst import assemble_burst
    from hbis_torch.capture.raw import normalised, raw_burst_stack
    from hbis_torch.reconstruct.classical.raw_burst import reconstruct_raw_burst
    from hbis_torch.reconstruct.registry import reconstruct
    from hbis_torch.training.heldout_burst import BurstCondition
    from hbis_torch.training.heldout_raw import make_raw_burst

    burst = make_raw_burst("astronaut", "RGGB", "indoor", 1, side, 1, BurstCondition("bench", frames=frames))
    grey = np.clip(normalised(burst.mosaics, burst.raw)[0], 0, 1).astype(np.float32)
    if case == "raw joint":
        stack, _ = raw_burst_stack(burst.mosaics, "RGGB", burst.raw, scale)
        step = lambda: reconstruct_raw_burst(stack)  # noqa: E731
    elif case == "raw assemble":
        step = lambda: raw_burst_stack(burst.mosaics, "RGGB", burst.raw, scale)  # noqa: E731
    elif case == "grey assemble":
        step = lambda: assemble_burst(grey, scale)  # noqa: E731
    elif case == "grey burst":
        stack, _ = assemble_burst(grey, scale)
        step = lambda: reconstruct(stack, "classical")  # noqa: E731
    else:
        raise SystemExit(f"unknown case {case!r}")
    before = _peak_mib()
    t, w = time.process_time(), time.perf_counter()
    step()
    return {"case": case, "side": side, "frames": frames, "scale": scale, "cpu_s": time.process_time() - t,
            "wall_s": time.perf_counter() - w, "peak_before_mib": before, "peak_mib": _peak_mib()}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--side", type=int, default=512)
    p.add_argument("--frames", type=int, default=16)
    p.add_argument("--scales", type=int, nargs="+", default=[1, 2])
    p.add_argument("--json", type=Path)
    p.add_argument("--case", help=argparse.SUPPRESS)
    p.add_argument("--scale", type=int, help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.case:
        print(json.dumps(run_case(args.case, args.side, args.frames, args.scale)))
        return 0
    rows = []
    for scale in args.scales:
        for case in ("raw assemble", "grey assemble", "raw joint", "grey burst"):
            if case == "grey burst" and scale == 1:
                # the RGB/grey burst path stops at S = 1 (reconstruct.burst.scale_to_run finds no scale to try)
                continue
            out = subprocess.run([sys.executable, __file__, "--case", case, "--side", str(args.side), "--frames",
                                  str(args.frames), "--scale", str(scale)], capture_output=True, text=True, check=True)
            row = json.loads(out.stdout.strip().splitlines()[-1])
            rows.append(row)
            print(f"S={scale} {case:14s} cpu {row['cpu_s']:7.2f} s  wall {row['wall_s']:7.2f} s  peak "
                  f"{row['peak_before_mib']:6.0f} -> {row['peak_mib']:6.0f} MiB", flush=True)
    if args.json:
        from hbis_torch.provenance import write_results

        write_results(args.json, {"rows": rows}, argv=argv)
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
