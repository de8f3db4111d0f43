"""Speed against error of every reconstruction method, on the held-out photographs: docs/speed-vs-error.md and its plot.

    python benchmarks/bench_speed_vs_error.py                # h = 2, 4, 7; 128², 256², 960²; every photograph
    python benchmarks/bench_speed_vs_error.py --quick        # h = 4; 128² and 256²; two photographs; best of 1
    python benchmarks/bench_speed_vs_error.py --checkpoint cells.jsonl   # resumable: a rerun skips the cells kept

Every cell is a stack of the held-out matrix's first condition (F 1.4, 10,000 e-, reference frame
0; :mod:`hbis_torch.training.heldout`) of one of its photographs, which no training pool holds,
at one h and one ROI side (960² is the sensor's full height, square: the largest stack the
held-out simulator makes). Each method reconstructs it in this process (imports, model
sessions and the positions' caches warm; best of ``--repeats``) and is scored by PSNR against
the simulator's truth without a border of 2 LR pixels (:func:`hbis_torch.training.heldout.score`):

- ``bicubic``: the reference frame upsampled h times (torch's bicubic), the floor any method must beat;
- ``classical``: the classical step (positions from the optics, splat, Wiener);
- ``learned ... xE``: the classical step and the network, in the file's precision, over E of the
  square's symmetries (its self-ensemble). :data:`LEARNED` lists the models: a tier of models
  (``best``, ...) is one more line there. fp32 and int8 run on onnxruntime's CPU kernels (the
  default provider); bf16 (``--precision bf16``) in OpenVINO, and only where this CPU has bf16
  units (its rows are left out elsewhere, and the run says so).

The table gives, per h and size, each method's median time and mean PSNR over the photographs;
the plot, one panel per h, PSNR against time. Timings on shared cores are noisy: compare
methods within one run (the same stacks, side by side), not across runs.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]

#: The learned variants: (label, model file name with {h} or None for the shipped one, precision, ensemble).
LEARNED = (
    ("learned fp32 x1", None, "fp32", 1),
    ("learned int8 x1", None, "int8", 1),
    ("learned bf16 x1", None, "bf16", 1),
    ("learned fp32 x2", None, "fp32", 2),
    ("learned fp32 x8", None, "fp32", 8),
    ("learned best fp32 x1", "hbis_sr_h{h}_best.onnx", "fp32", 1),  # the best tier (hbis reconstruct --model best)
    ("learned best fp32 x2", "hbis_sr_h{h}_best.onnx", "fp32", 2),  # its default self-ensemble at h = 2 and 4
    ("learned best int8 x2", "hbis_sr_h{h}_best.onnx", "int8", 2),
    ("learned best bf16 x2", "hbis_sr_h{h}_best.onnx", "bf16", 2),
    ("learned best fp32 x8", "hbis_sr_h{h}_best.onnx", "fp32", 8),
)


def bicubic(stack) -> np.ndarray:
    import torch
    import torch.nn.functional as F

    frame = stack.to_float()[stack.reference_index][None, None]
    return F.interpolate(frame, scale_factor=stack.h, mode="bicubic", align_corners=False)[0, 0].clamp(0, 1).numpy()


def best_of(fn, repeats: int):
    """(result, best seconds) of ``repeats`` calls of ``fn``."""
    best, result = float("inf"), None
    for _ in range(repeats):
        t0 = time.perf_counter()
        result = fn()
        best = min(best, time.perf_counter() - t0)
    return result, best


def cell(stack, truth, runners: dict, repeats: int) -> dict:
    """{method: (seconds, PSNR dB)} for one stack."""
    from hbis_torch.reconstruct.classical import optics_cutoff
    from hbis_torch.reconstruct.learned.method import classical_and_noise
    from hbis_torch.training.heldout import score

    h = stack.h
    out = {}
    image, seconds = best_of(lambda: bicubic(stack), repeats)
    out["bicubic"] = (seconds, score(image, truth, h))
    (image, noise), classical_s = best_of(lambda: classical_and_noise(stack, "optics"), repeats)
    out["classical"] = (classical_s, score(image, truth, h))
    cutoff = optics_cutoff(stack.system)
    for label, _, _, ensemble in LEARNED:
        if (h, label) not in runners:  # bf16 on a CPU without it
            continue
        refined, seconds = best_of(lambda r=runners[h, label], e=ensemble: r(image, noise, cutoff, ensemble=e,
                                                                          extrapolate=True), repeats)
        out[label] = (classical_s + seconds, score(refined, truth, h))
    return out


def measure(hs, sizes, photos, repeats: int, checkpoint: Path | None = None) -> list[dict]:
    """Every cell's rows; with ``checkpoint`` (JSON lines), each finished cell's rows are appended
    to it, and the cells it already holds (measured with the same ``repeats``) are read, not run
    again: a run stopped part way goes on where it stopped."""
    from hbis_torch.reconstruct.learned import LearnedSR, models_dir
    from hbis_torch.reconstruct.learned.runtime import bf16_available
    from hbis_torch.training.heldout import CONDITIONS, make_stack

    saved = []
    if checkpoint is not None and checkpoint.exists():
        saved = [json.loads(line) for line in checkpoint.read_text().splitlines() if line.strip()]
    bf16 = bf16_available()
    if not bf16:
        print("the bf16 rows are left out: bf16 needs the openvino package and a CPU with bf16 units", file=sys.stderr)
    runners = {(h, label): LearnedSR(None if name is None else models_dir() / name.format(h=h), h=h,
                                     provider="auto" if precision == "bf16" else "cpu", precision=precision)
               for h in hs for label, name, precision, _ in LEARNED if precision != "bf16" or bf16}
    rows = []
    for h in hs:
        for size in sizes:
            for photo in photos:
                key = {"h": h, "size": size, "photo": photo, "repeats": repeats}
                done = [r for r in saved if all(r.get(k) == v for k, v in key.items())]
                if not done:
                    stack, truth = make_stack(CONDITIONS[0], photo, h, size, seed=1000)
                    done = [{**key, "method": method, "seconds": seconds, "psnr_db": db}
                            for method, (seconds, db) in cell(stack, truth, runners, repeats).items()]
                    if checkpoint is not None:
                        with checkpoint.open("a") as file:
                            file.writelines(json.dumps(r) + "\n" for r in done)
                rows += done
                print(f"h = {h}, {size}², {photo}: done", file=sys.stderr, flush=True)
    return rows


def markdown(rows: list[dict], args, hs, sizes, photos) -> str:
    methods = list(dict.fromkeys(r["method"] for r in rows))
    lines = ["# Speed against error", "",
             "Regenerate with `python benchmarks/bench_speed_vs_error.py " + " ".join(args.argv) + "` "
             f"(its docstring says what each method and cell is). This run: {len(os.sched_getaffinity(0))} CPUs "
             f"shared with other jobs (load average {os.getloadavg()[0]:.1f} at the end), best of {args.repeats}; "
             f"photographs {', '.join(photos)} (held out from training), condition F 1.4, 10,000 e-, "
             "reference frame 0. Time: median over the photographs, seconds, in one warm process "
             "(start-up not counted: `benchmarks/bench_fast.py` measures it). PSNR: mean, dB.", "",
             "![PSNR against time](speed-vs-error.png)", ""]
    for h in hs:
        lines += [f"## h = {h}", "", "| method | " + " | ".join(f"{s}²: time, PSNR" for s in sizes) + " |",
                  "| --- |" + " ---: |" * len(sizes)]
        for method in methods:
            cells = []
            for size in sizes:
                sel = [r for r in rows if r["h"] == h and r["size"] == size and r["method"] == method]
                cells.append(f"{np.median([r['seconds'] for r in sel]):.3f} s, {np.mean([r['psnr_db'] for r in sel]):.2f} dB")
            lines.append(f"| {method} | " + " | ".join(cells) + " |")
        lines.append("")
    return "\n".join(lines)


def plot(rows: list[dict], hs, sizes, path: Path) -> None:
    from matplotlib import colormaps
    from matplotlib.figure import Figure

    fig = Figure(figsize=(5 * len(hs), 4))
    axes = fig.subplots(1, len(hs), squeeze=False)
    methods = list(dict.fromkeys(r["method"] for r in rows))
    colours = colormaps["tab20"]  # a colour of its own for each of up to 20 methods
    for ax, h in zip(axes[0], hs):
        for k, method in enumerate(methods):
            pts = [(np.median([r["seconds"] for r in rows if (r["h"], r["size"], r["method"]) == (h, s, method)]),
                    np.mean([r["psnr_db"] for r in rows if (r["h"], r["size"], r["method"]) == (h, s, method)]))
                   for s in sizes]
            ax.plot(*zip(*pts), marker="o", color=colours(k % 20), label=method)
        ax.set_xscale("log")
        ax.set_xlabel("time, s (one warm process)")
        ax.set_ylabel("PSNR, dB")
        ax.set_title(f"h = {h}; ROI {', '.join(f'{s}²' for s in sizes)}")
        ax.grid(alpha=0.3)
    axes[0][0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=100)


def main(argv=None) -> int:
    from hbis_torch.training.heldout import PHOTOS

    argv = sys.argv[1:] if argv is None else argv
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="h = 4, 128² and 256², two photographs, best of 1")
    parser.add_argument("--hs", type=int, nargs="+", default=None, choices=(2, 4, 7))
    parser.add_argument("--sizes", type=int, nargs="+", default=None, help="ROI sides, LR pixels (default 128 256 960)")
    parser.add_argument("--photos", nargs="+", default=None, choices=PHOTOS)
    parser.add_argument("--repeats", type=int, default=None)
    parser.add_argument("--out", type=Path, default=REPO / "docs" / "speed-vs-error.md")
    parser.add_argument("--checkpoint", type=Path, default=None,
                        help="JSON-lines file of the finished cells: a rerun with it skips them (the full frame "
                        "at h = 7 takes minutes a cell)")
    args = parser.parse_args(argv)
    # the command the report prints: a checkpoint file is where this run kept its cells, not how to rerun it
    args.argv = [a for i, a in enumerate(argv) if not a.startswith("--checkpoint")
                 and not (i and argv[i - 1] == "--checkpoint")]
    hs = args.hs or ([4] if args.quick else [2, 4, 7])
    sizes = args.sizes or ([128, 256] if args.quick else [128, 256, 960])
    photos = args.photos or (list(PHOTOS[:2]) if args.quick else list(PHOTOS))
    args.repeats = args.repeats or (1 if args.quick else 3)
    rows = measure(hs, sizes, photos, args.repeats, args.checkpoint)
    text = markdown(rows, args, hs, sizes, photos)
    from hbis_torch.provenance import write_results

    write_results(args.out, text, argv=args.argv)
    plot(rows, hs, sizes, args.out.with_suffix(".png"))
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
