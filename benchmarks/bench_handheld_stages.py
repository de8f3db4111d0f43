"""Where a hand-held burst's assemble + classical time goes, stage by stage, beside the FFT floor.

    python benchmarks/bench_handheld_stages.py [--size 640x480] [--frames 16] [--scale 2]
        [--repeats 3] [--cache DIR] [--json benchmarks/results/bench_handheld_stages.json]

The burst is bench_handheld.py's (:func:`hbis_torch.training.handheld_render.render_burst`,
motion ``all``, seed 0; ``--cache`` shares its files). In one process, after a first full run
(imports, first calls): ``--repeats`` times, ``assemble_burst`` then ``reconstruct(stack,
"classical")`` under cProfile, each stage's cumulative time read from the profile (the stages
below; "rest" is the step's time that no stage holds), the median over the repeats; then the
same without the profiler (the plain time, which the profiler's overhead inflates less than it
does the many small calls), and the floor of bench_handheld.py (F FFT pairs of one frame plus
one pair of the output, float32, one worker). Each stage is printed in seconds and in floors.

A stage map for the speed work, not the goal's measurement: bench_handheld.py measures the own
time against the floor from fresh processes.
"""

from __future__ import annotations

import argparse
import cProfile
import pstats
import sys
import time
from pathlib import Path

import numpy as np

# (step, stage, file suffix, function): the stages whose cumulative time is read from the profile
STAGES = (
    ("assemble", "pyramid and coarse-to-fine start", "registration/pyramid.py", "coarse_to_fine"),
    ("assemble", "every model's fit", "registration/stack.py", "register_models"),
    ("assemble", "model evidence", "registration/evidence.py", "model_evidence"),
    ("assemble", "local shifts", "registration/local.py", "local_offsets"),
    ("assemble", "brightness fit", "capture/brightness.py", "fit_gain_offset"),
    ("classical", "robustness weights (and positions)", "reconstruct/burst.py", "robustness_weights"),
    ("classical", "lens estimate", "reconstruct/lens_blur.py", "burst_lens"),
    ("classical", "splat", "reconstruct/classical/splat.py", "splat_on_lattice"),
    ("classical", "lattice fit of the holes", "reconstruct/classical/lattice_fit.py", "fill_holes_from_samples"),
    ("classical", "Wiener deblurring", "reconstruct/classical/wiener.py", "wiener_deblur"),
)


def cumulative(profile: cProfile.Profile, step: str) -> dict:
    """Each of ``step``'s stages' cumulative seconds in ``profile`` (summed over the functions of
    that name)."""
    stats = pstats.Stats(profile).stats
    out = {}
    for of, stage, suffix, name in STAGES:
        if of != step:
            continue
        out[stage] = sum(row[3] for (path, _, func), row in stats.items()
                         if func == name and path.replace("\\", "/").endswith(suffix))
    return out


def floor_s(frames: np.ndarray, scale: int) -> float:
    """bench_handheld.py's floor: the median of 5 runs of F FFT pairs of a frame and one of the output."""
    import scipy.fft

    F, H, W = frames.shape
    one = np.random.default_rng(0).random((H, W), dtype=np.float32)
    big = np.random.default_rng(1).random((scale * H, scale * W), dtype=np.float32)
    times = []
    for _ in range(5):
        t = time.perf_counter()
        for _ in range(F):
            scipy.fft.irfft2(scipy.fft.rfft2(one, workers=1), s=one.shape, workers=1)
        scipy.fft.irfft2(scipy.fft.rfft2(big, workers=1), s=big.shape, workers=1)
        times.append(time.perf_counter() - t)
    return float(np.median(times))


def run(frames: np.ndarray, scale: int, repeats: int) -> dict:
    """The stages' median seconds, each step's profiled and plain seconds."""
    from hbis_torch.capture.burst import assemble_burst
    from hbis_torch.reconstruct import reconstruct

    stack, _ = assemble_burst(frames, scale)  # imports and first calls
    reconstruct(stack, "classical")
    profiled: dict[str, list] = {}
    for _ in range(repeats):
        for step in ("assemble", "classical"):
            profile = cProfile.Profile()
            t = time.perf_counter()
            profile.enable()
            if step == "assemble":
                stack, _ = assemble_burst(frames, scale)
            else:
                reconstruct(stack, "classical")
            profile.disable()
            profiled.setdefault(step, []).append(time.perf_counter() - t)
            for stage, seconds in cumulative(profile, step).items():
                profiled.setdefault(stage, []).append(seconds)
    plain = {"assemble": [], "classical": []}
    for _ in range(repeats):
        t = time.perf_counter()
        stack, _ = assemble_burst(frames, scale)
        plain["assemble"].append(time.perf_counter() - t)
        t = time.perf_counter()
        reconstruct(stack, "classical")
        plain["classical"].append(time.perf_counter() - t)
    median = {k: float(np.median(v)) for k, v in profiled.items()}
    return {"profiled_s": median, "plain_s": {k: float(np.median(v)) for k, v in plain.items()}}


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0], epilog=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--size", default="640x480", help="the frames' WxH (default 640x480)")
    p.add_argument("--frames", type=int, default=16, help="frames in the burst (default 16)")
    p.add_argument("--scale", type=int, default=2, help="S (default 2)")
    p.add_argument("--repeats", type=int, default=3, help="profiled and plain runs, the median kept (default 3)")
    p.add_argument("--cache", type=Path, help="folder of rendered bursts (bench_handheld.py's names), reused")
    p.add_argument("--json", type=Path, help="results file")
    args = p.parse_args(argv)
    try:
        w, h = (int(v) for v in args.size.lower().split("x"))
    except ValueError:
        w = h = 0
    problem = None
    if min(w, h) < 64:
        problem = f"--size {args.size!r}: give WxH, each 64 px or more"
    elif args.frames < 2 or not 2 <= args.scale <= 4 or args.repeats < 1:
        problem = "--frames takes 2 or more, --scale 2 to 4, --repeats 1 or more"
    elif args.cache is not None and not args.cache.is_dir():
        problem = f"--cache {args.cache}: the folder does not exist"
    if problem:
        print(f"bench_handheld_stages: {problem}", file=sys.stderr)
        return 2
    name = f"handheld_all_{w}x{h}_S{args.scale}_F{args.frames}_seed0.npy"
    path = None if args.cache is None else args.cache / name
    if path is not None and path.exists():
        frames = np.load(path)
    else:
        from hbis_torch.training.handheld_render import render_burst

        frames = render_burst("all", args.scale, args.frames, w, h, seed=0).frames
        if path is not None:
            np.save(path, frames)
    result = run(frames, args.scale, args.repeats)
    floor = floor_s(frames, args.scale)
    profiled = result["profiled_s"]
    rows = []
    for step in ("assemble", "classical"):
        stages = [(stage, profiled[stage]) for s, stage, _, _ in STAGES if s == step]
        stages.append(("rest", profiled[step] - sum(t for _, t in stages)))
        rows += [{"step": step, "stage": stage, "seconds": t, "floors": t / floor} for stage, t in stages]
    out = {"size": f"{w}x{h}", "frames": args.frames, "scale": args.scale, "repeats": args.repeats,
           "floor_s": floor, **result, "stages": rows}
    for row in rows:
        print(f"{row['step']:9s} {row['stage']:38s} {row['seconds']:6.3f} s {row['floors']:6.1f} floors")
    print(f"profiled: assemble {profiled['assemble']:.3f} s, classical {profiled['classical']:.3f} s; plain: "
          f"assemble {result['plain_s']['assemble']:.3f} s, classical {result['plain_s']['classical']:.3f} s; "
          f"floor {floor:.4f} s")
    if args.json is not None:
        from hbis_torch.provenance import write_results

        write_results(args.json, out, argv)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
