"""Time and peak memory of the raw burst path beside the grey burst path at the same size.

    python benchmarks/bench_raw_burst.py [--size 512x512] [--frames 16] [--scales 1 2] [--threads 1]
        [--cache DIR] [--max-gb 14] [--json FILE]

The frames are [handheld]'s hand-held burst (:func:`hbis_torch.training.handheld_render.render_burst`,
motion ``all``: turn, perspective, rolling shutter, a moving object, brightness; 16-bit, S = 2,
seed 0, as benchmarks/bench_handheld.py renders it and under the same cache name), rendered in a
process of its own (``--cache DIR`` keeps it). The grey path takes those frames as they are; the
raw path takes them as an RGGB mosaic of 12 bits over a black level of 256 (white level 4095: a
grey scene, white balance 1), the same content. Each step runs in a fresh process, as
``hbis assemble --burst`` and ``hbis reconstruct`` would, the stack passing between them as a
stack file:

* ``raw assemble``: registering the raw frames on their 2 x 2-cell luminance
  (:func:`hbis_torch.capture.raw.raw_burst_stack`);
* ``raw joint``: the joint demosaicking and SR of that stack
  (:func:`hbis_torch.reconstruct.classical.raw_burst.reconstruct_raw_burst`);
* ``grey assemble`` / ``grey burst``: the same frames as a grey burst, registered at full
  resolution (:func:`hbis_torch.capture.burst.assemble_burst`) and reconstructed by the classical
  method's burst path ([handheld]'s grey path).

Reported per step: CPU seconds and wall seconds of the step alone (the input read and the
imports before it are not counted), and the process's peak resident memory before and after it
(``getrusage(RUSAGE_SELF).ru_maxrss``, MiB). Linux starts a child's peak from its parent's
resident set at the fork, so this process imports no numpy or torch and renders nothing itself.
``--threads`` (default 1) is each step's thread count (OMP_NUM_THREADS and torch's): on cores
shared with other jobs one thread keeps the CPU time steady; the goal's "2 cores" is
``--threads 2``. Timings on a shared machine are noisy: compare the raw and grey rows of one run,
and see the load average the JSON records before and after.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CASES = ("raw assemble", "raw joint", "grey assemble", "grey burst")
BLACK, WHITE = 256, 4095  # the raw frames' levels (12 bits in a 16-bit container)
MOTION, RENDER_SCALE, SEED = "all", 2, 0  # the render (the frames are the same for every S)


def _peak_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def raw_levels(frames: int) -> dict:
    """The ``raw`` block of the benchmark's raw frames (no colour matrix, white balance 1)."""
    return {"black": [[[float(BLACK)] * 2] * 2] * frames, "white": [float(WHITE)] * frames, "gain": [1.0] * frames,
            "white_balance": [1.0, 1.0, 1.0], "colour_matrix": [[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0]],
            "orientation": 0, "camera": "simulated", "exposure_s": None, "iso": None, "noise_profile": None,
            "clip_level": 0.99}


def child(case: str, frames_path: str, stack_path: str, scale: int, threads: int, max_gb: float) -> dict:
    """One step in this fresh process (module docstring): its row."""
    if max_gb > 0:  # on a shared machine a run that would take all memory fails alone (MemoryError)
        limit = int(max_gb * 2**30)
        resource.setrlimit(resource.RLIMIT_AS, (limit, limit))
    import numpy as np
    import torch

    torch.set_num_threads(threads)
    from hbis_torch.stack_io import read_stack, write_stack

    if case == "raw assemble":
        from hbis_torch.capture.raw import raw_burst_stack

        frames = np.load(frames_path)
        mosaics = np.empty(frames.shape, dtype=np.uint16)
        for k, frame in enumerate(frames):  # 16 bits -> 12 over the black level, a frame at a time
            mosaics[k] = np.round(BLACK + frame.astype(np.float32) * ((WHITE - BLACK) / 65535))
        del frames
        step = lambda: raw_burst_stack(mosaics, "RGGB", raw_levels(len(mosaics)), scale)[0]  # noqa: E731
    elif case == "grey assemble":
        from hbis_torch.capture.burst import assemble_burst

        frames = np.load(frames_path)
        step = lambda: assemble_burst(frames, scale)[0]  # noqa: E731
    elif case == "raw joint":
        from hbis_torch.reconstruct.classical.raw_burst import reconstruct_raw_burst

        stack = read_stack(stack_path)
        step = lambda: reconstruct_raw_burst(stack)  # noqa: E731
    elif case == "grey burst":
        from hbis_torch.reconstruct.registry import reconstruct

        stack = read_stack(stack_path)
        step = lambda: reconstruct(stack, "classical")  # noqa: E731
    else:
        raise SystemExit(f"unknown case {case!r}")
    before = _peak_mib()
    t, w = time.process_time(), time.perf_counter()
    out = step()
    row = {"cpu_s": time.process_time() - t, "wall_s": time.perf_counter() - w, "peak_before_mib": before,
           "peak_mib": _peak_mib()}
    if case.endswith("assemble"):
        write_stack(stack_path, out)
    return row


def run_child(case: str, frames_path: Path, stack_path: Path, scale: int, threads: int, max_gb: float) -> dict:
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])),
               OMP_NUM_THREADS=str(threads), OPENBLAS_NUM_THREADS=str(threads), MKL_NUM_THREADS=str(threads))
    cmd = [sys.executable, __file__, "--child", case, "--frames-file", str(frames_path), "--stack-file",
           str(stack_path), "--scale", str(scale), "--threads", str(threads), "--max-gb", str(max_gb)]
    done = subprocess.run(cmd, capture_output=True, text=True, env=env)
    lines = [x for x in done.stdout.splitlines() if x.startswith("RESULT ")]
    if done.returncode != 0 or not lines:
        return {"failed": f"exit {done.returncode}: {(done.stderr.strip().splitlines() or [''])[-1]}"}
    return json.loads(lines[-1][len("RESULT "):])


def parse_size(text: str) -> tuple[int, int]:
    w, h = (int(x) for x in text.lower().split("x"))
    if w < 32 or h < 32 or w % 2 or h % 2:
        raise ValueError
    return w, h


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--size", default="512x512", help="frame size WxH, even, 32 px or more (default 512x512; the "
                   "goal's is 4000x3000)")
    p.add_argument("--frames", type=int, default=16)
    p.add_argument("--scales", type=int, nargs="+", default=[1, 2])
    p.add_argument("--threads", type=int, default=1, help="threads of each step's process (default 1)")
    p.add_argument("--max-gb", type=float, default=14.0, help="address space a step's process may take, GiB "
                   "(default 14; 0: no limit): above it the step fails with MemoryError rather than crowd the machine")
    p.add_argument("--cache", type=Path, help="keep the rendered burst in this folder and reuse it (a 12 MP burst "
                   "takes minutes to render)")
    p.add_argument("--json", type=Path)
    p.add_argument("--child", help=argparse.SUPPRESS)
    p.add_argument("--frames-file", help=argparse.SUPPRESS)
    p.add_argument("--stack-file", help=argparse.SUPPRESS)
    p.add_argument("--scale", type=int, help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.child:
        row = child(args.child, args.frames_file, args.stack_file, args.scale, args.threads, args.max_gb)
        print("RESULT " + json.dumps(row), flush=True)
        return 0
    try:
        width, height = parse_size(args.size)
    except ValueError:
        print(f"bench_raw_burst: --size must be WxH, both even and 32 px or more, got {args.size!r}", file=sys.stderr)
        return 2
    if args.frames < 2 or args.threads < 1 or not all(1 <= s <= 8 for s in args.scales):
        print("bench_raw_burst: --frames must be 2 or more, --threads 1 or more and --scales 1..8", file=sys.stderr)
        return 2
    for name, folder in (("--cache", args.cache), ("--json", args.json and args.json.parent)):
        if folder is not None and not folder.is_dir():
            print(f"bench_raw_burst: {name}: the folder {folder} does not exist", file=sys.stderr)
            return 2

    rows, load_before = [], os.getloadavg()
    with tempfile.TemporaryDirectory() as tmp:
        name = f"handheld_{MOTION}_{width}x{height}_S{RENDER_SCALE}_F{args.frames}_seed{SEED}.npy"
        frames_path = (args.cache or Path(tmp)) / name
        t = time.perf_counter()
        if not frames_path.exists():  # rendered in a process of its own: this one stays small
            code = ("import sys, numpy as np; from hbis_torch.training.handheld_render import render_burst; "
                    f"np.save(sys.argv[1], render_burst({MOTION!r}, {RENDER_SCALE}, {args.frames}, {width}, {height}, "
                    f"seed={SEED}).frames)")
            env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])))
            subprocess.run([sys.executable, "-c", code, str(frames_path)], check=True, env=env)
            print(f"rendered {width} x {height} x {args.frames} in {time.perf_counter() - t:.0f} s", flush=True)
        parent = _peak_mib()
        for scale in args.scales:
            for case in CASES:
                stack_path = Path(tmp) / f"{case.split()[0]}_S{scale}.tif"
                row = {"case": case, "size": f"{width}x{height}", "megapixels": width * height / 1e6,
                       "frames": args.frames, "scale": scale, "threads": args.threads}
                row.update(run_child(case, frames_path, stack_path, scale, args.threads, args.max_gb))
                rows.append(row)
                if "failed" in row:
                    print(f"S={scale} {case:14s} failed: {row['failed']}", flush=True)
                    continue
                print(f"S={scale} {case:14s} cpu {row['cpu_s']:7.2f} s  wall {row['wall_s']:7.2f} s  peak "
                      f"{row['peak_before_mib']:6.0f} -> {row['peak_mib']:6.0f} MiB", flush=True)
            by = {r["case"]: r for r in rows if r["scale"] == scale and "failed" not in r}
            if len(by) == len(CASES):
                raw = by["raw assemble"]["cpu_s"] + by["raw joint"]["cpu_s"]
                grey = by["grey assemble"]["cpu_s"] + by["grey burst"]["cpu_s"]
                print(f"S={scale}: raw joint / grey burst {by['raw joint']['cpu_s'] / by['grey burst']['cpu_s']:.2f} x "
                      f"CPU time, {by['raw joint']['peak_mib'] / by['grey burst']['peak_mib']:.2f} x peak; assemble + "
                      f"reconstruct {raw / grey:.2f} x", flush=True)
    if args.json:
        from hbis_torch.provenance import write_results

        write_results(args.json, {"rows": rows, "parent_peak_mib": parent, "load_average_1_5_15_min":
                                  {"before": load_before, "after": os.getloadavg()}},
                      argv=sys.argv[1:] if argv is None else argv)
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
