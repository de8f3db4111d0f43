"""Colour: luminance + chroma against per-channel reconstruction, and Bayer joint demosaicking
(classical) against demosaicking first, on photographs of skimage.data.

Each scene is simulated channel by channel through the Risley model
(:func:`hbis_torch.simulate.colour.simulate_colour_stack`, 12-bit sensor, shot and read noise),
reconstructed with optical positions, and scored by PSNR over the three channels (and the
luminance) against the RGB ground truth, away from a border of 2h HR pixels. CPU seconds of this
process per reconstruction are given beside (one thread).

    python3 benchmarks/bench_colour.py [--h 4] [--size 64] [--json benchmarks/results/bench_colour.json]
"""

from __future__ import annotations

import argparse
import time

import benchutil  # first: pins numpy/scipy to one thread before they load
import numpy as np
import skimage.data
import torch

from hbis_torch.config import FoveaSystem
from hbis_torch.metrics import psnr
from hbis_torch.reconstruct import reconstruct
from hbis_torch.reconstruct.colour import LUMA, demosaic, mosaic
from hbis_torch.simulate import SensorModel
from hbis_torch.simulate.colour import simulate_colour_stack
from hbis_torch.stack_io import Stack

SCENES = {"astronaut": lambda: skimage.data.astronaut()[30:330, 120:420],
          "coffee": lambda: skimage.data.coffee()[60:360, 180:480],
          "chelsea": lambda: skimage.data.chelsea()[20:300, 100:380]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--h", type=int, default=4)
    parser.add_argument("--size", type=int, default=64)
    parser.add_argument("--json")
    args = parser.parse_args()
    torch.set_num_threads(1)
    system = FoveaSystem()
    cam = system.camera
    roi = ((cam.cols - args.size) // 2, (cam.rows - args.size) // 2, args.size, args.size)
    b = 2 * args.h
    rows = []
    for name, load in SCENES.items():
        stack, truth = simulate_colour_stack(load(), system, args.h, roi, SensorModel(), seed=1, name=name)
        raw = Stack(mosaic(stack.frames, "RGGB").astype(stack.frames.dtype), {**stack.meta, "cfa": "RGGB"})
        t = truth[b:-b, b:-b]
        cases = [("rgb", m, c) for m in ("classical", "learned") for c in ("luma", "channels")]
        cases += [("bayer", m, None) for m in ("classical", "learned")]  # joint demosaicking takes no mode
        for kind, method, mode in cases:
            src = stack if kind == "rgb" else raw
            start = time.process_time()
            image = reconstruct(src, method, registration="optics", colour=mode)
            seconds = time.process_time() - start
            x = image[b:-b, b:-b]
            row = {"scene": name, "frames": kind, "method": method,
                   "colour": mode if kind == "rgb" else ("joint demosaicking" if method == "classical" else "joint demosaicking, refined"),
                   "psnr_rgb": round(psnr(x, t), 2), "psnr_luma": round(psnr(x @ LUMA, t @ LUMA), 2),
                   "cpu_s": round(seconds, 2)}
            rows.append(row)
            print(row, flush=True)
        # the classical method on demosaicked-first Bayer frames, for comparison with joint
        rgb = demosaic(raw.to_float().numpy(), "RGGB")
        first = Stack(rgb.astype(np.float32), {k: v for k, v in stack.meta.items() if k not in ("bit_depth", "black_level")})
        image = reconstruct(first, "classical", registration="optics", colour="luma")[b:-b, b:-b]
        row = {"scene": name, "frames": "bayer", "method": "classical", "colour": "demosaic first, luma",
               "psnr_rgb": round(psnr(image, t), 2), "psnr_luma": round(psnr(image @ LUMA, t @ LUMA), 2), "cpu_s": None}
        rows.append(row)
        print(row, flush=True)
    summary = {}
    for key in {(r["frames"], r["method"], r["colour"]) for r in rows}:
        sel = [r["psnr_rgb"] for r in rows if (r["frames"], r["method"], r["colour"]) == key]
        summary[" / ".join(key)] = round(float(np.mean(sel)), 2)
    for k in sorted(summary):
        print(f"mean PSNR {k}: {summary[k]:.2f} dB")
    benchutil.finish(args, rows, summary)


if __name__ == "__main__":
    main()
