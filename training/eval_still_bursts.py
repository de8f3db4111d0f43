"""Bursts that hardly moved (a tripod, a fixed camera, a steady hand): the output against the single frame.

    python training/eval_still_bursts.py --out benchmarks/results/eval_still_bursts.json
        [--seeds 30 31] [--spreads 0 0.05 0.1 0.2 2.5] [--no-learned] [--photos held-out|training]
        [--still-spacings 0.1 0.05 0.02]
    python training/eval_still_bursts.py --raw --out benchmarks/results/eval_still_bursts_raw.json
        [--photos training] [--still-spacings 0.2]

A burst whose frames did not move holds no detail beyond its reference frame's, only less noise;
its samples all lie where the reference's do, which at even S is halfway between the output
lattice's nodes. Each cell renders a burst with the third renderer (``eval_third_renderer.py``:
the held-out photographs, a Gaussian lens of 0.3 LR px, 640 x 480, motion ``translation``) whose
shifts are drawn up to ``spread`` LR px each way (0: only the noise differs; 2.5: the renderer's
own hand-held shifts), and scores against the truth (a border of 4 LR px left out): bicubic of the
reference, the classical and learned methods as they are, and the same with the still rule off
(``hbis_torch.reconstruct.burst_fill.STILL_SPACING`` set to 0: the code before the rule, the same
bits), and with the lattice placed by the samples' common offset even where their shifts cluster
(``hbis_torch.reconstruct.classical.lattice.CLUSTERED`` set past 1: the code before that rule).
The rules' settings were chosen on the training photographs (``--photos training``: the still
rule's first spacing on seeds 12 and 13, its present one, the raw path's and the placement on 12
to 14); the defaults are other photographs and seeds. ``--still-spacings`` scores other spacings
beside the default in the same run, each a column. ``--raw``: raw bursts through the joint path
(:func:`run_raw_cell`), which the rule runs at the frames' own size and enlarges where most frames
are still (``--photos training``: the colour photographs among the training ones,
:data:`RAW_CELL_PHOTOS`).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

CELLS = ((2, 8), (2, 16), (3, 16), (4, 16))  # (S, F)
# --raw's photographs: held-out ones, or the colour photographs among the training ones
RAW_CELL_PHOTOS = {"held-out": ("chelsea", "rocket"), "training": ("immunohistochemistry", "hubble_deep_field")}
BORDER_LR = 4


def run_cell(scale: int, count: int, spread: float, seed: int, learned: bool, photos: str = "held-out",
             spacings: tuple = ()) -> dict:
    import eval_third_renderer as third
    from eval_handheld import bicubic, psnr

    import hbis_torch.reconstruct.burst_fill as burst_fill
    import hbis_torch.reconstruct.classical.lattice as lattice
    from hbis_torch.capture.burst import assemble_burst
    from hbis_torch.reconstruct import reconstruct
    from hbis_torch.simulate.rasters import HELD_OUT_PHOTOS
    from hbis_torch.training.data import TRAIN_PHOTOS

    third.MAX_SHIFT_PX = spread
    frames, truth, _ = third.render("translation", scale, count, 640, 480, seed,
                                    HELD_OUT_PHOTOS if photos == "held-out" else TRAIN_PHOTOS)
    stack, _ = assemble_burst(frames, scale)
    out = {"bicubic": psnr(bicubic(frames[0], scale), truth, BORDER_LR, scale)}
    rule = burst_fill.STILL_SPACING
    for method in ("classical", "learned") if learned else ("classical",):
        notes: list[str] = []
        out[method] = psnr(reconstruct(stack, method, messages=notes), truth, BORDER_LR, scale)
        out[f"{method}_said"] = [n for n in notes if "hardly moved" in n]
        for spacing in (0.0, *spacings):
            burst_fill.STILL_SPACING = spacing
            try:
                key = f"{method}_without_rule" if spacing == 0 else f"{method}_still_spacing_{spacing:g}"
                out[key] = psnr(reconstruct(stack, method), truth, BORDER_LR, scale)
            finally:
                burst_fill.STILL_SPACING = rule
        clustered = lattice.CLUSTERED
        lattice.CLUSTERED = 2.0
        try:
            out[f"{method}_without_placement"] = psnr(reconstruct(stack, method), truth, BORDER_LR, scale)
        finally:
            lattice.CLUSTERED = clustered
    return out


def run_raw_cell(scale: int, spread: float, seed: int, photo: str, spacings: tuple = ()) -> dict:
    """A raw cell (``--raw``): the raw matrix's renderer (:mod:`hbis_torch.training.heldout_raw`,
    RGGB, bright, 128 px, 12 frames, shifts up to ``spread`` px), the reference demosaicked
    (OpenCV's edge-aware) and enlarged (bicubic) against the joint path with and without the rule
    (``burst_fill.STILL_BURST_SHARE`` set past 1), and with each of ``spacings`` as
    ``burst_fill.RAW_STILL_SPACING``."""
    import cv2
    from eval_raw import score, single_frame_demosaicks

    import hbis_torch.reconstruct.burst_fill as burst_fill
    from hbis_torch.capture.raw import normalised, raw_burst_stack
    from hbis_torch.reconstruct.classical.raw_burst import reconstruct_raw_burst
    from hbis_torch.training.heldout_burst import BurstCondition
    from hbis_torch.training.heldout_raw import make_raw_burst

    burst = make_raw_burst(photo, "RGGB", "bright", scale, 128, seed, BurstCondition("still", frames=12,
                                                                                     max_shift_px=spread))
    stack, _ = raw_burst_stack(burst.mosaics, "RGGB", burst.raw, scale)
    values, _ = normalised(burst.mosaics, burst.raw)
    single = single_frame_demosaicks(values[0], "RGGB")["edge-aware"]
    out = {"bicubic": score(cv2.resize(single, None, fx=scale, fy=scale, interpolation=cv2.INTER_CUBIC),
                            burst.truth)["psnr"]}
    notes: list[str] = []
    out["joint"] = score(reconstruct_raw_burst(stack, messages=notes), burst.truth)["psnr"]
    out["joint_said"] = [n for n in notes if "hardly moved" in n]
    rule = burst_fill.STILL_BURST_SHARE
    burst_fill.STILL_BURST_SHARE = 2.0
    try:
        out["joint_without_rule"] = score(reconstruct_raw_burst(stack), burst.truth)["psnr"]
    finally:
        burst_fill.STILL_BURST_SHARE = rule
    spacing = burst_fill.RAW_STILL_SPACING
    for other in spacings:
        burst_fill.RAW_STILL_SPACING = other
        try:
            out[f"joint_still_spacing_{other:g}"] = score(reconstruct_raw_burst(stack), burst.truth)["psnr"]
        finally:
            burst_fill.RAW_STILL_SPACING = spacing
    return out


def summary(cells: dict) -> dict:
    out = {}
    for method in ("classical", "learned", "joint"):
        rows = [c for c in cells.values() if method in c]
        if not rows:
            continue
        still = [c for c in rows if c[f"{method}_said"]]
        out[method] = {
            "minus_bicubic_worst_db": float(min(c[method] - c["bicubic"] for c in rows)),
            "without_rule_minus_bicubic_worst_db": float(min(c[f"{method}_without_rule"] - c["bicubic"] for c in rows)),
            "minus_without_rule_worst_db": float(min(c[method] - c[f"{method}_without_rule"] for c in rows)),
            "minus_without_rule_best_db": float(max(c[method] - c[f"{method}_without_rule"] for c in rows)),
            **_placement(rows, method), **_spacings(rows, method),
            "cells_named_still": len(still), "cells": len(rows)}
    return out


def _placement(rows: list, method: str) -> dict:
    """What the clustered shifts' placement of the lattice gained, where a cell has it. The learned
    method's adaptation is bounded by a share of the classical step's seconds, so its figures vary a
    little from run to run and its count of cells changed includes some whose input did not move."""
    rows = [c for c in rows if f"{method}_without_placement" in c]
    if not rows:
        return {}
    gains = [c[method] - c[f"{method}_without_placement"] for c in rows]
    return {"without_placement_minus_bicubic_worst_db": float(min(c[f"{method}_without_placement"] - c["bicubic"]
                                                                  for c in rows)),
            "minus_without_placement_worst_db": float(min(gains)),
            "minus_without_placement_best_db": float(max(gains)),
            "cells_placement_changed": sum(abs(g) > 0 for g in gains)}


def _spacings(rows: list, method: str) -> dict:
    """Each other still spacing's (``--still-spacings``) ``method`` - bicubic (the demosaicked
    reference's, for raw cells), mean and worst, beside the default's mean."""
    out = {}
    for key in sorted({k for c in rows for k in c if k.startswith(f"{method}_still_spacing_")}):
        gains = [c[key] - c["bicubic"] for c in rows]
        out[key.removeprefix(f"{method}_")] = {"minus_bicubic_mean_db": float(sum(gains) / len(gains)),
                                               "minus_bicubic_worst_db": float(min(gains))}
    if not out:
        return {}
    gains = [c[method] - c["bicubic"] for c in rows]
    return {"minus_bicubic_mean_db": float(sum(gains) / len(gains)), **out}


def main(argv=None) -> int:
    from hbis_torch.provenance import write_results

    argv = sys.argv[1:] if argv is None else list(argv)
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0], epilog=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", type=Path, required=True, help="results JSON")
    p.add_argument("--seeds", nargs="+", type=int, default=[30, 31])
    p.add_argument("--spreads", nargs="+", type=float, default=[0.0, 0.05, 0.1, 0.2, 2.5],
                   help="the frames' largest shift each way, LR px")
    p.add_argument("--no-learned", action="store_true", help="the classical method alone")
    p.add_argument("--photos", choices=("held-out", "training"), default="held-out",
                   help="the held-out photographs (default) or the training ones (development data)")
    p.add_argument("--still-spacings", nargs="+", type=float, default=[],
                   help="other still spacings (burst_fill.STILL_SPACING; with --raw, RAW_STILL_SPACING) scored "
                        "beside the default, each a column")
    p.add_argument("--raw", action="store_true",
                   help="raw bursts instead (the joint path, S = 2 and 3; held-out photographs chelsea and rocket, "
                        "with --photos training immunohistochemistry and hubble_deep_field)")
    args = p.parse_args(argv)
    if any(s < 0 for s in args.spreads) or any(s <= 0 for s in args.still_spacings):
        print("eval_still_bursts: --spreads takes shifts of 0 LR px or more, --still-spacings above 0",
              file=sys.stderr)
        return 2
    cells = {}
    for seed in args.seeds:
        for spread in args.spreads:
            if args.raw:
                jobs = [(f"{photo}|S={scale}|shift {spread:g}|seed {seed}", run_raw_cell,
                         (scale, spread, seed, photo, tuple(args.still_spacings)))
                        for photo in RAW_CELL_PHOTOS[args.photos] for scale in (2, 3)]
            else:
                jobs = [(f"S={scale}|F={count}|shift {spread:g}|seed {seed}", run_cell,
                         (scale, count, spread, seed, not args.no_learned, args.photos, tuple(args.still_spacings)))
                        for scale, count in CELLS]
            for key, run, job in jobs:
                cells[key] = run(*job)
                print(key, {k: round(v, 2) if isinstance(v, float) else v for k, v in cells[key].items()}, flush=True)
    results = {"settings": vars(args) | {"out": str(args.out)}, "cells": cells, "summary": summary(cells)}
    write_results(args.out, results, argv=argv)
    print(results["summary"])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
