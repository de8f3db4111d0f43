"""Does ``hbis validate`` rank methods as the ground truth does? Simulated HBIS scans, where the
truth is known, scored both ways.

Each case is a benchmark stack (:mod:`hbis_torch.simulate.cases`: procedural scenes and held-out
photographs, 12-bit, shot and read noise) at h = 2 and 4. Every method (the single frame
enlarged bicubically, classical, learned) is scored by cross-validation
(:func:`hbis_torch.validate.cross_validate`, 3 frames held out, optical positions) and by PSNR
against the truth (all frames, a border of 2 LR pixels left out). Then simulated bursts
(:func:`hbis_torch.simulate.burst.simulate_burst`: photographs of skimage.data, 12 frames, shifts up
to 1.5 px and rotations up to 1 degree, noise 0.01, 8 bits; the true motions recorded) at S = 2 and
4, scored the same way with the stack's motions. A case agrees when the two
orders of the three methods are the same; the pairs column counts the pairs of methods ordered
alike (of 3), and "gap" is the truth's smallest difference between two methods, dB (orders that
differ by less are a coin toss for any score).

    python3 benchmarks/bench_validate.py [--size 48] [--blur 0.2] [--only scan|burst] [--json benchmarks/results/bench_validate.json]
"""

from __future__ import annotations

import argparse
import itertools

import benchutil  # first: pins numpy/scipy to one thread before they load
import torch

from hbis_torch.config import FoveaSystem
from hbis_torch.reconstruct import reconstruct
from hbis_torch.simulate.cases import make_stack, roi_for, scene_cases
from hbis_torch.training.heldout import score
from hbis_torch.validate import DEFAULT_BLUR_PX, cross_validate, single_frame

METHODS = ("single-frame", "classical", "learned")


BURST_SCENES = ("camera", "coins", "brick")


def scan_case(system, h: int, size: int, index: int, scene: str, blur: float) -> dict:
    """One simulated scan scored both ways: a row of the table."""
    stack, truth = make_stack(system, h, roi_for(system, size, index), scene, 1000 + index)
    return case(stack, truth, "scan", scene, blur, registration="optics")


def burst_case(scale: int, size: int, scene: str, blur: float) -> dict:
    """One simulated burst scored both ways: a row of the table."""
    import numpy as np
    import skimage.data

    from hbis_torch.simulate.burst import random_motions, simulate_burst
    from hbis_torch.stack_io import Stack, make_burst_meta

    image = getattr(skimage.data, scene)()
    side = size * scale
    v0, u0 = (image.shape[0] - side) // 2, (image.shape[1] - side) // 2
    truth = image[v0:v0 + side, u0:u0 + side].astype(np.float64) / 255
    motions = random_motions(12, (size, size), np.random.default_rng(0), max_shift=1.5, max_rotation_deg=1.0)
    burst = simulate_burst(truth, scale, motions, noise=0.01, seed=0)
    meta = make_burst_meta(scale, (0, 0, size, size), motions, [1.0] * 12, ["identity"] + ["similarity"] * 11,
                           [[1.0, 0.0]] * 12, bit_depth=8)
    return case(Stack(burst.frames, meta).validate(), burst.truth, "burst", scene, blur)


def case(stack, truth, kind: str, scene: str, blur: float, registration: str = "auto") -> dict:
    """A stack and its truth scored both ways."""
    h = stack.h
    result = cross_validate(stack, METHODS, registration=registration, blur_px=blur)
    ref = stack.to_float().numpy()[stack.reference_index]
    true = {"single-frame": score(single_frame(ref, h), truth, h)}
    for method in METHODS[1:]:
        true[method] = score(reconstruct(stack, method, registration=registration), truth, h)
    cv = {m: result.methods[m].mean_psnr for m in METHODS}
    pairs = sum((cv[a] < cv[b]) == (true[a] < true[b]) for a, b in itertools.combinations(METHODS, 2))
    gap = min(abs(true[a] - true[b]) for a, b in itertools.combinations(METHODS, 2))
    return {"kind": kind, "h": h, "scene": scene, "validate_db": cv, "truth_db": true, "pairs_agree": pairs,
            "agree": pairs == 3, "truth_gap_db": gap}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=48)
    parser.add_argument("--blur", type=float, default=DEFAULT_BLUR_PX)
    parser.add_argument("--only", choices=("scan", "burst"))
    parser.add_argument("--json")
    args = parser.parse_args()
    torch.set_num_threads(1)
    system = FoveaSystem()
    rows = []
    print(f"{'kind':<5} {'h':>2} {'scene':<10} " + " ".join(f"{m[:9]:>19}" for m in METHODS) + "  pairs  gap dB")
    print(f"{'':19}" + "  validate / truth " * 3)
    todo = []
    if args.only != "burst":
        todo += [lambda h=h, i=i, s=s: scan_case(system, h, args.size, i, s, args.blur)
                 for h in (2, 4) for i, (_, s) in enumerate(scene_cases(args.size))]
    if args.only != "scan":
        todo += [lambda h=h, s=s: burst_case(h, args.size, s, args.blur) for h in (2, 4) for s in BURST_SCENES]
    for run in todo:
        row = run()
        rows.append(row)
        cells = " ".join(f"{row['validate_db'][m]:9.2f} / {row['truth_db'][m]:6.2f}" for m in METHODS)
        print(f"{row['kind']:<5} {row['h']:>2} {row['scene']:<10} {cells}  {row['pairs_agree']}/3  "
              f"{row['truth_gap_db']:6.2f}", flush=True)
    clear = [r for r in rows if r["truth_gap_db"] >= 0.5]
    summary = {"cases": len(rows), "agree": sum(r["agree"] for r in rows),
               "pairs_agree": sum(r["pairs_agree"] for r in rows), "pairs": 3 * len(rows),
               "clear_cases": len(clear), "clear_agree": sum(r["agree"] for r in clear)}
    print(f"orders agree on {summary['agree']} of {summary['cases']} cases ({summary['pairs_agree']} of "
          f"{summary['pairs']} pairs); on {summary['clear_agree']} of {summary['clear_cases']} cases whose "
          "methods the truth separates by >= 0.5 dB")
    benchutil.finish(args, rows, summary)


if __name__ == "__main__":
    main()
