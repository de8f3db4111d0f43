"""Development bursts whose reference is out of focus: does comparing through its blur keep the detail?

    python training/dev_blurred_reference.py --out benchmarks/results/dev_blurred_reference.json
        [--seeds 0 1 2] [--frames 8 16] [--first-blurs 0 0.7 1.0] [--size 640x480]
        [--reference-weights 1 0]

The robustness weights compare every frame with the reference, each blurred by the same small
Gaussian (:data:`hbis_torch.reconstruct.burst.COMPARE_BLUR_PX`). Where the reference is out of
focus and the other frames are sharp, every edge differs between them by the blur alone, and
the sharp frames' samples there lose weight: the fused lattice then leans on the soft reference
where the detail is. Since 2026-12-07 each frame clearly sharper than the reference is compared
through the reference's blur (:func:`hbis_torch.capture.sharpness.blur_to_reference`: its
sharpness above the reference's over ``BLURRED_SHARE``, blurred for the comparison alone by the
Gaussian whose sharpness comes nearest the reference's; the samples fused are the frames' own).
This script measures it (``matched_db``) beside every frame compared as it is (``plain_db``, the
comparison before; the files made at 507bd29 and afdf8d3 name them ``default_db`` and
``matched_db``, with the matching written in the script).

Since 2026-12-08 an out-of-focus reference's own samples weigh a quarter in the fusion
(:data:`hbis_torch.reconstruct.burst.BLURRED_REFERENCE_WEIGHT`); ``--reference-weights W`` scores
the burst with that weight set to each W beside the default (``reference_weight_W_db``; 1 is the
code before, the same bits), and the summary gives the default less each. (``plain_db`` turns
``blur_to_reference`` off, which also decides that the reference is out of focus: its samples
are then at full weight, so since that day ``matched_minus_plain_db`` holds both changes.)

Bursts: ``training/adapt_dev.py``'s ``cam`` camera (the training photographs, homographies, a
lens of 0.2 to 0.5 LR px, Poisson-Gaussian noise, 12 bits), S = 2, its first frame (the
reference, on the truth's grid) out of focus by a further Gaussian of ``--first-blurs`` LR px
(0: the control, where nothing may change). Classical PSNR against the truth, 4 LR px of border
left out. Development data only: never the held-out renderers or their photographs.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np


def run_burst(seed: int, frames: int, first_blur: float, width: int, height: int, reference_weights=()) -> dict:
    from adapt_dev import camera_burst  # (training/, this script's folder)
    from skimage.metrics import peak_signal_noise_ratio

    import hbis_torch.capture.sharpness as sharpness
    import hbis_torch.reconstruct.burst as burst_path
    from hbis_torch.capture.burst import assemble_burst
    from hbis_torch.reconstruct import reconstruct

    scale = 2
    raw, truth, bits = camera_burst(seed, scale, frames, width, height, first_blur=first_blur)
    stack, _ = assemble_burst(raw, scale, bit_depth=bits)
    b = 4 * scale

    def score(image) -> float:
        return round(float(peak_signal_noise_ratio(truth[b:-b, b:-b], np.clip(image, 0, 1)[b:-b, b:-b],
                                                   data_range=1.0)), 3)

    out = {"seed": seed, "frames": frames, "first_blur": first_blur,
           "matched_db": score(reconstruct(stack, "classical")),
           "sigmas": sharpness.blur_to_reference(burst_path.corrected_frames(stack), stack.reference_index)}
    matching = sharpness.blur_to_reference
    sharpness.blur_to_reference = lambda grey, reference, trusted=None: [0.0] * len(grey)
    try:
        out["plain_db"] = score(reconstruct(stack, "classical"))
    finally:
        sharpness.blur_to_reference = matching
    out["matched_minus_plain_db"] = round(out["matched_db"] - out["plain_db"], 3)
    default = burst_path.BLURRED_REFERENCE_WEIGHT
    for weight in reference_weights:
        burst_path.BLURRED_REFERENCE_WEIGHT = weight
        try:
            out[f"reference_weight_{weight:g}_db"] = score(reconstruct(stack, "classical"))
        finally:
            burst_path.BLURRED_REFERENCE_WEIGHT = default
    return out


def main(argv=None) -> int:
    from hbis_torch.provenance import write_results

    argv = sys.argv[1:] if argv is None else list(argv)
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", type=Path, required=True, help="results JSON")
    p.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    p.add_argument("--frames", nargs="+", type=int, default=[8, 16])
    p.add_argument("--first-blurs", nargs="+", type=float, default=[0.0, 0.7, 1.0],
                   help="the reference's extra Gaussian, LR px (0: in focus, the control)")
    p.add_argument("--size", default="640x480", help="WxH")
    p.add_argument("--reference-weights", nargs="+", type=float, default=[],
                   help="an out-of-focus reference's sample weight, each scored beside the default "
                        "(1: the code before)")
    args = p.parse_args(argv)
    try:
        width, height = (int(v) for v in args.size.lower().split("x"))
    except ValueError:
        width = height = 0
    if (min(width, height) < 32 or min(args.frames) < 3 or min(args.first_blurs) < 0
            or not all(0 <= w <= 1 for w in args.reference_weights)):
        print("dev_blurred_reference: --size WxH of 32 px or more, --frames 3 or more, --first-blurs >= 0, "
              "--reference-weights in [0, 1]", file=sys.stderr)
        return 2
    if not args.out.parent.is_dir():
        print(f"dev_blurred_reference: --out {args.out}: its folder does not exist", file=sys.stderr)
        return 2
    rows = []
    for first_blur in args.first_blurs:
        for frames in args.frames:
            for seed in args.seeds:
                t = time.perf_counter()
                rows.append(run_burst(seed, frames, first_blur, width, height, args.reference_weights))
                print(rows[-1], f"{time.perf_counter() - t:.0f} s", flush=True)
    summary = {}
    for first_blur in args.first_blurs:
        for frames in args.frames:
            gains = [r["matched_minus_plain_db"] for r in rows
                     if r["first_blur"] == first_blur and r["frames"] == frames]
            summary[f"blur={first_blur:g}|F={frames}"] = {"mean_db": float(np.mean(gains)),
                                                          "worst_db": float(np.min(gains)),
                                                          "best_db": float(np.max(gains))}
            for weight in args.reference_weights:
                less = [r["matched_db"] - r[f"reference_weight_{weight:g}_db"] for r in rows
                        if r["first_blur"] == first_blur and r["frames"] == frames]
                summary[f"blur={first_blur:g}|F={frames}"][f"minus_reference_weight_{weight:g}"] = {
                    "mean_db": float(np.mean(less)), "worst_db": float(np.min(less)), "best_db": float(np.max(less))}
    print(summary)
    write_results(args.out, {"settings": {"size": args.size}, "rows": rows, "summary": summary}, argv)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
