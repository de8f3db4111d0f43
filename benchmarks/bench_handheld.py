"""Time and memory of a hand-held burst's assemble + classical, against an FFT floor and the peer.

    python benchmarks/bench_handheld.py [--sizes 640x480 4000x3000] [--frames 16] [--scale 2]
        [--threads N] [--colour] [--no-vidsr] [--no-learned] [--json benchmarks/results/bench_handheld.json]

For each size, a burst of :func:`hbis_torch.training.handheld_render.render_burst` (``--motion``,
by default ``all``: turn, perspective, rolling shutter, a moving object, brightness; 16-bit) is rendered
here and saved (``--cache DIR`` keeps it for the next run; ``--colour`` saves it as RGB frames, the
channels the grey frames times :data:`COLOUR_GAINS`: the timing and memory of a colour burst,
whose three channels the classical method reconstructs one by one); then fresh processes (so
that imports and first calls count as a user's ``hbis assemble`` + ``hbis reconstruct`` would)
run, each timed from its own start, glibc's malloc set as the hbis program sets it (``--allocator``):

* a 32 x 32 burst of the same frames' corner: assemble + classical (the *start-up*: imports, first
  calls), ``--repeats`` times, the fastest;
* the full burst (``--repeats`` times up to 1 MP, once above; the fastest run counts, as on a
  shared machine it is the least disturbed): assemble (:func:`~hbis_torch.capture.burst.assemble_burst`, defaults) and
  classical (``reconstruct(stack, "classical")``); then, in the same process, the *floor*: F FFT
  pairs (``scipy.fft.rfft2`` + ``irfft2``, float32, one worker) of one frame plus one pair of the
  output (S H x S W), the median of 5 repeats; at sizes up to 1 MP also the learned method on
  the same stack (``--no-learned`` skips it) and vidsr (benchmarks/peers/vidsr_peer.py, its
  fidelity setting; ``--no-vidsr`` skips it).

*Own time* = the full burst's time to the end of classical minus the 32 x 32 burst's; the goal of
issue 49 is own time <= 20 x floor. A colour burst's floor is its channels': three times the FFT
pairs. Peak memory: each full-burst process reports its own peak
resident set (``getrusage(RUSAGE_SELF).ru_maxrss``, read after classical, before learned and
vidsr run), and this process reads ``getrusage(RUSAGE_CHILDREN).ru_maxrss`` after it exits (the
largest child so far, the renders included). Linux starts a child's peak from its parent's
resident set at the fork, so the bursts are rendered in processes of their own and this one
stays small (``parent_rss_mb``: what every child's peak starts from).
The goal: 16 frames of 12 MP at S = 2 in <= 6 GB.

Timings on a machine shared with other jobs are noisy: the ratios are measured side by side in
one run, and the JSON says on what machine and under what load (the load average before and after).
A virtual machine's speed also drifts from one hour to the next, so a change is timed against
``--baseline DIR``, a checkout of another commit: each of its start-up and full-burst processes
runs right after this checkout's (its own ``benchmarks/bench_handheld.py``, no learned method, no
vidsr), and ``own_over_baseline`` is this checkout's own time over the baseline's. Where the
machine is busy enough that the imports alone vary by a second from process to process, the
fastest runs say little: ``own_median_s`` is the median full run's assemble + classical less the
median start-up run's (the imports, the same on both sides, left out), and
``own_median_over_baseline`` compares those (ask for ``--repeats 8`` or more).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
START = 32  # side of the start-up burst
COLOUR_GAINS = (1.0, 0.9, 0.75)  # --colour: each channel the grey frame times its gain


def child(path: str, scale: int, mode: str, learned: bool, vidsr: bool, max_gb: float, allocator: str) -> None:
    """Run in a fresh process: time what the module docstring says; print one JSON line."""
    t0 = time.perf_counter()
    if allocator == "hbis":  # first, as the hbis program does
        from hbis_torch.cli import keep_freed_memory

        keep_freed_memory()
    if max_gb > 0:  # on a shared machine a run that would take all memory fails alone (MemoryError)
        limit = int(max_gb * 2**30)
        resource.setrlimit(resource.RLIMIT_AS, (limit, limit))
    import numpy as np

    from hbis_torch.capture.burst import assemble_burst
    from hbis_torch.reconstruct import reconstruct

    frames = np.load(path, mmap_mode="r" if mode == "start" else None)
    if mode == "start":  # only the corner is read
        frames = np.ascontiguousarray(frames[:, :START, :START])
    if allocator == "hbis":  # as hbis assemble and hbis reconstruct do (a large burst's large arrays mapped)
        from hbis_torch.cli import map_large_arrays

        map_large_arrays(frames.size)
    out: dict = {"import_load_s": time.perf_counter() - t0}
    t = time.perf_counter()
    stack, messages = assemble_burst(frames, scale)
    out["assemble_s"] = time.perf_counter() - t
    t = time.perf_counter()
    reconstruct(stack, "classical")
    out["classical_s"] = time.perf_counter() - t
    out["to_classical_s"] = time.perf_counter() - t0
    out["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    out["rejected"] = int((stack.confidence == 0).sum())
    out["models"] = list(stack.meta["motion_models"])
    out["assemble_messages"] = messages
    if mode == "full":
        import scipy.fft

        F, H, W = frames.shape[:3]
        channels = frames.shape[3] if frames.ndim == 4 else 1
        one = np.random.default_rng(0).random((H, W), dtype=np.float32)
        big = np.random.default_rng(1).random((scale * H, scale * W), dtype=np.float32)

        def floor():
            for _ in range(channels):
                for _ in range(F):
                    scipy.fft.irfft2(scipy.fft.rfft2(one, workers=1), s=one.shape, workers=1)
                scipy.fft.irfft2(scipy.fft.rfft2(big, workers=1), s=big.shape, workers=1)

        times = []
        for _ in range(5):
            t = time.perf_counter()
            floor()
            times.append(time.perf_counter() - t)
        out["floor_s"] = float(np.median(times))
        if learned:
            t = time.perf_counter()
            reconstruct(stack, "learned")
            out["learned_s"] = time.perf_counter() - t
        if vidsr:
            from peers.vidsr_peer import available, vidsr_sr  # benchmarks/ is the script's folder

            if available():
                t = time.perf_counter()
                vidsr_sr(frames, scale)
                out["vidsr_s"] = time.perf_counter() - t
    print("RESULT " + json.dumps(out), flush=True)


def run_child(path: Path, scale: int, mode: str, learned: bool, vidsr: bool, max_gb: float = 0,
              allocator: str = "hbis", root: Path = ROOT) -> dict:
    """One burst's process of the checkout ``root`` (this one by default): its result line."""
    cmd = [sys.executable, str(root / "benchmarks" / "bench_handheld.py"), "--child", str(path), "--scale",
           str(scale), "--mode", mode, "--max-gb", str(max_gb), "--allocator", allocator]
    cmd += ["--no-learned"] * (not learned) + ["--no-vidsr"] * (not vidsr)
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [str(root), os.environ.get("PYTHONPATH")])))
    done = subprocess.run(cmd, capture_output=True, text=True, env=env)
    lines = [x for x in done.stdout.splitlines() if x.startswith("RESULT ")]
    if done.returncode != 0 or not lines:
        return {"failed": f"exit {done.returncode}: {done.stderr.strip().splitlines()[-1:] or ''}"}
    out = json.loads(lines[-1][len("RESULT "):])
    out["children_peak_rss_mb"] = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024
    return out


def fastest(runs: list) -> dict:
    """The run that reached the end of classical first (on a shared machine the least disturbed),
    with the largest peak memory of them all; a failed run where one failed."""
    failed = [r for r in runs if "failed" in r]
    if failed:
        return dict(failed[0])
    best = dict(min(runs, key=lambda r: r["to_classical_s"]))
    best["peak_rss_mb"] = max(r["peak_rss_mb"] for r in runs)
    return best


def median_own(start_runs: list, full_runs: list) -> float | None:
    """The median full run's assemble + classical seconds less the median start-up run's (the
    imports left out); None where a run failed."""
    if any("failed" in r for r in start_runs + full_runs):
        return None
    steps = [[r["assemble_s"] + r["classical_s"] for r in runs] for runs in (start_runs, full_runs)]
    return statistics.median(steps[1]) - statistics.median(steps[0])


def _commit(root: Path) -> str:
    """``git rev-parse HEAD`` of the checkout ``root``, with ``-dirty`` where tracked files changed."""
    head = subprocess.run(["git", "-C", str(root), "rev-parse", "HEAD"], capture_output=True, text=True).stdout.strip()
    dirty = subprocess.run(["git", "-C", str(root), "status", "--porcelain", "--untracked-files=no"],
                           capture_output=True, text=True).stdout.strip()
    return (head or "unknown") + ("-dirty" if dirty else "")


def parse_size(text: str) -> tuple[int, int]:
    w, h = (int(x) for x in text.lower().split("x"))
    if w < START or h < START:
        raise ValueError
    return w, h


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--sizes", nargs="+", default=["640x480", "4000x3000"], help="frame sizes WxH (default 640x480 "
                   "4000x3000)")
    p.add_argument("--frames", type=int, default=16)
    p.add_argument("--motion", default="all", help="the burst's motion (handheld_render.MOTIONS; default all)")
    p.add_argument("--scale", type=int, default=2)
    p.add_argument("--repeats", type=int, default=3, help="fresh processes per size up to 1 MP, and for the "
                   "start-up burst; the fastest counts (default 3; one above 1 MP)")
    p.add_argument("--max-gb", type=float, default=14.0, help="address space a full-burst process may take, GiB "
                   "(default 14; 0: no limit): above it the run fails with MemoryError rather than crowd the machine")
    p.add_argument("--threads", type=int, default=0, help="threads of each burst's process (OMP_NUM_THREADS; "
                   "default 0: torch's own choice, one a core). On a machine shared with other jobs one thread "
                   "keeps the time beside the floor's (one FFT worker) from the cost of contended threads")
    p.add_argument("--colour", action="store_true", help="RGB frames (the grey burst's channels times "
                   f"{COLOUR_GAINS}): a colour burst's time and memory")
    p.add_argument("--allocator", choices=("hbis", "default"), default="hbis", help="glibc malloc's settings in "
                   "each burst's process: hbis (the default) as the hbis program sets them (freed memory kept in the "
                   "heap, hbis_torch.cli.keep_freed_memory; a large burst's large arrays mapped, map_large_arrays); "
                   "default leaves glibc's own (the library called from another program)")
    p.add_argument("--no-learned", action="store_true")
    p.add_argument("--no-vidsr", action="store_true")
    p.add_argument("--json", type=Path, help="write the results here (atomically)")
    p.add_argument("--cache", type=Path, help="keep the rendered bursts in this folder and reuse them (a 12 MP "
                   "burst takes minutes to render)")
    p.add_argument("--baseline", type=Path, metavar="DIR", help="a checkout of another commit (git worktree add "
                   "DIR COMMIT), each of whose burst processes runs right after this checkout's: its own time "
                   "beside this one's, under the same machine")
    p.add_argument("--child", help=argparse.SUPPRESS)
    p.add_argument("--mode", default="full", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.child:
        child(args.child, args.scale, args.mode, not args.no_learned, not args.no_vidsr, args.max_gb, args.allocator)
        return 0
    try:
        sizes = sorted((parse_size(s) for s in args.sizes), key=lambda wh: wh[0] * wh[1])
    except ValueError:
        print(f"bench_handheld: --sizes must be WxH of {START} x {START} px or more, got {args.sizes}", file=sys.stderr)
        return 2
    from hbis_torch.training.handheld_render import MOTIONS

    if args.motion not in MOTIONS:
        print(f"bench_handheld: --motion must be one of {', '.join(MOTIONS)}", file=sys.stderr)
        return 2
    if args.frames < 2 or not 1 <= args.scale <= 8 or args.repeats < 1 or args.threads < 0:
        print("bench_handheld: --frames must be 2 or more, --scale 1..8, --repeats 1 or more and --threads 0 or "
              "more", file=sys.stderr)
        return 2
    if args.threads:  # the children inherit it
        os.environ["OMP_NUM_THREADS"] = str(args.threads)
    if args.cache is not None and not args.cache.is_dir():
        print(f"bench_handheld: --cache {args.cache}: the folder does not exist", file=sys.stderr)
        return 2
    if args.baseline is not None and not (args.baseline / "benchmarks" / "bench_handheld.py").is_file():
        print(f"bench_handheld: --baseline {args.baseline}: not a checkout of the project", file=sys.stderr)
        return 2
    if args.json is not None and not args.json.parent.is_dir():
        print(f"bench_handheld: --json {args.json}: the folder does not exist", file=sys.stderr)
        return 2

    rows, load_before = [], os.getloadavg()
    with tempfile.TemporaryDirectory() as tmp:
        for w, h in sizes:
            t = time.perf_counter()
            name = f"handheld_{args.motion}_{w}x{h}_S{args.scale}_F{args.frames}_seed0{'_rgb' * args.colour}.npy"
            path = (args.cache or Path(tmp)) / name
            if not path.exists():  # in a process of its own: this one stays small, and a child's peak
                # memory (which Linux starts from its parent's at the fork) is its own
                code = ("import sys, numpy as np; from hbis_torch.training.handheld_render import render_burst; "
                        f"f = render_burst({args.motion!r}, {args.scale}, {args.frames}, {w}, {h}, seed=0).frames; ")
                code += (f"rgb = np.empty(f.shape + (3,), f.dtype)\nfor k in range(len(f)): rgb[k] = np.round("
                         f"f[k][..., None] * np.array({COLOUR_GAINS}))\nf = rgb\n") if args.colour else ""
                code += "np.save(sys.argv[1], f)"
                env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])))
                subprocess.run([sys.executable, "-c", code, str(path)], check=True, env=env)
            row = {"size": f"{w}x{h}", "megapixels": w * h / 1e6, "frames": args.frames, "scale": args.scale,
                   "motion": args.motion, "colour": args.colour,
                   "render_s": time.perf_counter() - t}
            measure(row, path, w, h, args)
            rows.append(row)
            print(json.dumps(row), flush=True)
            if args.cache is None:
                path.unlink()
    if args.json is not None:
        from hbis_torch.provenance import write_results

        write_results(args.json, {"rows": rows, "threads": args.threads or "default", "allocator": args.allocator,
                                  "load_average_1_5_15_min": {"before": load_before, "after": os.getloadavg()}},
                      argv=sys.argv[1:] if argv is None else argv)
    for r in rows:
        print(summary(r))
    return 0


def measure(row: dict, path: Path, w: int, h: int, args) -> None:
    """Fill ``row`` with the start-up and full-burst runs of the burst at ``path`` (w x h px), this
    checkout's and the ``--baseline``'s interleaved, and the ratios (module docstring)."""
    small = w * h <= 1_000_000
    repeats = args.repeats if small else 1
    row["parent_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    base = {"root": str(args.baseline), "commit": _commit(args.baseline), "start_runs": [],
            "full_runs": []} if args.baseline else None
    row["start_runs"], row["full_runs"] = [], []
    for _ in range(args.repeats):
        row["start_runs"].append(run_child(path, args.scale, "start", False, False, allocator=args.allocator))
        if base:
            base["start_runs"].append(run_child(path, args.scale, "start", False, False,
                                                allocator=args.allocator, root=args.baseline))
    for i in range(repeats):
        row["full_runs"].append(run_child(path, args.scale, "full", small and not args.no_learned and i == 0,
                                          small and not args.no_vidsr and i == 0, args.max_gb, args.allocator))
        if base:
            base["full_runs"].append(run_child(path, args.scale, "full", False, False, args.max_gb,
                                               args.allocator, root=args.baseline))
    if base:
        base["start"], base["full"] = fastest(base["start_runs"]), fastest(base["full_runs"])
        if "failed" not in base["full"] and "failed" not in base["start"]:
            base["own_s"] = base["full"]["to_classical_s"] - base["start"]["to_classical_s"]
            base["own_over_floor"] = base["own_s"] / base["full"]["floor_s"]
        row["baseline"] = base
    row["start"], row["full"] = (fastest(row["start_runs"]), fastest(row["full_runs"]))
    full, start = row["full"], row["start"]
    if "failed" not in full and "failed" not in start:
        for key in ("learned_s", "vidsr_s"):  # measured in the first run only
            if key in row["full_runs"][0]:
                full[key] = row["full_runs"][0][key]
        row["own_s"] = full["to_classical_s"] - start["to_classical_s"]
        row["own_over_floor"] = row["own_s"] / full["floor_s"]
        if "learned_s" in full:
            row["learned_over_classical"] = full["learned_s"] / full["classical_s"]
            row["learned_over_classical_with_assemble"] = ((full["learned_s"] + full["assemble_s"])
                                                           / (full["classical_s"] + full["assemble_s"]))
        if "vidsr_s" in full:
            row["vidsr_over_hbis"] = full["vidsr_s"] / (full["assemble_s"] + full["classical_s"])
        if base and "own_s" in base:
            row["own_over_baseline"] = row["own_s"] / base["own_s"]
    row["own_median_s"] = median_own(row["start_runs"], row["full_runs"])
    if base:
        base["own_median_s"] = median_own(base["start_runs"], base["full_runs"])
        if row["own_median_s"] is not None and base["own_median_s"]:
            row["own_median_over_baseline"] = row["own_median_s"] / base["own_median_s"]


def summary(r: dict) -> str:
    """One line per size."""
    f = r["full"]
    if "failed" in f:
        return f"{r['size']}: failed ({f['failed']})"
    colour = " RGB" if r.get("colour") else ""
    text = (f"{r['size']} x {r['frames']}{colour}, S = {r['scale']}: assemble {f['assemble_s']:.2f} s + classical "
            f"{f['classical_s']:.2f} s; own time {r['own_s']:.2f} s = {r['own_over_floor']:.0f} x the FFT floor "
            f"({f['floor_s']:.3f} s); peak RSS {f['peak_rss_mb']:.0f} MB")
    if "learned_over_classical" in r:
        text += f"; learned {f['learned_s']:.2f} s = {r['learned_over_classical']:.1f} x classical"
    if "vidsr_over_hbis" in r:
        text += f"; vidsr {f['vidsr_s']:.2f} s = {r['vidsr_over_hbis']:.1f} x assemble + classical"
    if "own_over_baseline" in r:
        b = r["baseline"]
        text += (f"; the baseline {b['commit'][:10]}: own time {b['own_s']:.2f} s = {b['own_over_floor']:.0f} x "
                 f"the floor, this one {r['own_over_baseline']:.2f} x its")
    if "own_median_over_baseline" in r:
        text += (f"; medians, imports left out: {r['own_median_s']:.2f} s against "
                 f"{r['baseline']['own_median_s']:.2f} s, {r['own_median_over_baseline']:.2f} x")
    return text


if __name__ == "__main__":
    raise SystemExit(main())
