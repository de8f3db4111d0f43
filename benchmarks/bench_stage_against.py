"""One stage's time beside another commit's, in one process, on the same inputs.

    python benchmarks/bench_stage_against.py --baseline DIR [--stages brightness lattice_fit]
        [--size 640x480] [--frames 16] [--repeats 12] [--cache DIR] [--json benchmarks/results/bench_stage_against.json]

A burst's whole assemble + classical time moves by a tenth from one fresh process to the next on
a shared machine (bench_handheld.py), more than a cut in one stage saves. Here the stage itself
is timed: one burst (bench_handheld.py's: by default 16 frames of 640 x 480, motion ``all``, S = 2;
``--cache`` shares its file) is assembled and reconstructed once, every call of the stage's
function is recorded with its arguments, and then the calls are made again ``--repeats`` times
with this checkout's function and with the same function loaded from the baseline checkout's
file (``git worktree add DIR COMMIT``), the two alternating, the first of each pair swapped from
one repeat to the next. Printed: each one's median seconds (all the recorded calls), their ratio,
and whether the two gave the same bits. The baseline's module is its file alone, run against this
checkout's package: a comparison of that file's code, not of the commits' whole paths. A stage's
recorded calls must not change their arguments (the two here do not; a colour burst's lattice fit,
which fills a ``shared`` dictionary for the next channel, is not timed: the burst is grey).
"""

from __future__ import annotations

import argparse
import importlib
import importlib.util
import sys
import time
from pathlib import Path

import numpy as np
import torch

# name: (module, function, the modules whose name for the function the calls go through)
STAGES = {
    "brightness": ("hbis_torch.capture.brightness", "fit_gain_offset", ("hbis_torch.capture.burst",)),
    "lattice_fit": ("hbis_torch.reconstruct.classical.lattice_fit", "fit_lattice", ()),
}


def record_calls(frames: np.ndarray, scale: int, stages) -> dict:
    """Each stage's calls ([(args, kwargs)]) in one assemble + classical reconstruction."""
    from hbis_torch.capture.burst import assemble_burst
    from hbis_torch.reconstruct import reconstruct

    calls, restore = {name: [] for name in stages}, []
    for name in stages:
        module_name, function, callers = STAGES[name]
        original = getattr(importlib.import_module(module_name), function)

        def spy(*args, _name=name, _original=original, **kwargs):
            calls[_name].append((args, kwargs))
            return _original(*args, **kwargs)

        for holder in (module_name, *callers):
            module = importlib.import_module(holder)
            restore.append((module, function, getattr(module, function)))
            setattr(module, function, spy)
    try:
        stack, _ = assemble_burst(frames, scale)
        reconstruct(stack, "classical")
    finally:
        for module, function, value in restore:
            setattr(module, function, value)
    return calls


def baseline_function(root: Path, name: str):
    """The stage's function from the baseline checkout's file of its module."""
    module_name, function, _ = STAGES[name]
    path = root / (module_name.replace(".", "/") + ".py")
    spec = importlib.util.spec_from_file_location(f"baseline_{name}", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return getattr(module, function)


def same(a, b) -> bool:
    """Whether two results (tensors, numbers, tuples of them) are equal bit for bit."""
    if isinstance(a, torch.Tensor):
        return isinstance(b, torch.Tensor) and torch.equal(a, b)
    if isinstance(a, (tuple, list)):
        return isinstance(b, (tuple, list)) and len(a) == len(b) and all(same(x, y) for x, y in zip(a, b))
    return a == b


def compare(calls: list, ours, theirs, repeats: int) -> dict:
    """Median seconds of all ``calls`` with each function, alternating, and whether they agree."""
    def run(function):
        started = time.perf_counter()
        out = [function(*args, **kwargs) for args, kwargs in calls]
        return time.perf_counter() - started, out

    seconds = {"this": [], "baseline": []}
    agree = True
    for r in range(repeats):
        order = (("this", ours), ("baseline", theirs)) if r % 2 == 0 else (("baseline", theirs), ("this", ours))
        outs = {}
        for tag, function in order:
            t, outs[tag] = run(function)
            seconds[tag].append(t)
        agree = agree and same(outs["this"], outs["baseline"])
    this, baseline = float(np.median(seconds["this"])), float(np.median(seconds["baseline"]))
    return {"calls": len(calls), "this_s": this, "baseline_s": baseline, "this_over_baseline": this / baseline,
            "same_bits": agree}


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0], epilog=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--baseline", type=Path, required=True, help="a checkout of the commit to compare with")
    p.add_argument("--stages", nargs="+", default=list(STAGES), help=f"stages (default all: {', '.join(STAGES)})")
    p.add_argument("--size", default="640x480", help="the frames' WxH (default 640x480)")
    p.add_argument("--frames", type=int, default=16, help="frames in the burst (default 16)")
    p.add_argument("--repeats", type=int, default=12, help="timed runs of each, the median kept (default 12)")
    p.add_argument("--cache", type=Path, help="folder of rendered bursts (bench_handheld.py's names), reused")
    p.add_argument("--json", type=Path, help="results file")
    args = p.parse_args(argv)
    problem = None
    try:
        width, height = (int(v) for v in args.size.lower().split("x"))
    except ValueError:
        width = height = 0
    if min(width, height) < 64 or args.frames < 2:
        problem = f"--size {args.size!r} --frames {args.frames}: give WxH, each 64 px or more, and 2 frames or more"
    elif not (args.baseline / "hbis_torch").is_dir():
        problem = f"--baseline {args.baseline}: not a checkout of this project (no hbis_torch folder)"
    elif [s for s in args.stages if s not in STAGES]:
        problem = f"--stages: choose from {', '.join(STAGES)}"
    elif args.repeats < 2:
        problem = "--repeats takes 2 or more"
    elif args.cache is not None and not args.cache.is_dir():
        problem = f"--cache {args.cache}: the folder does not exist"
    if problem:
        print(f"bench_stage_against: {problem}", file=sys.stderr)
        return 2
    frames_count, scale = args.frames, 2
    name = f"handheld_all_{width}x{height}_S{scale}_F{frames_count}_seed0.npy"
    path = None if args.cache is None else args.cache / name
    if path is not None and path.exists():
        frames = np.load(path)
    else:
        from hbis_torch.training.handheld_render import render_burst

        frames = render_burst("all", scale, frames_count, width, height, seed=0).frames
        if path is not None:
            np.save(path, frames)
    calls = record_calls(frames, scale, args.stages)
    rows = []
    for name in args.stages:
        module_name, function, _ = STAGES[name]
        ours = getattr(importlib.import_module(module_name), function)
        if not calls[name]:  # (a lattice that needs no fit, say)
            print(f"{name:12s} not called on this burst: not timed")
            continue
        row = {"stage": name, "function": f"{module_name}.{function}",
               **compare(calls[name], ours, baseline_function(args.baseline, name), args.repeats)}
        rows.append(row)
        print(f"{name:12s} {row['calls']:3d} calls: {row['this_s'] * 1e3:8.1f} ms against "
              f"{row['baseline_s'] * 1e3:8.1f} ms, {row['this_over_baseline']:.2f} x; "
              f"the same bits: {row['same_bits']}")
    if args.json is not None:
        from hbis_torch.provenance import write_results

        commit = _commit(args.baseline)
        write_results(args.json, {"burst": f"{width}x{height} x {frames_count}, S = {scale}, motion all, seed 0",
                                  "repeats": args.repeats, "baseline": {"root": str(args.baseline), "commit": commit},
                                  "rows": rows}, argv)
    return 0


def _commit(root: Path) -> str | None:
    import subprocess

    done = subprocess.run(["git", "-C", str(root), "rev-parse", "HEAD"], capture_output=True, text=True)
    return done.stdout.strip() or None


if __name__ == "__main__":
    raise SystemExit(main())
