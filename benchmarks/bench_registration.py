"""Registration: hbis_torch.registration.register_stack against scikit-image's
phase_cross_correlation (upsample_factor=100), side by side on the same stacks.

Stacks are simulated through the Risley model (hbis_torch.simulate) at about 40 dB SNR (shot
noise, full well 20000 e-, 12 bits), with the motors off by ``--phase-error-deg`` (so the plan
alone is wrong and the data must measure the motion). The error of a method is the RMS, over
every pixel of every non-reference frame, of the distance between where it puts the pixel in
the reference frame and where the exact tracer at the true phases puts it. Times are medians of
``--repeats`` runs of the CPU time of this process (steadier than the wall clock on cores shared
with other jobs), both methods on one thread (numpy and scipy included).

Each ROI size is a separate table: our cost is mostly per point compared (at most
``max_points`` of them), plus a few passes over the stack, so the ratio grows with the ROI.

    python3 benchmarks/bench_registration.py [--quick] [--sizes 128 256 512] [--json benchmarks/results/bench_registration.json]
"""

from __future__ import annotations

import benchutil  # first: pins numpy/scipy to one thread before they load

import argparse
import copy
from pathlib import Path

import numpy as np
import torch
from skimage.registration import phase_cross_correlation

from hbis_torch.config import FoveaSystem
from hbis_torch.registration import apply_homography, homographies_from_positions, register_stack
from hbis_torch.scan import plan_scan
from hbis_torch.simulate import SensorModel, simulate_stack
from hbis_torch.reconstruct.classical import optical_sample_positions

SENSOR_40DB = SensorModel(full_well_e=20000.0, read_noise_e=2.0, bit_depth=12)


def pcc_homographies(frames: np.ndarray, ref: int) -> torch.Tensor:
    """Translations from phase_cross_correlation (upsample 100) as homographies (F, 3, 3)."""
    out = torch.eye(3, dtype=torch.float64).repeat(len(frames), 1, 1)
    for k, frame in enumerate(frames):
        shift = phase_cross_correlation(frames[ref], frame, upsample_factor=100)[0]  # (row, col)
        out[k, 0, 2], out[k, 1, 2] = float(shift[1]), float(shift[0])
    return out


def rms_error(homographies: torch.Tensor, true_positions: torch.Tensor, ref: int) -> float:
    F, H, W, _ = true_positions.shape
    vv, uu = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64), indexing="ij")
    grid = torch.stack((uu, vv), -1).reshape(-1, 2)
    got = apply_homography(homographies, grid).reshape(F, H, W, 2)
    err = ((got - true_positions) ** 2).sum(-1).mean((1, 2))
    keep = torch.arange(F) != ref
    return float(err[keep].mean().sqrt())



def measure(system, plan, size: int, args) -> list[dict]:
    """Rows of one ROI size: every scene, both methods, errors and CPU times."""
    roi = (640 - size // 2, 480 - size // 2, size, size)
    rows = []
    print(f"h={args.h}, ROI {size}x{size} px at the sensor centre, motors off by "
          f"{args.phase_error_deg} deg (1 sigma), ~40 dB SNR, 1 thread")
    print(f"{'scene':10s} {'plan only':>10s} {'ours+plan':>10s} {'ours':>10s} {'pcc':>10s}   "
          f"{'t ours+plan':>11s} {'t ours':>8s} {'t pcc':>8s} {'speed-up':>8s}")
    for name in args.scenes.split(","):
        stack, _ = simulate_stack(name, system, plan, roi=roi, sensor=SENSOR_40DB, seed=1,
                                  phase_error_deg=args.phase_error_deg)
        ref = stack.reference_index
        actual = copy.deepcopy(stack)
        actual.meta["phases_deg"] = stack.meta["simulation"]["true_phases_deg"]
        true_pos = optical_sample_positions(actual)
        planned = homographies_from_positions(optical_sample_positions(stack))
        frames = stack.to_float()
        frames_np = frames.numpy().astype(np.float64)
        register_stack(frames, ref, prediction=planned)  # warm-up
        pcc_homographies(frames_np[:2], ref if ref < 2 else 0)
        ours_plan, t_ours_plan = benchutil.cpu_timed(lambda: register_stack(frames, ref, prediction=planned), args.repeats)
        ours, t_ours = benchutil.cpu_timed(lambda: register_stack(frames, ref), args.repeats)
        pcc, t_pcc = benchutil.cpu_timed(lambda: pcc_homographies(frames_np, ref), args.repeats)
        row = {
            "scene": name,
            "size": size,
            "rms_px": {"plan_only": rms_error(planned, true_pos, ref),
                       "ours_with_plan": rms_error(ours_plan.homographies, true_pos, ref),
                       "ours_data_only": rms_error(ours.homographies, true_pos, ref),
                       "pcc_upsample100": rms_error(pcc, true_pos, ref)},
            "time_s": {"ours_with_plan": t_ours_plan, "ours_data_only": t_ours, "pcc_upsample100": t_pcc},
            "model": ours_plan.model,
            "frames_ok": int(ours_plan.ok.sum()),
            "frames": len(frames),
        }
        rows.append(row)
        e, t = row["rms_px"], row["time_s"]
        print(f"{name:10s} {e['plan_only']:10.4f} {e['ours_with_plan']:10.4f} {e['ours_data_only']:10.4f} "
              f"{e['pcc_upsample100']:10.4f}   {t['ours_with_plan']:10.3f}s {t['ours_data_only']:7.3f}s "
              f"{t['pcc_upsample100']:7.3f}s {t['pcc_upsample100'] / t['ours_with_plan']:7.1f}x")
    return rows


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenes", default="camera,texture,words,bars")
    parser.add_argument("--h", type=int, default=4)
    parser.add_argument("--sizes", type=int, nargs="+", default=[128, 256, 512], help="ROI widths (= heights), px")
    parser.add_argument("--phase-error-deg", type=float, default=0.02)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--quick", action="store_true", help="two scenes, 96 px, one repeat")
    parser.add_argument("--json", type=Path, help="also write the results here")
    args = parser.parse_args(argv)
    if args.quick:
        args.scenes, args.sizes, args.repeats = "camera,texture", [96], 1
    torch.set_num_threads(1)
    system = FoveaSystem()
    plan = plan_scan(system, args.h)
    rows = []
    summary = {}
    for size in args.sizes:
        part = measure(system, plan, size, args)
        rows += part
        summary[str(size)] = {
            "rms_px_mean": {k: float(np.mean([r["rms_px"][k] for r in part])) for k in part[0]["rms_px"]},
            "speedup_vs_pcc_with_plan": float(np.median([r["time_s"]["pcc_upsample100"] / r["time_s"]["ours_with_plan"] for r in part])),
            "speedup_vs_pcc_data_only": float(np.median([r["time_s"]["pcc_upsample100"] / r["time_s"]["ours_data_only"] for r in part])),
        }
        s = summary[str(size)]
        print("mean RMS error (px): " + ", ".join(f"{k} {v:.4f}" for k, v in s["rms_px_mean"].items()))
        print(f"median speed-up over phase_cross_correlation at {size}^2: {s['speedup_vs_pcc_with_plan']:.1f}x with "
              f"the plan, {s['speedup_vs_pcc_data_only']:.1f}x from the data alone\n")
    return benchutil.finish(args, rows, summary, argv)


if __name__ == "__main__":
    main()
