"""Scale-out on Dask against the in-process batch, side by side, and a projection past this machine.

Measured here (docs/scale-out.md):

* the same 50 small stacks (half HBIS scans, half bursts) reconstructed (classical) by
  ``hbis reconstruct --out-dir`` in one process and by ``--scheduler local:N``; 25 bursts assembled
  by ``hbis assemble --burst --out-dir`` in one process and on ``local:N`` (in one process, inputs
  side by side on threads, one torch thread each; on Dask, one per worker); each command in its own
  process with ``OMP_NUM_THREADS=1`` (as Dask's nanny starts its workers), the two ways
  alternated in each round (the machine is shared: a ratio is only fair between runs made side
  by side); the tasks' time is the summary line's ("in X s": after start-up
  and, on Dask, after the cluster is up), the command's time is the process's wall time;
  the outputs of the two ways are compared byte for byte;
* the engine's own cost per task: empty tasks (each writes and publishes a 1-byte file) through
  :func:`hbis_torch.cluster.engine.run_tasks` in this process and on a LocalCluster, one at a
  time (the latency a task pays) and all at once (what the scheduler sustains).

Projected on paper (nothing run): 10,000 full-frame stacks (h = 7) on 100 nodes of 2 cores, from
the full-frame times of benchmarks/results/bench_fullframe.json (measured on this machine), the
overhead measured here, and assumed file-system bandwidths (stated in the results).

    python benchmarks/bench_scale_out.py --json benchmarks/results/bench_scale_out.json

About 2.5 minutes on 2 idle cores; the last line gives the ratios, the overhead and the load.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def provenance(argv) -> dict:
    """Command, commit, dirty, date and machine of this run (:mod:`hbis_torch.provenance`), with the
    load average at the start and Dask's version."""
    import distributed

    from hbis_torch.provenance import provenance as shared

    prov = shared(list(argv) if argv is not None else None)
    prov["machine"]["load_average"] = list(os.getloadavg())
    prov["versions"]["distributed"] = distributed.__version__
    return prov


def make_inputs(folder: Path, count: int) -> dict:
    """``count`` small stacks: count/2 HBIS scans (h = 4, 32 x 32 px, 16 frames) and count/2
    bursts (8 frames of 40 x 40 px, scale 2) as multi-page TIFFs and as the burst stacks that
    ``hbis assemble --burst`` makes of them; made side by side on threads (each input has its
    own seed: the same files in any order)."""
    from concurrent.futures import ThreadPoolExecutor

    import numpy as np
    import tifffile
    import torch
    from skimage import data, transform

    from hbis_torch.capture.burst import assemble_burst
    from hbis_torch.config import FoveaSystem
    from hbis_torch.scan import plan_scan
    from hbis_torch.simulate import SceneSpec, load_scene, simulate_stack
    from hbis_torch.simulate.burst import random_motions, simulate_burst
    from hbis_torch.stack_io import write_stack

    system = FoveaSystem()
    plan = plan_scan(system, 4)
    spec = SceneSpec.around_roi(32, 32, system.object_pixel_mm)
    camera = data.camera().astype(float) / 255
    for sub in ("stacks", "bursts"):
        (folder / sub).mkdir(parents=True, exist_ok=True)

    def scan(k):
        stack, _ = simulate_stack(load_scene("words", spec, seed=k), system, plan, roi=(600, 400, 32, 32), seed=k)
        write_stack(folder / "stacks" / f"scan{k:03d}.tif", stack)
        return folder / "stacks" / f"scan{k:03d}.tif"

    def burst(k):
        y, x = 40 * (k % 10), 40 * (k // 10)
        truth = transform.resize(camera[y:y + 160, x:x + 160], (80, 80), anti_aliasing=True)
        frames = simulate_burst(truth, 2, random_motions(8, (40, 40), np.random.default_rng(k), 1.5, 1.0),
                                noise=0.005, seed=k).frames
        tifffile.imwrite(folder / "bursts" / f"clip{k:03d}.tif", frames, photometric="minisblack")
        write_stack(folder / "stacks" / f"burst{k:03d}.tif", assemble_burst(frames, 2)[0])
        return folder / "bursts" / f"clip{k:03d}.tif", folder / "stacks" / f"burst{k:03d}.tif"

    before = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        with ThreadPoolExecutor(len(os.sched_getaffinity(0))) as pool:
            scans = list(pool.map(scan, range(count // 2)))
            made = list(pool.map(burst, range(count - count // 2)))
    finally:
        torch.set_num_threads(before)
    return {"stacks": scans + [b for _, b in made], "bursts": [c for c, _ in made]}


def run_command(argv: list[str], env: dict) -> dict:
    """Run ``hbis ARGV`` in a fresh process: its wall time, the tasks' time of its summary and the
    CPU time of the command and every process it started (Dask's workers among them: a process's
    children's CPU time is added to its own when it waits for them), which the load of other jobs
    on the machine changes far less than the times."""
    import resource

    def children_cpu():
        usage = resource.getrusage(resource.RUSAGE_CHILDREN)
        return usage.ru_utime + usage.ru_stime

    started, cpu = time.perf_counter(), children_cpu()
    done = subprocess.run([sys.executable, "-m", "hbis_torch", "-q", *argv], capture_output=True, text=True, env=env)
    wall, cpu = time.perf_counter() - started, children_cpu() - cpu
    if done.returncode != 0:
        raise SystemExit(f"hbis {' '.join(argv[:3])} ... failed ({done.returncode}): {done.stderr.strip()[-2000:]}")
    match = re.search(r" in ([0-9.]+) s \(", done.stdout)
    return {"command_s": wall, "tasks_s": float(match.group(1)) if match else None, "command_cpu_s": cpu}


def same_outputs(a: Path, b: Path) -> bool:
    names = sorted(p.name for p in a.iterdir() if p.name != ".lock")
    return names == sorted(p.name for p in b.iterdir() if p.name != ".lock") and all(
        (a / n).read_bytes() == (b / n).read_bytes() for n in names)


def side_by_side(name: str, argv: list[str], out_flag_ok: bool, workers: int, repeats: int, work: Path,
                 count: int, env: dict) -> dict:
    """The in-process and the Dask runs of one workload, alternated ``repeats`` times."""
    runs: dict = {"in_process": [], "dask": []}
    identical = True
    for r in range(repeats):
        order = ("in_process", "dask") if r % 2 == 0 else ("dask", "in_process")
        dirs = {}
        for way in order:
            out = work / f"{name}-{way}-{r}"
            extra = ["--scheduler", f"local:{workers}"] if way == "dask" else []
            runs[way].append(run_command([*argv, "--out-dir", str(out), *extra], env))
            dirs[way] = out
            print(f"{name} round {r} {way}: {runs[way][-1]}", flush=True)
        identical &= same_outputs(dirs["in_process"], dirs["dask"])
        for d in dirs.values():
            shutil.rmtree(d)
    med = {way: {k: statistics.median(x[k] for x in v) for k in ("command_s", "tasks_s", "command_cpu_s")}
           for way, v in runs.items()}
    return {"inputs": count, "runs": runs, "median": med, "identical_outputs": identical,
            "throughput_per_s": {way: count / m["tasks_s"] for way, m in med.items()},
            "dask_over_in_process_tasks": med["in_process"]["tasks_s"] / med["dask"]["tasks_s"],
            "dask_over_in_process_command": med["in_process"]["command_s"] / med["dask"]["command_s"],
            "per_round_ratio_tasks": [a["tasks_s"] / b["tasks_s"] for a, b in zip(runs["in_process"], runs["dask"])],
            # CPU time over wall time: the cores each way got. On a machine whose other jobs run in
            # sessions of their own, Linux's scheduler (autogroup) shares the CPU between sessions,
            # not processes: this whole script then gets its session's share, and 2 workers get no
            # more cores than 1 thread, so Dask can only show its overhead there.
            "cores_used": {way: m["command_cpu_s"] / m["command_s"] for way, m in med.items()}}


class _Touch:
    """An empty job: write one byte (the file system's part of a task, nothing else)."""

    def __call__(self, source, staging):
        Path(staging).write_bytes(b"x")
        return []


def overhead(work: Path, workers: int, tasks: int) -> dict:
    """The engine's own cost per task, in this process and on a LocalCluster of ``workers``."""
    import distributed

    from hbis_torch.cluster.engine import connect, parse_scheduler, run_tasks, worker_plugin

    def batch(client, tag):
        out = work / f"touch-{tag}"
        outs = [out / f"t{i:05d}.bin" for i in range(tasks)]
        started = time.perf_counter()
        summary = run_tasks(_Touch(), [f"s{i}" for i in range(tasks)], outs, client=client, out_dir=out)
        wall = time.perf_counter() - started
        assert summary.code == 0 and all(o.written for o in summary.outcomes)
        shutil.rmtree(out)
        return wall

    def one_at_a_time(client, n):
        from hbis_torch.cluster.engine import run_task

        out = work / "touch-single"
        out.mkdir(exist_ok=True)
        times = []
        for i in range(n):
            started = time.perf_counter()
            if client is None:
                run_task(_Touch(), "s", str(out / f"t{i}.bin"))
            else:
                client.submit(run_task, _Touch(), "s", str(out / f"t{i}.bin"), pure=False).result()
            times.append(time.perf_counter() - started)
        shutil.rmtree(out)
        return statistics.median(times)

    here_batch = batch(None, "here")
    here_one = one_at_a_time(None, 50)
    started = time.perf_counter()
    with connect(parse_scheduler(f"local:{workers}")) as client:
        client.register_plugin(worker_plugin(1))
        cluster_start = time.perf_counter() - started
        client.submit(os.getpid, pure=False).result()  # warm
        dask_batch = batch(client, "dask")
        dask_one = one_at_a_time(client, 50)
    return {"tasks": tasks, "workers": workers, "cluster_start_s": cluster_start,
            "in_process": {"batch_s": here_batch, "per_task_ms": 1e3 * here_batch / tasks,
                           "one_at_a_time_ms": 1e3 * here_one},
            "dask": {"batch_s": dask_batch, "per_task_ms": 1e3 * dask_batch / tasks,
                     "tasks_per_s": tasks / dask_batch, "one_at_a_time_ms": 1e3 * dask_one},
            "overhead_per_task_ms": 1e3 * (dask_one - here_one),
            "distributed": distributed.__version__}


def model_open_s() -> float:
    """Seconds to open the shipped h = 7 model's session (what a worker pays once)."""
    from hbis_torch.reconstruct.learned import LearnedSR, default_model_path

    started = time.perf_counter()
    LearnedSR(model=default_model_path(7), threads=1)
    return time.perf_counter() - started


def projection(measured: dict, stacks: int = 10_000, nodes: int = 100, cores: int = 2,
               fs_gb_s=(1.0, 10.0)) -> dict:
    """10,000 full-frame h = 7 stacks on 100 nodes of 2 cores: compute, scheduler, file system."""
    full = json.loads((ROOT / "benchmarks/results/bench_fullframe.json").read_text())["runs"]
    h, H, W = 7, 960, 1280
    in_mb = h * h * H * W * 2 / 1e6  # uint16 frames (12-bit sensor)
    out_mb = (h * H) * (h * W) * 4 / 1e6  # float32 image
    over = measured["overhead"]
    rows = {}
    for method in ("classical", "learned"):
        runs = full[f"{method} h7 full"]
        cpu_s = statistics.median(r["cpu_seconds"] for r in runs)  # core-seconds for one stack
        wall_2 = statistics.median(r["seconds"] for r in runs)  # one stack on 2 threads
        rss = max(r["peak_rss_gb"] for r in runs)
        per_core_s = cpu_s  # one worker process per core, one thread each: a stack takes its CPU time
        compute_s = stacks * per_core_s / (nodes * cores)
        demand_gb_s = nodes * cores * (in_mb + out_mb) / 1e3 / per_core_s
        fs = {}
        for bw in fs_gb_s:
            io_s = stacks * (in_mb + out_mb) / 1e3 / bw
            fs[f"{bw:g}_gb_s"] = {"io_bound_s": io_s, "expected_s": max(compute_s, io_s),
                                  "nodes_before_io_bound": bw * per_core_s / (cores * (in_mb + out_mb) / 1e3)}
        rows[method] = {"cpu_s_per_stack": cpu_s, "wall_s_per_stack_2_threads": wall_2, "peak_rss_gb": rss,
                        "compute_bound_s": compute_s, "io_demand_gb_s": demand_gb_s, "file_system": fs,
                        # the scheduler must hand out this many tasks a second, against what it
                        # sustained here for empty tasks on 2 workers
                        "tasks_per_s_needed": stacks / compute_s,
                        # each task's own latency (one at a time, empty task) against its compute
                        "overhead_share": over["overhead_per_task_ms"] / 1e3 / per_core_s,
                        "model_open_s_per_worker": measured["model_open_s"] if method == "learned" else 0.0}
    return {"stacks": stacks, "nodes": nodes, "cores_per_node": cores, "h": h, "frame": [H, W],
            "input_mb_per_stack": in_mb, "output_mb_per_stack": out_mb,
            "total_tb": stacks * (in_mb + out_mb) / 1e6, "file_system_bandwidths_gb_s_assumed": list(fs_gb_s),
            "full_frame_source": "benchmarks/results/bench_fullframe.json (runs 'classical h7 full', 'learned h7 full')",
            "methods": rows}


def main(argv=None) -> dict:
    argv = sys.argv[1:] if argv is None else argv
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--stacks", type=int, default=50, help="stacks reconstructed (half scans, half bursts)")
    p.add_argument("--workers", type=int, default=2, help="LocalCluster worker processes (--scheduler local:N)")
    p.add_argument("--repeats", type=int, default=2, help="rounds, the two ways alternated in each")
    p.add_argument("--tasks", type=int, default=400, help="empty tasks for the per-task overhead")
    p.add_argument("--json", type=Path, help="write the results here")
    p.add_argument("--work", type=Path, help="keep the inputs in this folder and reuse them (default: a temporary one)")
    args = p.parse_args(argv)
    started = time.perf_counter()
    # Both ways with OpenMP and BLAS pools of one thread, as Dask's nanny starts each worker: the
    # same threads on both sides (each task also runs on one torch thread on both).
    env = {**os.environ, "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""), "HBIS_PROGRESS": "0",
           "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    result = {"provenance": provenance(argv)}
    with tempfile.TemporaryDirectory(prefix="bench-scale-out-") as tmp:
        work = args.work or Path(tmp)
        t = time.perf_counter()
        listing = work / f"inputs-{args.stacks}.json"
        if listing.exists():
            inputs = {k: [Path(p) for p in v] for k, v in json.loads(listing.read_text()).items()}
        else:
            work.mkdir(parents=True, exist_ok=True)
            inputs = make_inputs(work, args.stacks)
            listing.write_text(json.dumps({k: [str(p) for p in v] for k, v in inputs.items()}))
        print(f"inputs made in {time.perf_counter() - t:.0f} s", flush=True)
        result["reconstruct"] = side_by_side(
            "reconstruct", ["reconstruct", *map(str, inputs["stacks"]), "--method", "classical"], True, args.workers, args.repeats, work, len(inputs["stacks"]), env)
        result["assemble_burst"] = side_by_side(
            "assemble", ["assemble", "--burst", "--scale", "2", *map(str, inputs["bursts"])], True, args.workers,
            args.repeats, work, len(inputs["bursts"]), env)
        result["overhead"] = overhead(work, args.workers, args.tasks)
        result["model_open_s"] = model_open_s()
    result["projection"] = projection(result)
    result["provenance"]["machine"]["load_average_end"] = list(os.getloadavg())
    if args.json:
        from hbis_torch.provenance import write_results

        write_results(args.json, {k: v for k, v in result.items() if k != "provenance"}, prov=result["provenance"])
    print(json.dumps({k: result[k] for k in ("overhead", "model_open_s")}, indent=1))
    for k in ("reconstruct", "assemble_burst"):
        print(k, {x: result[k][x] for x in ("median", "identical_outputs", "dask_over_in_process_tasks",
                                             "dask_over_in_process_command")})
    load = result["provenance"]["machine"]
    print(f"--scheduler local:{args.workers} over in-process --out-dir, tasks' throughput (goal >= 0.9x): "
          f"reconstruct {result['reconstruct']['dask_over_in_process_tasks']:.2f}x, "
          f"assemble --burst {result['assemble_burst']['dask_over_in_process_tasks']:.2f}x; "
          f"outputs identical: {result['reconstruct']['identical_outputs'] and result['assemble_burst']['identical_outputs']}; "
          f"per-task overhead {result['overhead']['overhead_per_task_ms']:.1f} ms (goal <= 50 ms); "
          f"load average {load['load_average'][0]:.1f} at the start, {load['load_average_end'][0]:.1f} at the end "
          f"on {os.cpu_count()} CPUs; cores the commands got (CPU / wall), in-process and Dask: "
          + ", ".join(f"{k} {result[k]['cores_used']['in_process']:.2f} and {result[k]['cores_used']['dask']:.2f}"
                      for k in ("reconstruct", "assemble_burst"))
          + f"; {time.perf_counter() - started:.0f} s")
    return result


if __name__ == "__main__":
    main()
