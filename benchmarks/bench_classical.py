"""Classical SR: hbis_torch.reconstruct.classical.classical_sr against scipy.interpolate.griddata
(linear) on the same samples, and against single-frame bicubic upsampling.

Stacks are simulated through the Risley model (hbis_torch.simulate, ~40 dB SNR: shot noise, full
well 20000 e-, 12 bits). Every method gets the same samples at the same positions (the tracer's,
from the stack: ``optical_sample_positions``) and is scored against the simulator's ground truth
(the ideal pitch-p/h sensor), away from a border of 2h HR pixels. Times are medians of the CPU
time of this process over ``--repeats`` runs on one thread, which is steadier
than the wall clock on shared cores; the positions (common to all methods) are not timed.

    python3 benchmarks/bench_classical.py [--quick] [--json benchmarks/results/bench_classical.json]
"""

from __future__ import annotations

import benchutil  # first: pins numpy/scipy to one thread before they load

import argparse
from pathlib import Path

import numpy as np
import torch
from scipy.interpolate import griddata

from hbis_torch.config import FoveaSystem
from hbis_torch.metrics import psnr, ssim
from hbis_torch.scan import plan_scan
from hbis_torch.simulate import SensorModel, simulate_stack
from hbis_torch.reconstruct.classical import classical_sr, optical_sample_positions, optics_cutoff

SENSOR_40DB = SensorModel(full_well_e=20000.0, read_noise_e=2.0, bit_depth=12)



def griddata_sr(frames: np.ndarray, positions: np.ndarray, h: int) -> np.ndarray:
    """Linear interpolation of the scattered samples onto the HR grid (Delaunay, scipy)."""
    X = (positions[..., 0] + 0.5) * h - 0.5
    Y = (positions[..., 1] + 0.5) * h - 0.5
    rows, cols = h * frames.shape[1], h * frames.shape[2]
    gy, gx = np.mgrid[0:rows, 0:cols]
    out = griddata(np.stack((X.ravel(), Y.ravel()), -1), frames.ravel(), (gx, gy), method="linear")
    # Outside the samples' hull: nearest sample (griddata gives NaN there).
    holes = np.isnan(out)
    if holes.any():
        out[holes] = griddata(np.stack((X.ravel(), Y.ravel()), -1), frames.ravel(), (gx[holes], gy[holes]),
                              method="nearest")
    return np.clip(out, 0, 1).astype(np.float32)


def bicubic(frame: torch.Tensor, h: int) -> np.ndarray:
    up = torch.nn.functional.interpolate(frame[None, None], scale_factor=h, mode="bicubic", align_corners=False)
    return up[0, 0].clamp(0, 1).numpy()


def score(truth: np.ndarray, image: np.ndarray, h: int) -> tuple[float, float]:
    c = slice(2 * h, -2 * h)
    t, x = truth[c, c].astype(np.float64), image[c, c].astype(np.float64)
    return psnr(x, t), ssim(x, t)


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenes", default="camera,astronaut,texture,words,bars,siemens-star")
    parser.add_argument("--h", type=int, default=4)
    parser.add_argument("--size", type=int, default=128, help="ROI width and height, px")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--quick", action="store_true", help="two scenes, 64 px, one repeat")
    parser.add_argument("--json", type=Path, help="also write the results here")
    args = parser.parse_args(argv)
    if args.quick:
        args.scenes, args.size, args.repeats = "camera,bars", 64, 1
    torch.set_num_threads(1)
    system = FoveaSystem()
    plan = plan_scan(system, args.h)
    roi = (640 - args.size // 2, 480 - args.size // 2, args.size, args.size)
    cutoff = optics_cutoff(system)
    methods = ("ours", "ours_no_deblur", "griddata_linear", "bicubic_1_frame")
    print(f"h={args.h}, ROI {args.size}x{args.size} px (output {args.h * args.size}^2), ~40 dB SNR, "
          "1 thread; PSNR dB / SSIM / CPU s")
    print(f"{'scene':13s}" + "".join(f"{m:>26s}" for m in methods))
    rows = []
    for name in args.scenes.split(","):
        stack, truth = simulate_stack(name, system, plan, roi=roi, sensor=SENSOR_40DB, seed=1)
        frames = stack.to_float()
        positions = optical_sample_positions(stack)
        frames_np, positions_np = frames.numpy().astype(np.float64), positions.numpy()
        classical_sr(frames, positions, args.h, cutoff=cutoff)  # warm-up
        runs = {
            "ours": lambda: classical_sr(frames, positions, args.h, cutoff=cutoff).numpy(),
            "ours_no_deblur": lambda: classical_sr(frames, positions, args.h, deblur=False).numpy(),
            "griddata_linear": lambda: griddata_sr(frames_np, positions_np, args.h),
            "bicubic_1_frame": lambda: bicubic(frames[stack.reference_index], args.h),
        }
        row = {"scene": name}
        for method, fn in runs.items():
            image, seconds = benchutil.cpu_timed(fn, 1 if method == "griddata_linear" else args.repeats)
            p, s = score(truth, image, args.h)
            row[method] = {"psnr_db": p, "ssim": s, "cpu_s": seconds}
        rows.append(row)
        print(f"{name:13s}" + "".join(
            f"{row[m]['psnr_db']:9.2f} {row[m]['ssim']:6.3f} {row[m]['cpu_s']:8.3f}s" for m in methods))
    summary = {m: {k: float(np.mean([r[m][k] for r in rows])) for k in ("psnr_db", "ssim", "cpu_s")} for m in methods}
    summary["speedup_vs_griddata"] = float(np.median([r["griddata_linear"]["cpu_s"] / r["ours"]["cpu_s"] for r in rows]))
    summary["speedup_vs_griddata_no_deblur"] = float(np.median(
        [r["griddata_linear"]["cpu_s"] / r["ours_no_deblur"]["cpu_s"] for r in rows]))
    summary["psnr_gain_vs_griddata_db"] = summary["ours"]["psnr_db"] - summary["griddata_linear"]["psnr_db"]
    summary["psnr_gain_vs_bicubic_db"] = summary["ours"]["psnr_db"] - summary["bicubic_1_frame"]["psnr_db"]
    print("mean        " + "".join(
        f"{summary[m]['psnr_db']:9.2f} {summary[m]['ssim']:6.3f} {summary[m]['cpu_s']:8.3f}s" for m in methods))
    print(f"ours vs griddata: {summary['speedup_vs_griddata']:.0f}x faster (median), "
          f"{summary['psnr_gain_vs_griddata_db']:+.2f} dB; vs bicubic: {summary['psnr_gain_vs_bicubic_db']:+.2f} dB; "
          f"interpolation alone (no deblurring) vs griddata: {summary['speedup_vs_griddata_no_deblur']:.0f}x faster, "
          f"{summary['ours_no_deblur']['psnr_db'] - summary['griddata_linear']['psnr_db']:+.2f} dB")
    return benchutil.finish(args, rows, summary, argv)


if __name__ == "__main__":
    main()
