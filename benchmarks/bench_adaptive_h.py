"""Scene-adaptive h: hbis_torch.reconstruct.classical.adaptive_h.recommend_h against every fixed h.

For each scene and sensor, a stack is simulated and reconstructed (classical, optics positions)
at every h = 1..h_max; each reconstruction is resampled (bicubic) onto the h_max grid and scored
against the h_max ground truth (the same scene object for every h). The recommendation comes
from a quick pre-scan, the h = 2 stack (4 frames and their optical positions), and, for
comparison, from one frame alone (the h = 1 frame). Reported: the best fixed h, the recommended
h, the PSNR given up and the frames used (h^2; the pre-scan's 4 frames are not counted).

``--budget total`` (default) holds the scan's total exposure fixed: at h every frame gets 1/h^2
of the first frame's exposure (the sensor's full well is divided by h^2, read noise unchanged),
so more frames buy resolution, not noise averaging. ``--budget frame`` gives every frame the full
exposure; then more frames always average noise down and the best h is h_max.

    python3 benchmarks/bench_adaptive_h.py [--quick] [--json benchmarks/results/bench_adaptive_h.json]
"""

from __future__ import annotations

import benchutil  # first: pins numpy/scipy to one thread before they load

import argparse
import dataclasses
from pathlib import Path

import numpy as np
import torch
from skimage.metrics import peak_signal_noise_ratio

from hbis_torch.config import FoveaSystem
from hbis_torch.design import design
from hbis_torch.scan import plan_scan
from hbis_torch.simulate import SensorModel, simulate_stack
from hbis_torch.simulate.stacks import scene_for_roi
from hbis_torch.reconstruct.classical.adaptive_h import recommend_h
from hbis_torch.reconstruct import optical_sample_positions, reconstruct

SENSORS = {
    "40dB": SensorModel(full_well_e=20000.0, read_noise_e=2.0, bit_depth=12),
    "25dB": SensorModel(full_well_e=600.0, read_noise_e=5.0, bit_depth=12),
}


def on_grid(image: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Bicubic resampling onto another h-times grid of the same ROI (pixel-centre aligned)."""
    if image.shape == shape:
        return image
    x = torch.from_numpy(image)[None, None]
    return torch.nn.functional.interpolate(x, size=shape, mode="bicubic", align_corners=False)[0, 0].clamp(0, 1).numpy()


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenes", default="gradient,camera,astronaut,texture,words,bars,siemens-star")
    parser.add_argument("--sensors", default="40dB,25dB")
    parser.add_argument("--size", type=int, default=64, help="ROI width and height, px")
    parser.add_argument("--tolerance-db", type=float, default=0.07)
    parser.add_argument("--budget", choices=("total", "frame"), default="total")
    parser.add_argument("--quick", action="store_true", help="three scenes, 40 dB only, 48 px")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args(argv)
    if args.quick:
        args.scenes, args.sensors, args.size = "gradient,camera,bars", "40dB", 48
    torch.set_num_threads(1)
    system = FoveaSystem()
    h_max = design(system).h_max
    roi = (640 - args.size // 2, 480 - args.size // 2, args.size, args.size)
    rows = []
    print(f"h_max = {h_max}; ROI {args.size}x{args.size} px; exposure budget: {args.budget}; "
          f"PSNR (dB) on the h_max grid")
    print(f"{'scene':13s} {'sensor':6s} " + " ".join(f"{'h=' + str(h):>6s}" for h in range(1, h_max + 1))
          + "   best | pre-scan: rec loss(dB) | 1 frame: rec loss(dB) | frames (pre-scan rec)/best")
    for sensor_name in args.sensors.split(","):
        sensor = SENSORS[sensor_name]
        for name in args.scenes.split(","):
            scene = scene_for_roi(name, system, roi, h_max, seed=1)
            psnr, truth_max, stacks = {}, None, {}
            for h in range(h_max, 0, -1):
                per_frame = sensor
                if args.budget == "total":
                    per_frame = dataclasses.replace(sensor, full_well_e=sensor.full_well_e / (h * h))
                stack, truth = simulate_stack(scene, system, plan_scan(system, h), roi=roi, sensor=per_frame, seed=1)
                stacks[h] = stack
                if h == h_max:
                    truth_max = truth
                image = on_grid(reconstruct(stack, registration="optics"), truth_max.shape)
                psnr[h] = float(peak_signal_noise_ratio(truth_max.astype(np.float64), image.astype(np.float64),
                                                        data_range=1.0))
            common = dict(h_max=h_max, tolerance_db=args.tolerance_db, fill_factor=sensor.fill_factor,
                          budget=args.budget)
            prescan = recommend_h(stacks[2].to_float(), system, positions=optical_sample_positions(stacks[2]), **common)
            single = recommend_h(stacks[1].to_float()[0], system, **common)
            best = max(psnr, key=psnr.get)
            loss, loss1 = psnr[best] - psnr[prescan.h], psnr[best] - psnr[single.h]
            rows.append({"scene": name, "sensor": sensor_name, "psnr_db": psnr, "best_h": best,
                         "recommended_h": prescan.h, "predicted_psnr_db": prescan.predicted_psnr_db,
                         "loss_db": loss, "single_frame_h": single.h, "single_frame_loss_db": loss1,
                         "frames_recommended": prescan.h ** 2, "frames_best": best ** 2})
            print(f"{name:13s} {sensor_name:6s} " + " ".join(f"{psnr[h]:6.2f}" for h in range(1, h_max + 1))
                  + f"   {best:4d} | {prescan.h:3d} {loss:8.2f} | {single.h:3d} {loss1:8.2f} | "
                  f"{prescan.h ** 2:3d}/{best ** 2}")
    losses = [r["loss_db"] for r in rows]
    summary = {
        "single_frame_within_0p5_db": int(sum(r["single_frame_loss_db"] <= 0.5 for r in rows)),
        "max_loss_db": float(max(losses)),
        "mean_loss_db": float(np.mean(losses)),
        "within_0p5_db": int(sum(x <= 0.5 for x in losses)),
        "cases": len(rows),
        "frames_recommended_total": int(sum(r["frames_recommended"] for r in rows)),
        "frames_best_total": int(sum(r["frames_best"] for r in rows)),
        "frames_h_max_total": len(rows) * h_max ** 2,
    }
    print(f"pre-scan: recommended h within 0.5 dB of the best fixed h in {summary['within_0p5_db']}/{summary['cases']} "
          f"cases (largest loss {summary['max_loss_db']:.2f} dB, mean {summary['mean_loss_db']:.2f} dB); frames: "
          f"{summary['frames_recommended_total']} recommended vs {summary['frames_best_total']} for the best h "
          f"and {summary['frames_h_max_total']} at h_max; one frame alone: within 0.5 dB in "
          f"{summary['single_frame_within_0p5_db']}/{summary['cases']}")
    return benchutil.finish(args, rows, summary, argv)


if __name__ == "__main__":
    main()
