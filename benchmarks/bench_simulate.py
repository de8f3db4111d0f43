"""Speed of synthetic-stack generation, and the forward model's speed-versus-error trade-off.

Run from the repository root:

    python3 benchmarks/bench_simulate.py [--items 200] [--out benchmarks/results/bench_simulate.json]

1. Training stacks (64 x 64, h = 4: 16 frames, truth 256 x 256) of the training pipeline
   (hbis_torch.training.data.simulate_example: its standard mix of scenes
   and exposures, random places on the sensor), pool example i of seed ``--seed``: one process
   with one thread (wall and CPU seconds per stack), then a torch DataLoader with two
   single-threaded workers (stacks per second, wall clock), against the goal of 50 stacks/s on
   two cores.
2. The forward model at several oversampling factors on a grating at the sensor's corner:
   time per stack and the largest error against the closed form (hbis_torch.simulate.reference).

The load average is printed with the numbers: on a shared machine wall-clock rates fall with it,
while CPU seconds per stack stay close to what an idle core would take.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time

import torch

from hbis_torch.config import FoveaSystem
from hbis_torch.training.data import example_seed, simulate_example
from hbis_torch.scan import plan_scan
from hbis_torch.simulate import GratingScene, SensorModel, render_scan
from hbis_torch.simulate.forward import grid_factor
from hbis_torch.simulate.reference import grating_frame, grating_truth

GOAL = 50.0
H, SIZE = 4, 64  # the training stacks timed: h and the side of their ROI (LR pixels)


class PoolExamples(torch.utils.data.Dataset):
    """Example i of the training pool of seed ``seed`` (h = H, SIZE x SIZE), simulated on
    demand: a map-style dataset over :func:`simulate_example`, for the DataLoader."""

    def __init__(self, items: int, seed: int):
        self.items, self.seed = items, seed
        self.system = FoveaSystem()
        self.plan = plan_scan(self.system, H)

    def __len__(self) -> int:
        return self.items

    def __getitem__(self, index: int) -> dict:
        if not 0 <= index < self.items:
            raise IndexError(f"index {index} out of range for {self.items} items")
        return simulate_example(self.system, self.plan, SIZE, example_seed(self.seed, index))


def single_process(items: int, seed: int) -> dict:
    torch.set_num_threads(1)
    ds = PoolExamples(items + 10, seed)
    for i in range(5):  # warm caches (plans, transfer tables) and imports
        ds[items + i]
    wall, cpu = time.perf_counter(), time.process_time()
    for i in range(items):
        ds[i]
    wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
    return {"items": items, "wall_s_per_stack": wall / items, "cpu_s_per_stack": cpu / items,
            "stacks_per_s_wall": items / wall, "stacks_per_s_cpu": items / cpu}


def data_loader(items: int, seed: int, workers: int) -> dict:
    """Wall-clock rate, and the CPU seconds all processes spent per stack (workers measured
    through RUSAGE_CHILDREN once they have exited, plus the main process's collation)."""
    import resource

    ds = PoolExamples(items, seed)
    children = resource.getrusage(resource.RUSAGE_CHILDREN)
    main_cpu = time.process_time()
    loader = torch.utils.data.DataLoader(ds, batch_size=8, shuffle=False, num_workers=workers,
                                         persistent_workers=False, prefetch_factor=4)
    start, count = time.perf_counter(), 0
    for batch in loader:
        count += batch["frames"].shape[0]
    wall = time.perf_counter() - start
    del loader
    time.sleep(0.5)  # let the workers exit so that their CPU time is accounted
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime + after.ru_stime - children.ru_utime - children.ru_stime
           + time.process_time() - main_cpu)
    return {"workers": workers, "items": count, "stacks_per_s_wall": count / wall,
            "cpu_s_per_stack_all_processes": cpu / count,
            "stacks_per_s_on_idle_cores": workers * count / cpu}


def accuracy_versus_speed(repeats: int = 3) -> list[dict]:
    system = FoveaSystem()
    h = 4
    plan = plan_scan(system, h)
    roi = (1216, 896, 64, 64)  # bottom-right corner
    pixel_mm = system.object_pixel_mm
    grating = GratingScene(size_mm=(1.0, 1.0), period_mm=0.7 * pixel_mm, angle_deg=30.0, mean=0.5, amplitude=0.45)
    sensor = SensorModel(fill_factor=0.8, noise=False, bit_depth=None)
    rows = []
    u0, v0, w, hh = roi
    vv, uu = torch.meshgrid(torch.arange(hh), torch.arange(w), indexing="ij")
    pixels = torch.stack((uu.flatten() + u0, vv.flatten() + v0), -1).double()
    hv, hu = torch.meshgrid(torch.arange(h * hh), torch.arange(h * w), indexing="ij")
    hr = torch.stack((hu.flatten(), hv.flatten()), -1)
    for oversample in (8, 16):
        for dtype in (torch.float32, torch.float64):
            args = (grating, system, plan.phases_deg, plan.reference_index, h, roi, sensor)
            render_scan(*args, oversample=oversample, dtype=dtype, margin_px=16)
            start = time.perf_counter()
            for _ in range(repeats):
                out = render_scan(*args, oversample=oversample, dtype=dtype, margin_px=16)
            seconds = (time.perf_counter() - start) / repeats
            spacing = pixel_mm / (h * grid_factor(h, oversample))
            frame_err = max(
                float((out.irradiance[k].flatten().double()
                       - grating_frame(out.scene, system, plan.phases_deg[k], pixels, sensor, spacing)).abs().max())
                for k in range(plan.frames)
            )
            truth_err = float((out.truth.flatten().double() - grating_truth(
                out.scene, system, plan.phases_deg[plan.reference_index], hr, roi, h, sensor, spacing)).abs().max())
            rows.append({"oversample": oversample, "grid_points_per_px": h * grid_factor(h, oversample),
                         "dtype": str(dtype).replace("torch.", ""), "seconds": seconds,
                         "max_frame_error": frame_err, "max_truth_error": truth_err})
    return rows


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--items", type=int, default=200, help="stacks per timing (default 200)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", help="also write the results as JSON here")
    args = parser.parse_args(argv)

    load_before = os.getloadavg()
    single = single_process(args.items, args.seed)
    loader2 = data_loader(args.items, args.seed + 1, 2)
    load_after = os.getloadavg()
    torch.set_num_threads(1)
    table = accuracy_versus_speed()

    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} CPUs visible, "
          f"load average {load_before[0]:.1f} before / {load_after[0]:.1f} after")
    print("training crops 64 x 64, h = 4 (16 frames + truth 256 x 256), default scene/noise mix:")
    print(f"  1 process, 1 thread : {single['wall_s_per_stack'] * 1e3:6.1f} ms wall, "
          f"{single['cpu_s_per_stack'] * 1e3:6.1f} ms CPU per stack -> {single['stacks_per_s_wall']:5.1f} stacks/s "
          f"(CPU-bound rate {single['stacks_per_s_cpu']:5.1f}/s per core)")
    print(f"  DataLoader, 2 workers: {loader2['stacks_per_s_wall']:5.1f} stacks/s wall "
          f"= {loader2['stacks_per_s_wall'] / GOAL:.2f} x the goal of {GOAL:.0f}/s on this (shared) machine")
    print(f"    all processes used {loader2['cpu_s_per_stack_all_processes'] * 1e3:.1f} ms CPU per stack "
          f"(workers startup, generation, transfer, collation): on 2 idle cores "
          f"{loader2['stacks_per_s_on_idle_cores']:5.1f} stacks/s = "
          f"{loader2['stacks_per_s_on_idle_cores'] / GOAL:.2f} x the goal")
    print("forward model on a grating (period 0.7 px, 30 deg) at the sensor's corner, 64 x 64, h = 4:")
    print("  oversample  points/px  dtype    ms/stack  max |frame error|  max |truth error|")
    base = next(r["seconds"] for r in table if r["oversample"] == 8 and r["dtype"] == "float32")
    for r in table:
        print(f"  {r['oversample']:10d}  {r['grid_points_per_px']:9d}  {r['dtype']:7s}  {r['seconds'] * 1e3:8.1f}"
              f"  {r['max_frame_error']:17.2e}  {r['max_truth_error']:17.2e}   ({r['seconds'] / base:.2f} x default)")
    if args.out:
        result = {"load_average_before": load_before, "load_average_after": load_after,
                  "single_process": single, "data_loader_2_workers": loader2, "goal_stacks_per_s": GOAL,
                  "forward_model": table}
        from hbis_torch.provenance import write_results

        write_results(args.out, result, argv=argv)
    return 0


if __name__ == "__main__":
    sys.exit(main())
