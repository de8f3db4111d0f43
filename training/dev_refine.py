"""The refinement on the samples, on the training simulator: each method with and without it.

    python training/dev_refine.py --out benchmarks/results/dev_refine.json
        [--bursts shift:2:8 object:2:8 rot:2:16 ...] [--seed 1] [--no-learned]

Development data, never the held-out renderer: bursts of :func:`~hbis_torch.simulate.burst.
simulate_burst` over collages of the training photographs (640 x 480 frames, lens blur 0.3 LR px,
noise 1 %, shifts to 2 px), as ``training/adapt_dev.py`` and the Wiener fit's development runs
draw them. A burst ``KIND:S:F`` is ``shift`` (translation), ``rot`` (turns to 0.5 degrees) or
``object`` (a fifth of the frame displaced in every frame but the reference). Each goes through
``assemble_burst`` and then ``reconstruct`` with ``refine=False`` and with the default
(:mod:`hbis_torch.reconstruct.classical.refine`), for the classical method and (unless
``--no-learned``) the learned one, scored by PSNR against the truth without 4 LR px of border.
Rows are written as they finish; a rerun with the same ``--out`` resumes.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from eval_handheld import provenance, psnr  # noqa: E402

KINDS = ("shift", "rot", "object")
DEFAULT_BURSTS = ["shift:2:8", "rot:2:8", "object:2:8", "shift:2:16", "rot:2:16", "object:2:16",
                  "shift:3:16", "rot:3:16", "object:3:16", "shift:4:16", "rot:4:16", "object:4:16"]


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    p.add_argument("--out", type=Path, required=True, help="results JSON (resumed where it exists)")
    p.add_argument("--bursts", nargs="+", default=DEFAULT_BURSTS, help="KIND:S:F, KIND in shift, rot, object")
    p.add_argument("--seed", type=int, default=1, help="the bursts' seed (default 1)")
    p.add_argument("--no-learned", action="store_true", help="the classical method alone")
    return p.parse_args(argv)


def check_args(args) -> str | None:
    for burst in args.bursts:
        parts = burst.split(":")
        if len(parts) != 3 or parts[0] not in KINDS or not all(x.isdigit() for x in parts[1:]):
            return f"--bursts takes KIND:S:F with KIND in {', '.join(KINDS)}; got {burst!r}"
        if not 2 <= int(parts[1]) <= 4 or int(parts[2]) < 2:
            return f"--bursts: S must be 2 to 4 and F at least 2; got {burst!r}"
    return None


def make_burst(kind: str, scale: int, frames: int, seed: int, width: int = 640, height: int = 480):
    """(truth (S H, S W), frames (F, H, W)) of one development burst."""
    from hbis_torch.simulate.burst import random_motions, simulate_burst
    from hbis_torch.training.data import TRAIN_PHOTOS
    from hbis_torch.training.handheld_render import collage

    rng = np.random.default_rng([seed, KINDS.index(kind), scale, frames])
    truth = collage(scale * height, scale * width, rng, photos=[n for n in TRAIN_PHOTOS if n not in ("page", "text")])
    motions = random_motions(frames, (height, width), rng, max_shift=2.0,
                             max_rotation_deg=0.5 if kind == "rot" else 0.0)
    patch, moving = None, ()
    if kind == "object":
        side = scale * (width // 5)
        patch, moving = (scale * height // 3, scale * width // 3, side, scale * 25, scale * 35), range(1, frames)
    b = simulate_burst(truth, scale, motions, noise=0.01, seed=seed, blur_px=0.3, moving_patch=patch,
                       moving_frames=moving)
    return b.truth, b.frames


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    args = parse_args(argv)
    problem = check_args(args)
    if problem:
        print(f"dev_refine: {problem}", file=sys.stderr)
        return 2
    from hbis_torch.capture.burst import assemble_burst
    from hbis_torch.io_utils import atomic_write_text
    from hbis_torch.reconstruct import reconstruct

    results = json.loads(args.out.read_text()) if args.out.exists() else {"provenance": [], "rows": {}}
    results["provenance"].append(provenance(argv, "training/dev_refine.py"))
    methods = ["classical"] + ([] if args.no_learned else ["learned"])
    for burst in args.bursts:
        kind, S, F = burst.split(":")
        S, F = int(S), int(F)
        key = f"{burst}:{args.seed}"
        row = results["rows"].setdefault(key, {})
        todo = [(m, r) for m in methods for r in (False, True) if f"{m}{'' if r else '_unrefined'}_db" not in row]
        if not todo:
            continue
        truth, frames = make_burst(kind, S, F, args.seed)
        stack, _ = assemble_burst(frames, S)
        for method, refine in todo:
            t = time.perf_counter()
            image = reconstruct(stack, method, refine=refine)
            name = f"{method}{'' if refine else '_unrefined'}"
            row[name + "_db"] = psnr(image, truth, 4, S)
            row[name + "_s"] = time.perf_counter() - t
            atomic_write_text(args.out, json.dumps(results, indent=1) + "\n")
            print(f"{key:18s} {name:20s} {row[name + '_db']:6.2f} dB", flush=True)
    results["summary"] = summary(results["rows"])
    atomic_write_text(args.out, json.dumps(results, indent=1) + "\n")
    return 0


def summary(rows: dict) -> dict:
    """Per S, over the bursts that have both: the mean and the least of each change (dB)."""
    changes = {"classical_refined_minus_unrefined": ("classical_db", "classical_unrefined_db"),
               "learned_refined_minus_unrefined": ("learned_db", "learned_unrefined_db"),
               "learned_minus_classical": ("learned_db", "classical_db"),
               "learned_minus_classical_unrefined": ("learned_unrefined_db", "classical_unrefined_db")}
    out: dict = {}
    for key, row in rows.items():
        group = out.setdefault(f"S={key.split(':')[1]}", {})
        for name, (a, b) in changes.items():
            if a in row and b in row:
                group.setdefault(name, []).append(row[a] - row[b])
    return {S: {name: {"mean_db": float(np.mean(v)), "worst_db": float(np.min(v)), "bursts": len(v)}
                for name, v in group.items()} for S, group in out.items()}


if __name__ == "__main__":
    raise SystemExit(main())
