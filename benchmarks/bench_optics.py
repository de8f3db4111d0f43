"""Speed of the Risley tracer, measured side by side in one run.

1. Trace all 960 x 1280 chief rays at one phase pair (float64): a plain vectorised NumPy version
   of the same formulas (faces as (N, 3) arrays) against the torch tracer, eager and fused
   (``fast=True``, torch.compile).
2. Per-pixel landing maps for a whole h = 7 scan (49 phase pairs): the exact trace against the
   spline-interpolated maps, with the measured maximum error.

Run:  python3 benchmarks/bench_optics.py [--out benchmarks/results/bench_optics.txt]
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import numpy as np
import torch

from hbis_torch import FoveaSystem
from hbis_torch.optics import landing_map, landing_map_interpolated, pixel_rays, trace_risley
from hbis_torch.provenance import run_recorded


def best_of(fn, repeats=5):
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def numpy_trace(rays, phi1_deg, phi2_deg, a_deg, n):
    """Reference: the same four refractions with (N, 3) NumPy arrays."""

    def refract(i, normal, eta):
        c = (i * normal).sum(-1, keepdims=True)
        k = 1 - eta**2 * (1 - c**2)
        return eta * i + (np.sqrt(np.clip(k, 0, None)) - eta * c) * normal

    a, p1, p2 = np.radians([a_deg, phi1_deg, phi2_deg])
    n11 = np.array([0.0, 0.0, 1.0])
    n12 = np.array([-np.sin(a) * np.cos(p1), -np.sin(a) * np.sin(p1), np.cos(a)])
    n21 = np.array([np.sin(a) * np.cos(p2), np.sin(a) * np.sin(p2), np.cos(a)])
    r = refract(rays, n11, 1 / n)
    r = refract(r, n12, n)
    r = refract(r, n21, 1 / n)
    return refract(r, n11, n)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=None,
                        help="also write what is printed to this file (.txt/.md, or .json), with its provenance")
    args = parser.parse_args(argv)
    return run_recorded("bench_optics", lambda _: measure() or 0, args, argv)


def measure() -> None:
    """Run the benchmark and print its result."""
    torch.manual_seed(0)
    system = FoveaSystem()
    a, n = system.prisms.wedge_angle_deg, system.prisms.refractive_index
    rays = pixel_rays(system.camera)  # (960, 1280, 3) float64
    rays_np = rays.reshape(-1, 3).numpy().copy()
    print(f"torch {torch.__version__}, threads {torch.get_num_threads()}")

    print("\n1. full-sensor trace, 960 x 1280 rays, one phase pair, float64")
    ref = numpy_trace(rays_np, 5.0, 70.0, a, n)
    trace_risley(rays, 5.0, 70.0, fast=True)  # compile once, outside the timing
    t_np = best_of(lambda: numpy_trace(rays_np, 5.0, 70.0, a, n))
    t_eager = best_of(lambda: trace_risley(rays, 5.0, 70.0))
    t_fast = best_of(lambda: trace_risley(rays, 5.0, 70.0, fast=True))
    err = np.abs(trace_risley(rays, 5.0, 70.0, fast=True).directions.reshape(-1, 3).numpy() - ref).max()
    print(f"   numpy (plain, vectorised)   {t_np * 1e3:8.1f} ms")
    print(f"   torch eager                 {t_eager * 1e3:8.1f} ms   {t_np / t_eager:5.1f}x numpy")
    print(f"   torch fast (compiled)       {t_fast * 1e3:8.1f} ms   {t_np / t_fast:5.1f}x numpy")
    print(f"   max |difference| to numpy   {err:.1e}")

    print("\n2. landing maps of a whole h = 7 scan (49 phase pairs, full sensor)")
    grid = torch.linspace(-0.3, 0.3, 7, dtype=torch.float64)
    p1 = (5.0 + grid[:, None] + 0 * grid[None, :]).reshape(-1)
    p2 = (70.0 + grid[None, :] + 0 * grid[:, None]).reshape(-1)
    t0 = time.perf_counter()
    exact = torch.cat([landing_map(system, p1[i:i + 7], p2[i:i + 7]) for i in range(0, 49, 7)])
    t_exact = time.perf_counter() - t0
    print(f"   exact trace                 {t_exact * 1e3:8.1f} ms")
    for dtype in (torch.float64, torch.float32):
        t_fast = best_of(lambda: landing_map_interpolated(system, p1, p2, dtype=dtype), repeats=3)
        fast = landing_map_interpolated(system, p1, p2, dtype=dtype)
        err_px = float((fast.double() - exact).abs().max()) / system.object_pixel_mm
        name = str(dtype).replace("torch.", "")
        print(f"   interpolated, {name:8s}      {t_fast * 1e3:8.1f} ms   {t_exact / t_fast:5.1f}x exact,"
              f"  max error {err_px:.1e} px")
        del fast
    print(f"   (one object-plane pixel = {system.object_pixel_mm * 1e3:.3f} um; output "
          f"{49 * 960 * 1280 * 2 * 8 / 2**20:.0f} MiB in float64)")
    assert math.isfinite(t_exact)


if __name__ == "__main__":
    raise SystemExit(main())
