"""Full-frame super-resolution, end to end, against the network alone: speed, memory, linear cost.

    python benchmarks/bench_fullframe.py                    # h = 4 and 7, 3 rounds
    python benchmarks/bench_fullframe.py --hs 4 --repeats 5

The stacks are what ``hbis simulate --scene camera --h H --roi full`` writes (and the same at the
default 256 x 256 ROI, for the linear-cost check), made once into ``--work`` with their ground
truths. Every measurement runs in a fresh Python process, in turn with the others, ``--repeats``
rounds; the tables give medians:

- ``network``: the learned network alone, :meth:`LearnedSR.run_network` on inputs prepared
  beforehand (the classical image and the noise map; onnxruntime, the shipped provider), as
  many times as the learned method runs it by default (its self-ensemble: twice at h = 7). Since
  the network refines the classical image, the learned method's floor is the classical
  method's time plus this.
- ``learned``, ``classical``: end to end, as ``hbis reconstruct --method M`` does it (default
  registration "auto"): read the stack, :func:`hbis_torch.reconstruct.reconstruct`, write the
  TIFF. Timed inside the process from the first read to the written file ("e2e"); the process's
  own start (interpreter and imports) is reported apart ("start-up"), and its CPU seconds (user
  + system, all threads) beside the wall clock, which other jobs on shared cores disturb less.
- Peak RSS: ``resource.getrusage(RUSAGE_SELF).ru_maxrss`` of each process at its end.
- Linear cost: e2e(full) / e2e(256^2) over the area ratio (goal <= 1.2); the e2e time is already
  net of the process's start-up.
- PSNR of each end-to-end output against the simulator's ground truth (peak 1): the full-frame
  rows of the speed/error (Pareto) table.

Writes ``benchmarks/results/bench_fullframe.json`` and ``.md`` and the plot
``docs/pareto_fullframe.png``.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SIZES = ("256", "full")
METHODS = ("network", "learned", "classical")
GOALS = {"learned_over_network": 1.3, "classical_over_learned": {4: 2.0, 7: 3.0}, "peak_rss_gb": 2.0,
         "linear": 1.2}

# One measurement, run as ``python -c CHILD MODE STACK OUT``; prints one JSON line.
CHILD = r"""
import json, resource, sys, time
t_start = time.perf_counter()
mode, stack_path, out_path = sys.argv[1:4]
import numpy as np
from hbis_torch.stack_io import read_stack
from hbis_torch.reconstruct.registry import reconstruct
t_imports = time.perf_counter()
result = {}
if mode == "network":
    from hbis_torch.reconstruct.learned import LearnedSR, default_ensemble, network_inputs
    from hbis_torch.reconstruct.learned.method import classical_and_noise
    stack = read_stack(stack_path)
    image, noise_params = classical_and_noise(stack, "optics")
    base, noise = network_inputs(image, stack.h, noise_params)
    h = stack.h
    del image, stack
    runner = LearnedSR(h=h)  # opened after the classical step, as the learned method does
    t0, c0 = time.perf_counter(), time.process_time()
    runner.run_network(base, noise, default_ensemble(h))  # as often as the learned method runs it
    result.update(seconds=time.perf_counter() - t0, cpu_seconds=time.process_time() - c0)
else:
    import tifffile
    t0, c0 = time.perf_counter(), time.process_time()
    stack = read_stack(stack_path)
    image = reconstruct(stack, method=mode, registration="auto")
    tifffile.imwrite(out_path, image, photometric="minisblack")
    result.update(seconds=time.perf_counter() - t0, cpu_seconds=time.process_time() - c0)
usage = resource.getrusage(resource.RUSAGE_SELF)
result.update(startup_seconds=t_imports - t_start, peak_rss_gb=usage.ru_maxrss / 1e6)
print(json.dumps(result))
"""


def make_stacks(work: Path, hs) -> dict:
    """{(h, size): (stack path, truth path)}, simulated through the CLI where missing."""
    work.mkdir(parents=True, exist_ok=True)
    paths = {}
    for h in hs:
        for size in SIZES:
            stack, truth = work / f"camera_h{h}_{size}.tif", work / f"camera_h{h}_{size}_truth.tif"
            if not (stack.exists() and truth.exists()):
                roi = ["--roi", "full"] if size == "full" else []
                subprocess.run([sys.executable, "-m", "hbis_torch", "simulate", "--scene", "camera",
                                "--h", str(h), *roi, "--out", str(stack), "--truth", str(truth), "--overwrite"],
                               check=True, cwd=REPO, env=child_env())
            paths[h, size] = (stack, truth)
    return paths


def child_env() -> dict:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(REPO) + os.pathsep + env.get("PYTHONPATH", "")
    return env


def measure(mode: str, stack: Path, out: Path) -> dict:
    """One measurement in a fresh process: its JSON, plus the process's whole wall time."""
    t0 = time.perf_counter()
    done = subprocess.run([sys.executable, "-c", CHILD, mode, str(stack), str(out)], check=False,
                          cwd=REPO, env=child_env(), capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if done.returncode != 0:
        raise RuntimeError(f"{mode} {stack.name} failed:\n{done.stderr}")
    result = json.loads(done.stdout.strip().splitlines()[-1])
    result["process_seconds"] = wall
    return result


def psnr(path: Path, truth_path: Path) -> float:
    import numpy as np
    import tifffile

    a = tifffile.imread(path).astype(np.float64)
    t = tifffile.imread(truth_path).astype(np.float64)
    return float(10 * np.log10(1.0 / np.mean((a - t) ** 2)))


def run(hs, repeats: int, work: Path) -> dict:
    paths = make_stacks(work, hs)
    runs = {}
    for round_ in range(repeats):
        for h in hs:
            for size in SIZES:
                for mode in METHODS:
                    stack, _ = paths[h, size]
                    out = work / f"out_{mode}_h{h}_{size}.tif"
                    r = measure(mode, stack, out)
                    runs.setdefault(f"{mode} h{h} {size}", []).append(r)
                    print(f"round {round_ + 1}: {mode:9s} h={h} {size:4s} {r['seconds']:7.2f} s "
                          f"(cpu {r['cpu_seconds']:6.1f} s, rss {r['peak_rss_gb']:.2f} GB)", flush=True)
    summary = {}
    for key, rs in runs.items():
        mode, h, size = key.split()
        med = {name: statistics.median(r[name] for r in rs) for name in rs[0]}
        med["max_peak_rss_gb"] = max(r["peak_rss_gb"] for r in rs)
        if mode != "network":
            med["psnr"] = psnr(work / f"out_{mode}_{h}_{size}.tif", paths[int(h[1:]), size][1])
        summary[key] = med
    return {"runs": runs, "summary": summary}


def ratios(summary: dict, h: int) -> dict:
    def s(mode, size="full", what="seconds"):
        return summary[f"{mode} h{h} {size}"][what]

    area = (1280 * 960) / (256 * 256)
    return {
        "learned_over_network": s("learned") / s("network"),
        "classical_over_learned": s("classical") / s("learned"),
        "learned_linear": s("learned") / s("learned", "256") / area,
        "classical_linear": s("classical") / s("classical", "256") / area,
        "learned_over_network_cpu": s("learned", what="cpu_seconds") / s("network", what="cpu_seconds"),
        "classical_over_learned_cpu": s("classical", what="cpu_seconds") / s("learned", what="cpu_seconds"),
        "area_ratio": area,
    }


def markdown(result: dict, hs, load: tuple) -> str:
    summary = result["summary"]
    lines = [(f"Load average {load[0]:.1f} / {load[1]:.1f} at the start and end (2 cores); medians of "
              f"{result['settings']['repeats']} rounds, each measurement in its own process."), "",
             "| h | ROI | method | e2e s | CPU s | start-up s | peak RSS GB | PSNR dB |",
             "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    for h in hs:
        for size in SIZES:
            for mode in METHODS:
                m = summary[f"{mode} h{h} {size}"]
                roi = "960x1280" if size == "full" else "256^2"
                name = "network alone" if mode == "network" else f"{mode}, end to end"
                psnr_cell = f"{m['psnr']:.2f}" if "psnr" in m else "-"
                lines.append(f"| {h} | {roi} | {name} | {m['seconds']:.2f} | {m['cpu_seconds']:.1f} | "
                             f"{m['startup_seconds']:.2f} | {m['max_peak_rss_gb']:.2f} | {psnr_cell} |")
    lines += ["", ("| h | learned e2e / network (goal <= 1.3) | classical / learned e2e (goal) | "
                   "full / (area x 256^2): learned, classical (goal <= 1.2) | peak RSS, full frame: "
                   "learned, classical (goal <= 2 GB) |"), "| --- | --- | --- | --- | --- |"]
    for h in hs:
        r = result["ratios"][str(h)]
        goal = GOALS["classical_over_learned"].get(h, "-")
        rss = [summary[f"{m} h{h} full"]["max_peak_rss_gb"] for m in ("learned", "classical")]
        lines.append(f"| {h} | {r['learned_over_network']:.2f} (CPU {r['learned_over_network_cpu']:.2f}) | "
                     f"{r['classical_over_learned']:.2f} (CPU {r['classical_over_learned_cpu']:.2f}; goal "
                     f"<= {goal}) | {r['learned_linear']:.2f}, {r['classical_linear']:.2f} | "
                     f"{rss[0]:.2f}, {rss[1]:.2f} |")
    return "\n".join(lines) + "\n"


def plot(result: dict, hs, path: Path) -> None:
    from matplotlib.figure import Figure

    fig = Figure(figsize=(6, 4))
    ax = fig.subplots()
    for mode, marker in (("learned", "o"), ("classical", "s")):
        for h in hs:
            m = result["summary"][f"{mode} h{h} full"]
            ax.scatter(m["seconds"], m["psnr"], marker=marker, label=f"{mode}, h = {h}")
    ax.set_xscale("log")
    ax.set_xlabel("end-to-end seconds, full 960 x 1280 frame (2 cores)")
    ax.set_ylabel("PSNR (dB), camera scene")
    ax.set_title("Full frame: speed against error")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--hs", type=int, nargs="+", default=[4, 7])
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--work", type=Path, default=Path("/tmp/hbis_bench_fullframe"),
                   help="folder for the simulated stacks and the outputs")
    p.add_argument("--json", type=Path, default=REPO / "benchmarks/results/bench_fullframe.json")
    p.add_argument("--plot", type=Path, default=REPO / "docs/pareto_fullframe.png")
    args = p.parse_args(argv)
    load0 = os.getloadavg()
    result = run(args.hs, args.repeats, args.work)
    load1 = os.getloadavg()
    result["settings"] = {"hs": args.hs, "repeats": args.repeats, "load_start": load0, "load_end": load1,
                          "cpus": os.cpu_count()}
    result["ratios"] = {str(h): ratios(result["summary"], h) for h in args.hs}
    text = markdown(result, args.hs, (load0[0], load1[0]))
    print(text)
    from hbis_torch.provenance import write_results

    write_results(args.json, result, argv=argv)
    write_results(args.json.with_suffix(".md"), text, argv=argv)
    plot(result, args.hs, args.plot)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
