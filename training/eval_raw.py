"""The held-out raw matrix: raw bursts against the truth, three ways.

    python training/eval_raw.py [--scales 1 2] [--photos chelsea rocket] [--size 96] [--motion homography]
                                [--out raw.json]

Cells (:mod:`hbis_torch.training.heldout_raw`): colour photographs (camera RGB by assumption),
each frame's pixels averaged over their footprint through [handheld]'s held-out motions
(:func:`hbis_torch.training.heldout_burst.motions_for`: shifts uniform in +-1.5 px), mosaicked
with each Bayer pattern (RGGB, BGGR, GRBG, GBRG), Poisson shot noise and Gaussian read noise at
three light levels (20,000 e- / 2 e-, 2,000 / 4, 300 / 6 at the white level), 12 bits over a
black level of 256. Each burst is assembled as ``hbis assemble --burst`` assembles raw files
(:func:`hbis_torch.capture.raw.raw_burst_stack`: motion measured on the 2 x 2-cell luminance),
and every row uses those same measured motions:

* ``demosaick + bicubic``: the reference frame demosaicked (OpenCV's edge-aware), enlarged by
  OpenCV's bicubic resize (S = 1: the demosaick alone);
* ``best single-frame demosaick`` (S = 1): the best of OpenCV's bilinear, VNG and edge-aware
  demosaickers on the reference frame, cell by cell (an oracle choice);
* ``demosaick every frame + RGB burst``: every frame demosaicked (edge-aware), then the RGB burst
  path of ``hbis reconstruct`` (classical: robustness, splat, Wiener deblurring, per channel);
* ``joint``: :func:`hbis_torch.reconstruct.classical.raw_burst.reconstruct_raw_burst`.

Scores: PSNR (data range 1) and the RMS error of each colour (R, G, B) against the truth, in
camera RGB, without a border of 4 output px. S = 1 uses 8 frames, S >= 2 uses 12.
The JSON holds every cell, the means and a provenance block (command, commit, dirty, date, machine).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from hbis_torch.training.heldout_burst import BurstCondition
from hbis_torch.training.heldout_raw import LIGHT_LEVELS, PATTERNS, RAW_PHOTOS, make_raw_burst, provenance

BORDER = 4
ROWS = ("demosaick + bicubic", "best single-frame demosaick", "demosaick every frame + RGB burst", "joint")


def score(image: np.ndarray, truth: np.ndarray) -> dict:
    """PSNR and per-colour RMS error without a border of :data:`BORDER` px."""
    a = np.asarray(image, dtype=np.float64)[BORDER:-BORDER, BORDER:-BORDER]
    b = np.asarray(truth, dtype=np.float64)[BORDER:-BORDER, BORDER:-BORDER]
    mse = float(np.mean((a - b) ** 2))
    return {"psnr": float(10 * np.log10(1.0 / max(mse, 1e-12))),
            "rmse_rgb": [float(np.sqrt(np.mean((a[..., c] - b[..., c]) ** 2))) for c in range(3)]}


def single_frame_demosaicks(values: np.ndarray, cfa: str) -> dict:
    """OpenCV's bilinear, VNG and edge-aware demosaicks of one normalised mosaic (H, W)."""
    import cv2

    out = {}
    scaled16 = np.round(np.clip(values, 0, 1) * 65535).astype(np.uint16)
    scaled8 = np.round(np.clip(values, 0, 1) * 255).astype(np.uint8)
    for name, suffix, data, top in (("bilinear", "", scaled16, 65535), ("VNG", "_VNG", scaled8, 255),
                                    ("edge-aware", "_EA", scaled16, 65535)):
        code = getattr(cv2, f"COLOR_Bayer{cfa}2RGB{suffix}")
        out[name] = cv2.cvtColor(np.ascontiguousarray(data), code).astype(np.float32) / top
    return out


def run_cell(photo: str, cfa: str, light: str, scale: int, size: int, seed: int, motion: str | None = None) -> dict:
    import cv2

    from hbis_torch.capture.raw import normalised, raw_burst_stack
    from hbis_torch.reconstruct.classical.raw_burst import reconstruct_raw_burst
    from hbis_torch.reconstruct.registry import reconstruct
    from hbis_torch.sensor.cfa import demosaic
    from hbis_torch.stack_io import Stack, make_burst_meta

    frames = 8 if scale == 1 else 12
    burst = make_raw_burst(photo, cfa, light, scale, size, seed, BurstCondition("raw", frames=frames), motion)
    times = {}
    t = time.perf_counter()
    stack, _ = raw_burst_stack(burst.mosaics, cfa, burst.raw, scale)
    times["register"] = time.perf_counter() - t
    values, _ = normalised(burst.mosaics, burst.raw)
    cells = {}
    singles = single_frame_demosaicks(values[0], cfa)
    ea = singles["edge-aware"]
    bicubic = ea if scale == 1 else cv2.resize(ea, None, fx=scale, fy=scale, interpolation=cv2.INTER_CUBIC)
    cells[ROWS[0]] = score(bicubic, burst.truth)
    if scale == 1:
        best = max((score(image, burst.truth) | {"which": name} for name, image in singles.items()),
                   key=lambda s: s["psnr"])
        cells[ROWS[1]] = best
    t = time.perf_counter()
    rgb = np.clip(demosaic(values, cfa), 0, 1)
    meta = make_burst_meta(scale, stack.roi, stack.motions, stack.confidence, stack.meta["motion_models"],
                           stack.gain_offset, reference_index=0)
    image = reconstruct(Stack(rgb.astype(np.float32), meta), "classical")
    times["rgb burst"] = time.perf_counter() - t
    cells[ROWS[2]] = score(image, burst.truth)
    t = time.perf_counter()
    image = reconstruct_raw_burst(stack)
    times["joint"] = time.perf_counter() - t
    cells[ROWS[3]] = score(image, burst.truth)
    from hbis_torch.registration import apply_homography
    import torch

    grid = torch.stack(torch.meshgrid(torch.arange(0.0, size, 8, dtype=torch.float64),
                                      torch.arange(0.0, size, 8, dtype=torch.float64), indexing="xy"), -1).reshape(1, -1, 2)
    true = apply_homography(torch.from_numpy(burst.motions), grid.expand(frames, -1, -1))
    found = apply_homography(torch.from_numpy(stack.motions), grid.expand(frames, -1, -1))
    return {"photo": photo, "cfa": cfa, "light": light, "scale": scale, "frames": frames, "size": size,
            "motion": motion or "heldout_burst shifts to 1.5 px",
            "seed": seed, "rows": cells, "seconds": times,
            "motion_error_px": float((true - found).square().sum(-1).mean().sqrt())}


def summarise(cells: list) -> dict:
    out = {}
    for scale in sorted({c["scale"] for c in cells}):
        mine = [c for c in cells if c["scale"] == scale]
        rows = {}
        for row in ROWS:
            psnr = [c["rows"][row]["psnr"] for c in mine if row in c["rows"]]
            if psnr:
                rgb = np.mean([c["rows"][row]["rmse_rgb"] for c in mine if row in c["rows"]], 0)
                rows[row] = {"mean_psnr": float(np.mean(psnr)), "mean_rmse_rgb": rgb.tolist()}
        joint = np.array([c["rows"][ROWS[3]]["psnr"] for c in mine])
        gains = {}
        for row in ROWS[:3]:
            if all(row in c["rows"] for c in mine):
                other = np.array([c["rows"][row]["psnr"] for c in mine])
                gains[row] = {"mean": float(np.mean(joint - other)), "min": float(np.min(joint - other)),
                              "cells_ahead": int(np.sum(joint > other)), "cells": len(mine)}
        out[f"S={scale}"] = {"rows": rows, "joint_minus": gains}
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scales", type=int, nargs="+", default=[1, 2])
    # chelsea and rocket by default: the splat width was chosen on astronaut and coffee
    p.add_argument("--photos", nargs="+", default=["chelsea", "rocket"], choices=RAW_PHOTOS)
    p.add_argument("--patterns", nargs="+", default=list(PATTERNS), choices=PATTERNS)
    p.add_argument("--lights", nargs="+", default=[name for name, _, _ in LIGHT_LEVELS],
                   choices=[name for name, _, _ in LIGHT_LEVELS])
    p.add_argument("--size", type=int, default=96, help="frame side, px (even)")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--motion", choices=("translation", "similarity", "homography"),
                   help="[handheld]'s renderer's motion (handheld_render.draw_motion: shifts to 2 px, turns to "
                   "1 deg, perspective to 2 px) instead of heldout_burst's shifts to 1.5 px")
    p.add_argument("--out", type=Path, default=Path("training/results/eval_raw.json"))
    args = p.parse_args(argv)
    import torch

    torch.set_num_threads(1)
    cells = []
    for scale in args.scales:
        for photo in args.photos:
            for cfa in args.patterns:
                for light in args.lights:
                    seed = args.seed + len(cells)
                    cell = run_cell(photo, cfa, light, scale, args.size, seed, args.motion)
                    cells.append(cell)
                    r = cell["rows"]
                    print(f"S={scale} {photo:9s} {cfa} {light:6s} " + "  ".join(
                        f"{row.split(' ')[0]} {r[row]['psnr']:.2f}" for row in ROWS if row in r), flush=True)
    summary = summarise(cells)
    for key, block in summary.items():
        print(key, json.dumps(block, indent=1))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"provenance": provenance(), "summary": summary, "cells": cells}, indent=1))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
