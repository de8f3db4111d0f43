"""Is a held-out cell's loss its draw of shifts? The same burst rendered with another cell's motion.

    python training/swap_shifts.py --out benchmarks/results/swap_shifts.json
        [--pairs moving_object:translation translation:moving_object] [--scale 2] [--frames 8] [--seed 0]
        [--size 640x480] [--vidsr]

Each pair ``A:B`` renders cell A of :mod:`training/eval_handheld.py` twice with
:func:`~hbis_torch.training.handheld_render.render_burst`: as drawn, and with the frames' global
motion of cell B (same S, F and seed) in place of A's, everything else (scene, moving object,
rolling shutter, gains, noise draw) kept. Both go through the classical path with its defaults
(``assemble_burst``, then ``reconstruct(stack, "classical")``), and with ``--vidsr`` through the
peer vidsr in its best setting for fidelity (``benchmarks/peers/vidsr_peer.py``), and are scored as
the evaluation scores them. Beside the PSNRs the file holds each frame's sub-pixel phase at the frame's centre,
in output px (the true motion's shift times S, modulo S): a burst whose phases cluster leaves
rows or columns of the S-times lattice without samples of their own, and the filled-in nodes
cost what no motion estimate can win back.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np


def _evaluation():
    """training/eval_handheld.py, loaded from its path: its scoring, bicubic row, peer and provenance."""
    import importlib.util

    if "eval_handheld" not in sys.modules:
        spec = importlib.util.spec_from_file_location("eval_handheld", Path(__file__).resolve().parent / "eval_handheld.py")
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        sys.modules["eval_handheld"] = module
    return sys.modules["eval_handheld"]


_peer, bicubic, psnr, provenance = (getattr(_evaluation(), name) for name in ("_peer", "bicubic", "psnr", "provenance"))


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    p.add_argument("--out", type=Path, required=True, help="results JSON (refused if it exists)")
    p.add_argument("--pairs", nargs="+", default=["moving_object:translation", "translation:moving_object"],
                   help="CELL:DONOR motions: cell CELL rendered with DONOR's frame motions")
    p.add_argument("--scale", type=int, default=2, help="S (default 2)")
    p.add_argument("--frames", type=int, default=8, help="F (default 8)")
    p.add_argument("--seed", type=int, default=0, help="the evaluation's seed (default 0)")
    p.add_argument("--size", default="640x480", help="frame size WxH in LR px (default 640x480, the evaluation's)")
    p.add_argument("--vidsr", action="store_true", help="score the peer vidsr too (installed apart)")
    p.add_argument("--border", type=int, default=4, help="LR px left out of the PSNR (default 4)")
    return p.parse_args(argv)


def check_args(args) -> str | None:
    from hbis_torch.training.handheld_render import MOTIONS

    if args.out.exists():
        return f"--out {args.out} exists: choose a new path (nothing is overwritten)"
    for pair in args.pairs:
        names = pair.split(":")
        if len(names) != 2 or any(n not in MOTIONS for n in names):
            return f"--pairs takes CELL:DONOR with both in {', '.join(MOTIONS)}; got {pair!r}"
    if args.vidsr and not _peer().available():
        return "--vidsr: vidsr is not installed (pip install vidsr)"
    if args.scale < 2 or args.frames < 2:
        return "--scale and --frames must be at least 2"
    try:
        args.width, args.height = (int(n) for n in args.size.lower().split("x"))
    except ValueError:
        return f"--size takes WxH in px, e.g. 640x480; got {args.size!r}"
    if min(args.width, args.height) < 32:
        return "--size must be at least 32 x 32 px"
    return None


def centre_phases(motions: np.ndarray, scale: int, width: int, height: int) -> list[list[float]]:
    """Each frame's sub-pixel phase (x, y) at the frame's centre, output px in [0, S)."""
    c = np.array([(width - 1) / 2, (height - 1) / 2, 1.0])
    out = []
    for m in motions:
        p = m @ c
        out.append([round(float((scale * (p[i] / p[2] - c[i])) % scale), 3) for i in (0, 1)])
    return out


def render_with(motion: str, donor: str | None, args):
    """Cell ``motion``'s burst, with ``donor``'s frame motions where given."""
    import hbis_torch.training.handheld_render as render

    drawn = render.draw_motion
    if donor is not None:
        seed = [args.seed, render.MOTIONS.index(donor), args.scale, args.frames]
        theirs = drawn(donor, args.frames, args.width, args.height, np.random.default_rng(seed))[0]
        render.draw_motion = lambda *a: (theirs,) + drawn(*a)[1:]
    try:
        return render.render_burst(motion, args.scale, args.frames, args.width, args.height, seed=args.seed)
    finally:
        render.draw_motion = drawn


def classical(burst, args) -> float:
    from hbis_torch.capture.burst import assemble_burst
    from hbis_torch.reconstruct import reconstruct

    stack, _ = assemble_burst(burst.frames, args.scale)
    return psnr(reconstruct(stack, "classical"), burst.truth, args.border, args.scale)


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    args = parse_args(argv)
    problem = check_args(args)
    if problem:
        print(f"swap_shifts: {problem}", file=sys.stderr)
        return 2
    results = {"provenance": provenance(argv, "training/swap_shifts.py"),
               "settings": {"scale": args.scale, "frames": args.frames, "seed": args.seed, "size": [args.width, args.height],
                            "border_px": args.border},
               "pairs": {}}
    for pair in args.pairs:
        motion, donor = pair.split(":")
        t = time.perf_counter()
        row = {}
        for name, burst in (("drawn", render_with(motion, None, args)), ("swapped", render_with(motion, donor, args))):
            row[name] = {"classical_db": classical(burst, args),
                         "bicubic_db": psnr(bicubic(burst.frames[0], args.scale), burst.truth, args.border, args.scale),
                         "phases_px": centre_phases(burst.motions, args.scale, args.width, args.height)}
            if args.vidsr:
                image = _peer().vidsr_sr(burst.frames, args.scale)
                row[name]["vidsr_db"] = psnr(image, burst.truth, args.border, args.scale)
        row["seconds"] = time.perf_counter() - t
        results["pairs"][pair] = row
        print(f"{motion} as drawn {row['drawn']['classical_db']:.2f} dB, with {donor}'s motion "
              f"{row['swapped']['classical_db']:.2f} dB", flush=True)
    from hbis_torch.io_utils import atomic_write_text

    atomic_write_text(args.out, json.dumps(results, indent=1) + "\n")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
