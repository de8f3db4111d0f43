"""Real captured bursts: assemble, reconstruct and cross-validate the shared real-bursts set.

The shared set (four MDSP sequences of Farsiu et al., 2004; not shipped with the project: it
has no licence) is read from ``../shared/data/real-bursts`` beside the checkout. For every
sequence and scale: ``hbis assemble --burst`` (frames, motion models picked, frames trusted, CPU
seconds), then observation-space cross-validation (:func:`hbis_torch.validate.cross_validate`,
three frames held out one at a time) of the single-frame estimate, the classical and the learned
method and the peer vidsr (PSNR of the held-out frames' predictions, dB, and seconds per
reconstruction), and the reconstructions from every frame: the reference enlarged beside
classical and learned, with a crop, as pictures. Writes the JSON results, docs/real-bursts.md's
tables and the pictures.

The peer **vidsr** (benchmarks/peers/vidsr_peer.py: its best setting for fidelity) is scored by
the same folds as the project's methods: ``cross_validate``'s ``extra_methods`` hands it each
fold's stack (every frame but the held-out one, the reference's index re-indexed in it) and
its image, on the reference frame's grid, is predicted through the same forward model. It is
given the frames as the methods see them, in [0, 1]; an RGB sequence's frames as their luma
(BT.601; what the score compares). Included where vidsr is installed (a line on stderr where it
is not); ``--no-vidsr`` leaves it out, ``--vidsr`` insists on it.

    python3 benchmarks/bench_real_bursts.py [--scales 2 3 4] [--holdout 3] [--vidsr | --no-vidsr]
        [--json benchmarks/results/bench_real_bursts.json] [--doc docs/real-bursts.md]
    python3 benchmarks/bench_real_bursts.py --scales 2 4 --extrapolate --no-doc --no-figures \
        --json benchmarks/results/bench_real_bursts_extrapolate.json
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import benchutil  # first: pins numpy/scipy to one thread before they load
import numpy as np
import torch

from hbis_torch.capture.burst import assemble_burst
from hbis_torch.capture.frames import read_frames
from hbis_torch.reconstruct.burst import single_frame
from hbis_torch.reconstruct.registry import reconstruct
from hbis_torch.validate import cross_validate
from peers import vidsr_peer  # benchmarks/ is the script's folder; it imports vidsr only when asked

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data" / "real-bursts"
SEQUENCES = ("text.tif", "disk.tif", "Emily_small.tif", "Book_case1_small.tif")
METHODS = ("single-frame", "classical", "learned")
PEER = "vidsr"


def peer_of(stack) -> np.ndarray:
    """vidsr's image of one fold's stack (:func:`hbis_torch.validate.select_frames` of the frames
    kept): the stack's frames in [0, 1] (an RGB stack's as BT.601 luma), its reference frame
    (``stack.reference_index``, re-indexed in the fold) the one whose grid the output refines.

    Returns
    -------
    np.ndarray, shape (h H, h W), float32
    """
    from hbis_torch.reconstruct.colour import LUMA

    frames = stack.to_float().numpy()
    if frames.ndim == 4:
        frames = frames @ LUMA.astype(np.float32)
    return vidsr_peer.vidsr_sr(frames, stack.h, reference=stack.reference_index)


def run_sequence(path: Path, scale: int, holdout: int, figures: Path | None, extrapolate: bool = False,
                 peer: bool = False) -> dict:
    """Assemble, cross-validate and picture one sequence at one scale: one result row (``peer``:
    with vidsr scored by the same folds)."""
    frames, names = read_frames([path])
    start = time.process_time()
    stack, messages = assemble_burst(frames, scale, names=names)
    assemble_s = time.process_time() - start
    models = stack.meta["motion_models"]
    validation = cross_validate(stack, METHODS, holdout=holdout,
                                method_options={"learned": {"extrapolate": True}} if extrapolate else None,
                                extra_methods={PEER: peer_of} if peer else None)
    row = {"sequence": path.name, "scale": scale, "frames": len(frames), "size": list(frames.shape[1:]),
           "trusted": int((stack.confidence >= 0.5).sum()),
           "models": {m: models.count(m) for m in dict.fromkeys(models)}, "assemble_cpu_s": assemble_s,
           "assemble_messages": messages, "held_out": validation.held_out, "scored_on": validation.scored_on}
    for name, scores in validation.methods.items():
        row[name] = {"psnr_db": scores.mean_psnr, "per_frame_db": scores.psnr, "seconds": scores.seconds,
                     "messages": scores.messages}
    row["classical_gain_db"] = validation.gain("classical")
    row["learned_minus_classical_db"] = validation.gain("learned", "classical")
    if peer:
        row["classical_minus_vidsr_db"] = validation.gain("classical", PEER)
        row["learned_minus_vidsr_db"] = validation.gain("learned", PEER)
    row["learned_ran"] = learned_ran(validation.methods["learned"].messages)
    if figures is not None:
        row["figure"] = picture(stack, path.stem, scale, figures)
    return row


def learned_ran(messages: list) -> str:
    """What the learned method did, from its messages: ran the network, or returned the classical
    image (no model for the scale; noise outside the model's training range)."""
    if any("no learned model" in m for m in messages):
        return "classical (no model for S)"
    if any("training range" in m for m in messages):
        return "classical (noise outside the training range)" + (" in some runs" if not all(
            "training range" in m for m in messages if "learned method" in m) else "")
    return "network"


def picture(stack, name: str, scale: int, figures: Path) -> str:
    """The reference enlarged beside the classical and learned reconstructions from every frame,
    with a crop of each below; returns the picture's file name."""
    from matplotlib.figure import Figure

    ref = stack.to_float().numpy()[stack.reference_index]
    images = {"reference, enlarged (cubic)": single_frame(ref, scale),
              "classical": reconstruct(stack, "classical"), "learned": reconstruct(stack, "learned")}
    H, W = images["classical"].shape[:2]
    crop = (slice(H // 4, H // 4 + H // 3), slice(W // 4, W // 4 + W // 3))
    fig = Figure(figsize=(9, 6 * H / W + 0.6))
    axes = fig.subplots(2, 3)
    for col, (title, image) in enumerate(images.items()):
        cmap = None if image.ndim == 3 else "gray"
        axes[0, col].imshow(np.clip(image, 0, 1), cmap=cmap, vmin=0, vmax=1, interpolation="nearest")
        axes[0, col].set_title(title, fontsize=9)
        axes[1, col].imshow(np.clip(image[crop], 0, 1), cmap=cmap, vmin=0, vmax=1, interpolation="nearest")
        for ax in axes[:, col]:
            ax.set_axis_off()
    fig.suptitle(f"{name}: {len(stack.frames)} frames, scale {scale}", fontsize=10)
    fig.tight_layout()
    figures.mkdir(parents=True, exist_ok=True)
    out = f"real-bursts-{name}-s{scale}.png"
    fig.savefig(figures / out, dpi=80)
    return out


def table(rows: list) -> str:
    """docs/real-bursts.md's results, as Markdown (vidsr's columns where the rows have them)."""
    peer = all(PEER in r for r in rows)
    head = ["sequence", "S", "frames (trusted)", "motion models", "single frame", "classical", "learned"]
    head += [PEER] if peer else []
    head += ["classical - single", "learned - classical"]
    head += ["classical - vidsr", "learned - vidsr"] if peer else []
    head += ["learned gave", "assemble CPU s", "s per reconstruction (cl. / le." + (" / vidsr)" if peer else ")")]
    lines = ["| " + " | ".join(head) + " |", "|" + " --- |" * len(head)]
    for r in rows:
        models = ", ".join(f"{n} {m}" for m, n in r["models"].items())
        cells = [r["sequence"], r["scale"], f"{r['frames']} ({r['trusted']})", models,
                 f"{r['single-frame']['psnr_db']:.2f}", f"{r['classical']['psnr_db']:.2f}", f"{r['learned']['psnr_db']:.2f}"]
        cells += [f"{r[PEER]['psnr_db']:.2f}"] if peer else []
        cells += [f"{r['classical_gain_db']:+.2f}", f"{r['learned_minus_classical_db']:+.2f}"]
        cells += [f"{r['classical_minus_vidsr_db']:+.2f}", f"{r['learned_minus_vidsr_db']:+.2f}"] if peer else []
        seconds = [r[m]["seconds"] for m in ("classical", "learned", *([PEER] if peer else []))]
        cells += [r["learned_ran"], f"{r['assemble_cpu_s']:.1f}", " / ".join(f"{t:.2f}" for t in seconds)]
        lines.append("| " + " | ".join(str(c) for c in cells) + " |")
    return "\n".join(lines)


def summary(rows: list) -> dict:
    """Per scale: the mean and worst gains the issue's goals are about."""
    out = {}
    for scale in sorted({r["scale"] for r in rows}):
        part = [r for r in rows if r["scale"] == scale]
        gain = [r["classical_gain_db"] for r in part]
        learned = [r["learned_minus_classical_db"] for r in part]
        out[str(scale)] = {"classical_gain_mean_db": float(np.mean(gain)), "classical_gain_worst_db": float(min(gain)),
                           "learned_minus_classical_mean_db": float(np.mean(learned)),
                           "learned_minus_classical_worst_db": float(min(learned))}
        if all(PEER in r for r in part):
            for method in ("classical", "learned"):
                lead = [r[f"{method}_minus_vidsr_db"] for r in part]
                out[str(scale)].update({f"{method}_minus_vidsr_mean_db": float(np.mean(lead)),
                                        f"{method}_minus_vidsr_worst_db": float(min(lead))})
    return out


#: Where the committed results live (the docs' figures cite it).
RESULTS = "benchmarks/results/bench_real_bursts.json"


def write_doc(doc: Path, rows: list, result: dict, command: str) -> None:
    """Replace the generated part of ``doc`` (between the two markers) with the tables."""
    begin, end = "<!-- bench_real_bursts: begin -->", "<!-- bench_real_bursts: end -->"
    lines = [begin, "", f"Generated by `{command}` (PSNR in dB of the held-out frames' predictions, "
             f"{result['settings']['holdout']} frames held out one at a time; CPU seconds on one thread"
             + (f"; vidsr {result['settings']['vidsr_version']}, scored by the same folds, where it is installed"
                if result["settings"].get("vidsr") else "") + ").", "",
             f"<!-- src-table: {RESULTS} -->", table(rows), ""]
    for scale, s in result["summary"].items():
        names = ["classical_gain_mean_db", "classical_gain_worst_db", "learned_minus_classical_mean_db",
                 "learned_minus_classical_worst_db"]
        text = (f"* S = {scale}: classical - single frame {s['classical_gain_mean_db']:+.2f} dB on average, "
                f"{s['classical_gain_worst_db']:+.2f} dB at worst; learned - classical "
                f"{s['learned_minus_classical_mean_db']:+.2f} dB on average, "
                f"{s['learned_minus_classical_worst_db']:+.2f} dB at worst")
        if "classical_minus_vidsr_mean_db" in s:
            names += [f"{m}_minus_vidsr_{k}_db" for m in ("classical", "learned") for k in ("mean", "worst")]
            text += (f"; classical - vidsr {s['classical_minus_vidsr_mean_db']:+.2f} dB on average, "
                     f"{s['classical_minus_vidsr_worst_db']:+.2f} dB at worst; learned - vidsr "
                     f"{s['learned_minus_vidsr_mean_db']:+.2f} dB on average, "
                     f"{s['learned_minus_vidsr_worst_db']:+.2f} dB at worst")
        keys = [f"summary.{scale}.{k}" for k in names]
        lines.append(f"{text}<!-- src: {RESULTS}: {', '.join(keys)} -->.")
    lines += ["", "Pictures (the reference enlarged, classical, learned; a crop of each below). The benchmark draws them where it "
              "runs; they are not shipped, since the sequences carry no licence (the links work after a run):", ""]
    lines += [f"![{r['sequence']} at S = {r['scale']}](figures/{r['figure']})" for r in rows if "figure" in r]
    lines += ["", end]
    text = doc.read_text() if doc.exists() else f"# Real bursts\n\n{begin}\n{end}\n"
    head, _, rest = text.partition(begin)
    _, _, tail = rest.partition(end)
    doc.write_text(head + "\n".join(lines) + tail)


class _Parser(argparse.ArgumentParser):
    """Bad flags in one line on stderr, exit status 2."""

    def error(self, message):
        refuse(message)


def refuse(message: str):
    """One line on stderr and exit status 2 (before any work)."""
    print(f"bench_real_bursts: {message}", file=sys.stderr)
    raise SystemExit(2)


def check_args(args) -> str | None:
    """One line saying what is wrong with the arguments, or None."""
    if not args.data.is_dir():
        return f"the shared real-bursts set is not at {args.data} (it is not shipped)"
    missing = [n for n in args.sequences if not (args.data / n).is_file()]
    if missing:
        return f"no sequence {', '.join(missing)} in {args.data}"
    if any(not 1 <= s <= 8 for s in args.scales):
        return f"--scales must lie in 1..8, got {args.scales}"
    if args.holdout < 1:
        return f"--holdout must be 1 or more, got {args.holdout}"
    if args.json and not Path(args.json).resolve().parent.is_dir():
        return f"--json {args.json}: the folder does not exist"
    counts = {n: len(read_frames([args.data / n])[0]) for n in args.sequences}
    short = [f"{n} ({c} frames)" for n, c in counts.items() if args.holdout > c - 1]
    if short:
        return f"--holdout {args.holdout}: more than the frames besides the reference of {', '.join(short)}"
    return None


def main() -> None:
    parser = _Parser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=DATA)
    parser.add_argument("--scales", type=int, nargs="+", default=[2])
    parser.add_argument("--holdout", type=int, default=3)
    parser.add_argument("--sequences", nargs="+", default=list(SEQUENCES))
    parser.add_argument("--json", default=str(ROOT / "benchmarks/results/bench_real_bursts.json"))
    parser.add_argument("--doc", type=Path, default=ROOT / "docs/real-bursts.md")
    parser.add_argument("--no-figures", action="store_true")
    parser.add_argument("--extrapolate", action="store_true",
                        help="run the learned network even outside its training domain (with --no-doc)")
    parser.add_argument("--no-doc", action="store_true", help="leave docs/real-bursts.md as it is")
    parser.add_argument("--vidsr", action=argparse.BooleanOptionalAction, default=None,
                        help="score the peer vidsr by the same folds (default: where it is installed)")
    args = parser.parse_args()
    problem = check_args(args)
    if problem:
        refuse(problem)
    installed = args.vidsr is not False and vidsr_peer.available()
    if args.vidsr and not installed:
        refuse("--vidsr: vidsr is not installed (pip install vidsr)")
    if args.vidsr is None and not installed:
        print("bench_real_bursts: vidsr is not installed: its row is skipped", file=sys.stderr)
    args.vidsr = installed
    args.vidsr_version = vidsr_peer.version() if installed else None
    torch.set_num_threads(1)
    figures = None if args.no_figures else args.doc.parent / "figures"
    rows = []
    for scale in args.scales:
        for name in args.sequences:
            rows.append(run_sequence(args.data / name, scale, args.holdout, figures, args.extrapolate, args.vidsr))
            r = rows[-1]
            peer = f", vidsr {r[PEER]['psnr_db']:.2f}" if args.vidsr else ""
            print(f"{name} S={scale}: single {r['single-frame']['psnr_db']:.2f}, classical "
                  f"{r['classical']['psnr_db']:.2f}, learned {r['learned']['psnr_db']:.2f}{peer} dB; models {r['models']}",
                  flush=True)
    shown = argparse.Namespace(**{**vars(args), "doc": str(args.doc.resolve().relative_to(ROOT)) if
                                  args.doc.resolve().is_relative_to(ROOT) else str(args.doc),
                                  "data": "the shared real-bursts set (not shipped)" if args.data == DATA else str(args.data)})
    result = benchutil.finish(shown, rows, summary(rows))
    print(table(rows))
    print(result["summary"])
    if not args.no_doc:
        command = "python3 benchmarks/bench_real_bursts.py --scales " + " ".join(map(str, args.scales))
        write_doc(args.doc, rows, result, command)


if __name__ == "__main__":
    main()
