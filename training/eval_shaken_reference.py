"""Hand-held bursts with shaken frames: which frame to refine, and whether to fuse the shaken ones.

    python training/eval_shaken_reference.py --out benchmarks/results/eval_shaken_reference.json
        [--motions all translation homography] [--seeds 100 101 102] [--frames 8] [--size 640x480]

The first frame of a hand-held burst is often shaken by the press of the shutter, and frame 0 is
the default reference. Each cell renders a burst with the hand-held renderer
(:func:`hbis_torch.training.handheld_render.render_burst`, S = 2) and puts a shaken copy of its
frame 0 in front: the same noise-free frame (so it lies on the truth's grid) blurred by a
Gaussian of 1 px (defocus, a shake in every direction) or by 3 px along its rows (a shake one
way), then given its own Poisson-Gaussian noise as the renderer's. The classical method's PSNR
against the truth, the border of 8 LR px left out, for the shaken frame as the reference (the
default), for the sharp frame 0 behind it (index 1, on the same grid), and for the burst without
the shaken frame; and the frame ``--reference sharpest`` picks
(:func:`hbis_torch.capture.sharpness.choose_reference`), whether it named the shaken reference.

The second part (``inside``) shakes frames 3 and 5 of the burst itself (the first way, then the
second) and reconstructs it as it is, which leaves out the frames it finds blurred
(:func:`hbis_torch.capture.sharpness.blurred_frames`), beside ``keep_blurred=True``, which fuses
every frame. No setting was tuned on these bursts.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

SHAKES = ("gaussian 1 px", "rows 3 px")
BORDER_LR = 8


def shaken(clean: np.ndarray, shake: str, rng: np.random.Generator, full_well_e: float, read_noise_e: float):
    """The noise-free frame ``clean`` (H, W) in [0, 1] blurred by ``shake``, with noise as the
    renderer's: uint16 (H, W)."""
    from scipy.ndimage import gaussian_filter, uniform_filter1d

    blurred = gaussian_filter(clean, 1.0) if shake == SHAKES[0] else uniform_filter1d(clean, 3, axis=1)
    level = (rng.poisson(blurred * full_well_e) + rng.normal(0, read_noise_e, blurred.shape)) / full_well_e * 65535
    return np.clip(np.round(level), 0, 65535).astype(np.uint16)


def run_cell(motion: str, seed: int, shake: str, frames: int, width: int, height: int) -> dict:
    from hbis_torch.capture.burst import assemble_burst
    from hbis_torch.metrics import psnr
    from hbis_torch.reconstruct import reconstruct
    from hbis_torch.training.handheld_render import render_burst

    burst = render_burst(motion, 2, frames, width, height, seed=seed, keep_clean=True)
    first = shaken(burst.clean[0].astype(np.float64), shake, np.random.default_rng(seed), 5000.0, 3.0)
    cut = slice(2 * BORDER_LR, -2 * BORDER_LR)

    def score(stack) -> float:
        return psnr(reconstruct(stack, "classical")[cut, cut], burst.truth[cut, cut])

    with_shaken = np.concatenate([first[None], burst.frames])
    out = {}
    for name, reference in (("shaken_reference_db", 0), ("sharp_reference_db", 1)):
        stack, messages = assemble_burst(with_shaken, 2, reference=reference)
        out[name] = score(stack)
        if reference == 0:
            out["named"] = any("is blurred" in m for m in messages)
    out["without_shaken_db"] = score(assemble_burst(burst.frames, 2)[0])
    out["sharpest_picks"] = int(assemble_burst(with_shaken, 2, reference="sharpest")[0].reference_index)
    return out


def run_inside(motion: str, seed: int, frames: int, width: int, height: int) -> dict:
    """Frames 3 and 5 shaken (:data:`SHAKES` in turn): the default (blurred frames left out) and
    every frame fused, against the truth."""
    from hbis_torch.capture.burst import assemble_burst
    from hbis_torch.metrics import psnr
    from hbis_torch.reconstruct import reconstruct
    from hbis_torch.training.handheld_render import render_burst

    burst = render_burst(motion, 2, frames, width, height, seed=seed, keep_clean=True)
    rng = np.random.default_rng(seed)
    shaken_frames = burst.frames.copy()
    for k, shake in zip((3, 5), SHAKES):
        shaken_frames[k] = shaken(burst.clean[k].astype(np.float64), shake, rng, 5000.0, 3.0)
    stack, _ = assemble_burst(shaken_frames, 2)
    cut = slice(2 * BORDER_LR, -2 * BORDER_LR)
    notes: list[str] = []
    left_out = psnr(reconstruct(stack, "classical", messages=notes)[cut, cut], burst.truth[cut, cut])
    kept = psnr(reconstruct(stack, "classical", keep_blurred=True)[cut, cut], burst.truth[cut, cut])
    line = next((m for m in notes if "blurred frame" in m), "")
    return {"default_db": left_out, "keep_blurred_db": kept, "left_out": line}


def _stats(values) -> dict:
    return {"mean_db": float(np.mean(values)), "worst_db": float(np.min(values)), "best_db": float(np.max(values))}


def summary(cells: dict, inside: dict) -> dict:
    return {"sharp_minus_shaken_reference": _stats([c["sharp_reference_db"] - c["shaken_reference_db"]
                                                    for c in cells.values()]),
            "named": sum(c["named"] for c in cells.values()), "cells": len(cells),
            "sharpest_picks_a_sharp_frame": sum(c["sharpest_picks"] != 0 for c in cells.values()),
            "inside_default_minus_keep_blurred": _stats([c["default_db"] - c["keep_blurred_db"]
                                                         for c in inside.values()]),
            "inside_both_left_out": sum("[3, 5]" in c["left_out"] for c in inside.values()),
            "inside_cells": len(inside)}


def main(argv=None) -> int:
    from hbis_torch.provenance import write_results

    argv = sys.argv[1:] if argv is None else list(argv)
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, required=True, help="results JSON")
    p.add_argument("--motions", nargs="+", default=["all", "translation", "homography"])
    p.add_argument("--seeds", nargs="+", type=int, default=[100, 101, 102])
    p.add_argument("--frames", type=int, default=8, help="the burst's frames besides the shaken one")
    p.add_argument("--size", default="640x480", help="WxH")
    args = p.parse_args(argv)
    width, height = (int(v) for v in args.size.split("x"))
    cells, inside = {}, {}
    for motion in args.motions:
        for seed in args.seeds:
            for shake in SHAKES:
                key = f"{motion}|{seed}|{shake}"
                cells[key] = run_cell(motion, seed, shake, args.frames, width, height)
                print(key, {k: round(v, 2) if isinstance(v, float) else v for k, v in cells[key].items()}, flush=True)
            for frames in (8, 16):
                key = f"{motion}|{seed}|{frames} frames"
                inside[key] = run_inside(motion, seed, frames, width, height)
                print("inside", key, {k: round(v, 2) if isinstance(v, float) else v for k, v in inside[key].items()},
                      flush=True)
    results = {"settings": vars(args) | {"out": str(args.out)}, "cells": cells, "inside": inside,
               "summary": summary(cells, inside)}
    write_results(args.out, results, argv=argv)
    print(results["summary"])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
