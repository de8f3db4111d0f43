"""Hand-held bursts at real sizes, against the truth: the project, its peer and the true motion.

    python training/eval_handheld.py --out benchmarks/results/eval_handheld.json
        [--motions translation similarity ...] [--scales 2 3 4] [--frames 8 16] [--size 640x480]
        [--no-learned] [--no-vidsr] [--rows classical learned] [--blur 0.3] [--border 4] [--full-well 5000]
        [--seed 0]

Every cell is a motion (:data:`hbis_torch.training.handheld_render.MOTIONS`) x S x F: one burst
of :func:`~hbis_torch.training.handheld_render.render_burst` (frames W x H, 16-bit, lens blur,
Poisson-Gaussian noise of about 1 %, or more with a smaller ``--full-well``: a dimmer light),
scored against its truth by PSNR (scikit-image) over the image without a border of ``--border``
LR px (4 by default: S x 4 output px). The rows:

* **bicubic**: the reference frame enlarged S times (torch, bicubic, pixel centres kept);
* **vidsr**: the peer, in its best setting for fidelity (benchmarks/peers/vidsr_peer.py; skipped
  where vidsr is not installed);
* **classical**: what ``hbis assemble --burst --scale S`` then ``hbis reconstruct --method
  classical`` do, by their library calls: :func:`~hbis_torch.capture.burst.assemble_burst` with
  its defaults, then :func:`~hbis_torch.reconstruct.registry.reconstruct` (``"classical"``);
* **classical_lens**: the same stack, the lens's blur given as a calibration would give it
  (``hbis reconstruct --psf-sigma``: the render's sigma);
* **learned**: the same stack through ``reconstruct(stack, "learned")`` (``--no-learned`` skips it);
* **oracle**: classical given the true motion: the stack built with the true homographies
  (:meth:`~hbis_torch.training.handheld_render.HandheldBurst.oracle_motions`: for the rolling
  shutter, the homography nearest the true per-row flow, as a stack holds one homography a frame),
  confidence 1, and the true gain and offset where the brightness changes (1 and 0 elsewhere).

Each finished row of each cell is written at once to ``--out`` (JSON, atomically): a run that
stops resumes where it stopped when run again with the same ``--out`` and settings, and a run
with more rows or cells adds to it. With it, the table goes to the same path with ``.md``
(``--table-only`` writes it from ``--out`` alone): each
cell's rows and which goals of the issue it misses (classical within 0.3 dB of the oracle;
classical no more than 0.3 dB behind vidsr; classical 2 dB or more over bicubic with 8 frames or
more).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
ROWS = ("bicubic", "vidsr", "classical", "classical_lens", "learned", "oracle")
#: The goals of the issue: classical within ORACLE_GAP of the oracle, never more than PEER_GAP behind
#: vidsr, at least BICUBIC_GAIN over bicubic with BICUBIC_FRAMES frames or more.
ORACLE_GAP, PEER_GAP, BICUBIC_GAIN, BICUBIC_FRAMES = 0.3, 0.3, 2.0, 8
#: The renderer's full well by default (electrons at white).
FULL_WELL_E = 5000.0


def parse_args(argv=None):
    from hbis_torch.training.handheld_render import MOTIONS

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", type=Path, required=True, help="results JSON (resumed if it exists); the table goes "
                   "beside it as .md")
    p.add_argument("--motions", nargs="+", default=list(MOTIONS), metavar="MOTION",
                   help=f"motions (default all: {', '.join(MOTIONS)})")
    p.add_argument("--scales", nargs="+", type=int, default=[2, 3, 4], help="S (default 2 3 4)")
    p.add_argument("--frames", nargs="+", type=int, default=[8, 16], help="frames per burst (default 8 16)")
    p.add_argument("--size", default="640x480", help="frame size WxH (default 640x480)")
    p.add_argument("--no-learned", action="store_true", help="skip the learned row (the slowest)")
    p.add_argument("--no-vidsr", action="store_true", help="skip the vidsr row")
    p.add_argument("--rows", nargs="+", default=list(ROWS), metavar="ROW",
                   help=f"only these rows (default all: {', '.join(ROWS)}); --no-learned and --no-vidsr still apply")
    p.add_argument("--redo", nargs="+", default=[], metavar="ROW",
                   help="run these rows again where --out holds them (after a change of the method; a stopped run "
                        "resumes); the others are run only where missing")
    p.add_argument("--blur", type=float, default=0.3, help="the lens's Gaussian sigma, LR px (default 0.3)")
    p.add_argument("--border", type=int, default=4, help="border left out of the score, LR px (default 4)")
    p.add_argument("--full-well", type=float, default=FULL_WELL_E,
                   help=f"electrons at white (default {FULL_WELL_E:g}: about 1 %% noise at mid-grey); fewer is "
                        "a dimmer light: 1000 about 2.2 %%, 200 about 5 %%")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--table-only", action="store_true", help="only write the .md table of what --out holds "
                   "(e.g. of a run still going or stopped)")
    return p.parse_args(argv)


def check_args(args) -> str | None:
    """One line saying what is wrong with the arguments, or None."""
    from hbis_torch.training.handheld_render import MOTIONS

    bad = [m for m in args.motions if m not in MOTIONS]
    if bad:
        return f"unknown motion(s) {', '.join(bad)}; choose from {', '.join(MOTIONS)}"
    bad = [r for r in args.rows + args.redo if r not in ROWS]
    if bad:
        return f"unknown row(s) {', '.join(bad)}; choose from {', '.join(ROWS)}"
    if not set(args.redo) <= set(args.rows):
        return f"--redo {' '.join(args.redo)}: rows of this run's --rows ({', '.join(args.rows)})"
    if any(not 1 <= s <= 8 for s in args.scales):
        return f"--scales must lie in 1..8, got {args.scales}"
    if any(f < 2 for f in args.frames):
        return f"--frames must be 2 or more, got {args.frames}"
    try:
        w, h = (int(x) for x in args.size.lower().split("x"))
    except ValueError:
        return f"--size must be WxH, e.g. 640x480, got {args.size!r}"
    if w < 32 or h < 32:
        return f"--size {args.size}: frames must be 32 x 32 px or more"
    if not 0 <= args.blur <= 3:
        return f"--blur must lie in 0..3 LR px, got {args.blur}"
    if not 10 <= args.full_well <= 1e6:
        return f"--full-well must lie in 10..1e6 electrons, got {args.full_well:g}"
    if not 0 <= 2 * args.border < min(w, h):
        return f"--border {args.border} leaves nothing of {args.size} frames"
    if not args.out.parent.is_dir():
        return f"--out {args.out}: the folder {args.out.parent} does not exist"
    args.width, args.height = w, h
    return None


def settings_of(args) -> dict:
    """What a resumed run must share with the file it resumes (the full well where it is not the
    default, so that the files made before it was a setting resume)."""
    settings = {"size": [args.width, args.height], "blur_sigma_px": args.blur, "border_px": args.border,
                "seed": args.seed}
    return settings if args.full_well == FULL_WELL_E else {**settings, "full_well_e": args.full_well}


def cell_key(motion: str, scale: int, frames: int) -> str:
    return f"{motion}|S={scale}|F={frames}"


def psnr(image, truth, border_lr: int, scale: int) -> float:
    """PSNR (dB, scikit-image, data range 1) of ``image`` against ``truth`` (both (S H, S W)),
    without a border of ``border_lr`` LR px."""
    from skimage.metrics import peak_signal_noise_ratio

    b = border_lr * scale
    inner = (slice(b, -b or None), slice(b, -b or None))
    return float(peak_signal_noise_ratio(np.asarray(truth, np.float64)[inner],
                                         np.clip(np.asarray(image, np.float64), 0, 1)[inner], data_range=1.0))


def bicubic(frame: np.ndarray, scale: int) -> np.ndarray:
    """The frame (H, W) or (H, W, C) uint16 enlarged S times, bicubic (torch; pixel centres
    kept), float32 (S H, S W[, C])."""
    import torch

    x = torch.from_numpy(frame.astype(np.float32) / 65535.0)
    x = x[None, None] if x.ndim == 2 else x.permute(2, 0, 1)[None]
    big = torch.nn.functional.interpolate(x, scale_factor=scale, mode="bicubic", align_corners=False)[0]
    return big[0].numpy() if frame.ndim == 2 else big.permute(1, 2, 0).numpy()


def oracle_stack(burst):
    """The burst's stack with the true motion (module docstring), validated."""
    from hbis_torch.stack_io import Stack, make_burst_meta

    F, H, W = burst.frames.shape
    motions = burst.oracle_motions()
    models = ["identity"] + ["homography"] * (F - 1)
    meta = make_burst_meta(burst.scale, (0, 0, W, H), motions, np.ones(F), models, burst.stack_gain_offset(),
                           reference_index=0, bit_depth=16)
    return Stack(np.ascontiguousarray(burst.frames), meta).validate("oracle burst")


def run_row(row: str, burst, cache: dict) -> dict:
    """One row of one cell: its image's PSNR is added by the caller; here the image, time and notes."""
    from hbis_torch.reconstruct import reconstruct

    S = burst.scale
    started = time.perf_counter()
    out: dict = {}
    if row == "bicubic":
        image = bicubic(burst.frames[0], S)
    elif row == "vidsr":
        vidsr_sr, version = _peer().vidsr_sr, _peer().version

        image = vidsr_sr(burst.frames, S)
        out["vidsr_version"] = version()
    elif row in ("classical", "classical_lens", "learned"):
        if "stack" not in cache:
            from hbis_torch.capture.burst import assemble_burst

            t = time.perf_counter()
            stack, messages = assemble_burst(burst.frames, S)
            cache["stack"], cache["assemble"] = stack, {"assemble_s": time.perf_counter() - t,
                                                        "assemble_messages": messages,
                                                        "models": list(stack.meta["motion_models"]),
                                                        "rejected": int(np.sum(stack.confidence == 0))}
            started = time.perf_counter()  # the assemble's time is its own
            out.update(cache["assemble"])
        stack = cache["stack"]
        notes: list[str] = []
        if row == "classical_lens":
            image = reconstruct(stack, "classical", messages=notes, lens_sigma=burst.blur_sigma_px)
        else:
            image = reconstruct(stack, row, messages=notes)
        out["messages"] = notes
        errors = motion_error(burst, stack.motions)
        out["frame_motion_error_px"] = [None if c == 0 else e for e, c in zip(errors, stack.confidence)]
        out["motions"] = stack.motions.tolist()
    elif row == "oracle":
        notes = []
        image = reconstruct(oracle_stack(burst), "classical", messages=notes)
        out["messages"] = notes
    else:  # pragma: no cover - checked before
        raise ValueError(row)
    out["seconds"] = time.perf_counter() - started
    out["image"] = image
    return out


def _peer():
    """benchmarks/peers/vidsr_peer.py, loaded from its path (a benchmark's module, not the package's)."""
    import importlib.util

    if "vidsr_peer" not in sys.modules:
        spec = importlib.util.spec_from_file_location("vidsr_peer", ROOT / "benchmarks" / "peers" / "vidsr_peer.py")
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        sys.modules["vidsr_peer"] = module
    return sys.modules["vidsr_peer"]


def motion_error(burst, motions: np.ndarray) -> list[float]:
    """Per frame, the largest distance (LR px), over a grid of every 16th pixel, between where the
    found motion and the true flow put the frame's pixels."""
    F, H, W = burst.frames.shape
    v, u = np.mgrid[0:H:16, 0:W:16].astype(np.float64)
    errors = [0.0]
    for k in range(1, F):
        m = motions[k]
        w = m[2, 0] * u + m[2, 1] * v + m[2, 2]
        x, y = (m[0, 0] * u + m[0, 1] * v + m[0, 2]) / w, (m[1, 0] * u + m[1, 1] * v + m[1, 2]) / w
        true = burst.flow(k)[0:H:16, 0:W:16]
        errors.append(float(np.hypot(x - true[..., 0], y - true[..., 1]).max()))
    return errors


def provenance(argv, script: str = "training/eval_handheld.py") -> dict:
    """Command, commit, dirty, date, machine of this run (hbis_torch.provenance's where it exists)."""
    try:
        import hbis_torch.provenance as shared
    except ImportError:
        shared = None
    # only this checkout's own: an installed checkout's module describes that checkout's git state
    if shared is not None and ROOT in Path(shared.__file__).resolve().parents:
        return shared.provenance(argv=list(argv))
    import datetime
    import platform
    import subprocess

    def git(*a):
        try:
            return subprocess.run(["git", "-C", str(ROOT), *a], capture_output=True, text=True, timeout=30).stdout.strip()
        except (OSError, subprocess.SubprocessError):
            return ""
    import os

    return {"command": f"python {script} " + " ".join(argv), "commit": git("rev-parse", "HEAD"),
            "dirty": bool(git("status", "--porcelain", "--untracked-files=no")),
            "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
            "machine": f"{_cpu_name() or platform.machine()}, {os.cpu_count()} CPUs (shared with other jobs), "
                       f"{platform.system()} {platform.release()}",
            "python": platform.python_version()}


def _cpu_name() -> str | None:
    try:
        with open("/proc/cpuinfo") as f:
            return next((line.split(":", 1)[1].strip() for line in f if line.startswith("model name")), None)
    except OSError:
        return None


def _machine(p: dict) -> str:
    m = p.get("machine", "")
    return m if isinstance(m, str) else f"{m.get('cpu')}, {m.get('cores')} cores"


def load_results(args) -> tuple[dict | None, str | None]:
    """(the results so far in ``--out`` (resumed) or a fresh record, None), or (None, one line
    saying why the file cannot be resumed: not this script's, or other settings)."""
    fresh = {"settings": settings_of(args), "provenance": [], "cells": {}}
    if not args.out.exists():
        return fresh, None
    try:
        old = json.loads(args.out.read_text())
        settings = old.get("settings")
    except (OSError, ValueError, AttributeError) as exc:
        return None, f"--out {args.out} exists but is not a results file of this script ({exc})"
    if settings != settings_of(args):
        return None, f"--out {args.out} holds a run with other settings ({settings}); give another --out to start afresh"
    return old, None


def runs_with(runs, this: dict) -> list:
    """The provenance list of a results file a ``--redo`` run adds to: its runs (one dict in a file
    that held one) and this run, unless the last is this run's own command at this commit (a
    stopped run resumed)."""
    runs = runs if isinstance(runs, list) else [runs]
    if runs and runs[-1].get("command") == this["command"] and runs[-1].get("commit") == this["commit"]:
        return runs
    return [*runs, this]


def _refuse(line: str) -> int:
    print(f"eval_handheld: {line}", file=sys.stderr)
    return 2


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    args = parse_args(argv)
    problem = check_args(args)
    if problem:
        return _refuse(problem)
    if args.table_only:
        if not args.out.exists():
            return _refuse(f"--out {args.out} does not exist")
        write_table(args.out, json.loads(args.out.read_text()), argv)
        return 0
    rows = [r for r in ROWS if r in args.rows and not (r == "learned" and args.no_learned)
            and not (r == "vidsr" and args.no_vidsr)]
    if "vidsr" in rows:
        available = _peer().available

        if not available():
            print("eval_handheld: vidsr is not installed: its row is skipped", file=sys.stderr)
            rows.remove("vidsr")
    results, problem = load_results(args)
    if problem:
        return _refuse(problem)
    this, runs = provenance(argv), results["provenance"]
    results["provenance"] = runs = runs_with(runs, this) if args.redo else [*runs, this]
    run = len(runs) - 1
    from hbis_torch.io_utils import atomic_write_text
    from hbis_torch.training.handheld_render import render_burst

    def save():
        atomic_write_text(args.out, json.dumps(results, indent=1) + "\n")

    for S in args.scales:
        for F in args.frames:
            for motion in args.motions:
                key = cell_key(motion, S, F)
                cell = results["cells"].setdefault(key, {"motion": motion, "scale": S, "frames": F, "rows": {}})
                todo = [r for r in rows
                        if r not in cell["rows"] or (r in args.redo and cell["rows"][r].get("run") != run)]
                if not todo:
                    continue
                t = time.perf_counter()
                burst = render_burst(motion, S, F, args.width, args.height, blur_sigma_px=args.blur,
                                     full_well_e=args.full_well, seed=args.seed)
                cell["render_s"] = time.perf_counter() - t
                cache: dict = {}
                for row in todo:
                    got = run_row(row, burst, cache)
                    got["psnr_db"] = psnr(got.pop("image"), burst.truth, args.border, S)
                    got["run"] = run
                    cell["rows"][row] = got
                    save()
                    write_table(args.out, results, argv)
                    print(f"{key:32s} {row:9s} {got['psnr_db']:6.2f} dB  {got['seconds']:6.1f} s", flush=True)
    results["summary"] = summary(results)
    save()
    write_table(args.out, results, argv)
    print(f"wrote {args.out} and {args.out.with_suffix('.md')}")
    return 0


def write_table(out: Path, results: dict, argv) -> None:
    """The Markdown table beside the JSON ``out``, under a provenance header (the runs behind each
    row are listed in it too)."""
    from hbis_torch.provenance import write_results

    write_results(out.with_suffix(".md"), table(results), argv=argv)


def summary(results: dict) -> dict:
    """Per S and frame count: each row's mean PSNR over the motions, the gaps the issue's goals
    speak of (classical minus the oracle, vidsr and bicubic: mean and worst cell) and how many
    cells miss a goal; keyed ``"S=2|F=16"``."""
    out = {}
    cells = list(results["cells"].values())
    for S, F in sorted({(c["scale"], c["frames"]) for c in cells}):
        group = [c for c in cells if c["scale"] == S and c["frames"] == F]
        entry = {"cells": len(group), "missing_a_goal": sum(bool(misses(c)) for c in group), "mean_db": {}}
        for row in ROWS:
            values = [c["rows"][row]["psnr_db"] for c in group if row in c["rows"]]
            if values:
                entry["mean_db"][row] = float(np.mean(values))
        for row in ("classical", "classical_lens"):
            for other in ("oracle", "vidsr", "bicubic"):
                gaps = [c["rows"][row]["psnr_db"] - c["rows"][other]["psnr_db"] for c in group
                        if row in c["rows"] and other in c["rows"]]
                if gaps:
                    entry[f"{row}_minus_{other}"] = {"mean_db": float(np.mean(gaps)), "worst_db": float(np.min(gaps))}
        learned = learned_against_classical(group)
        if learned:
            entry["learned_minus_classical"] = learned
        out[f"S={S}|F={F}"] = entry
    return out


def learned_against_classical(group: list[dict]) -> dict | None:
    """Over the cells that have both rows: learned minus classical (dB; mean, worst cell) and
    the learned row's time over the classical row's (the classical row's ``seconds`` are its
    reconstruct's alone, as the learned row's: the assemble is the stack's, shared), mean and
    worst; None without such cells. The issue's goals: +0.3 dB on the mean, -0.3 dB or more in
    every cell, at most 3 times the time."""
    both = [c["rows"] for c in group if "learned" in c["rows"] and "classical" in c["rows"]]
    if not both:
        return None
    gaps = [r["learned"]["psnr_db"] - r["classical"]["psnr_db"] for r in both]
    ratios = [r["learned"]["seconds"] / max(r["classical"]["seconds"], 1e-9) for r in both]
    return {"cells": len(both), "mean_db": float(np.mean(gaps)), "worst_db": float(np.min(gaps)),
            "time_ratio_mean": float(np.mean(ratios)), "time_ratio_worst": float(np.max(ratios))}


def misses(cell: dict) -> list[str]:
    """The goals of the issue that the cell's classical row misses."""
    r = {k: v["psnr_db"] for k, v in cell["rows"].items()}
    out = []
    if "classical" not in r:
        return out
    c = r["classical"]
    if "oracle" in r and c < r["oracle"] - ORACLE_GAP:
        out.append(f"oracle {c - r['oracle']:+.2f}")
    if "vidsr" in r and c < r["vidsr"] - PEER_GAP:
        out.append(f"vidsr {c - r['vidsr']:+.2f}")
    if "bicubic" in r and cell["frames"] >= BICUBIC_FRAMES and c < r["bicubic"] + BICUBIC_GAIN:
        out.append(f"bicubic {c - r['bicubic']:+.2f}")
    return out


def table(results: dict) -> str:
    """The results as a Markdown page: provenance, settings, one table per (S, F), goals missed."""
    s = results["settings"]
    lines = ["# Hand-held bursts against the truth (training/eval_handheld.py)", "",
             f"Frames {s['size'][0]} x {s['size'][1]}, 16-bit, lens blur sigma {s['blur_sigma_px']} LR px, "
             f"Poisson-Gaussian noise ({s.get('full_well_e', FULL_WELL_E):g} e- full well, 3 e- read), "
             f"seed {s['seed']}; PSNR (dB) against the truth without a border of {s['border_px']} LR px. "
             "hbis_torch/training/handheld_render.py renders the bursts; training/eval_handheld.py's docstring says what each row is. A cell misses a goal of the "
             f"issue where classical is more than {ORACLE_GAP} dB below the oracle, more than {PEER_GAP} dB "
             f"below vidsr, or (with {BICUBIC_FRAMES} frames or more) less than {BICUBIC_GAIN} dB above bicubic.",
             "", "## Provenance", ""]
    for i, p in enumerate(results["provenance"]):
        lines.append(f"- run {i}: `{p['command']}`, commit {p['commit'][:10]}{' (dirty)' if p['dirty'] else ''}, "
                     f"{p['date']}, {_machine(p)}")
    cells = list(results["cells"].values())
    for S, F in sorted({(c["scale"], c["frames"]) for c in cells}):
        group = [c for c in cells if c["scale"] == S and c["frames"] == F]
        present = [r for r in ROWS if any(r in c["rows"] for c in group)]
        lines += ["", f"## S = {S}, {F} frames", "",
                  "| motion | " + " | ".join(present) + " | classical: frames rejected, models | misses |",
                  "|---" * (len(present) + 3) + "|"]
        for c in group:
            vals = [f"{c['rows'][r]['psnr_db']:.2f}" if r in c["rows"] else "" for r in present]
            cl = c["rows"].get("classical", {})
            models = cl.get("models", [])
            counted = ", ".join(f"{models.count(m)} {m}" for m in dict.fromkeys(models) if m != "identity")
            how = f"{cl.get('rejected', '')} rejected; {counted}" if cl else ""
            kept = [e for e in cl.get("frame_motion_error_px", []) if e is not None]
            if kept:
                how += f"; worst kept frame's motion off by {max(kept):.2f} px"
            lines.append(f"| {c['motion']} | " + " | ".join(vals) + f" | {how} | {'; '.join(misses(c)) or '-'} |")
        whole = [c for c in group if all(r in c["rows"] for r in present)]  # the mean over the same cells
        if whole:
            means = [np.mean([c["rows"][r]["psnr_db"] for c in whole]) for r in present]
            lines.append(f"| **mean** ({len(whole)} cells with every row) | " + " | ".join(f"{m:.2f}" for m in means)
                         + " | | |")
        lost = [c for c in group if misses(c)]
        lines += ["", f"{len(lost)} of {len(group)} cells miss a goal."]
        learned = learned_against_classical(group)
        if learned:
            lines.append(f"Learned - classical over the {learned['cells']} cells with both: {learned['mean_db']:+.2f} dB "
                         f"on the mean, {learned['worst_db']:+.2f} dB in the worst cell; learned's time "
                         f"{learned['time_ratio_mean']:.1f} x classical's on the mean, {learned['time_ratio_worst']:.1f} x "
                         "at worst (the goals: +0.3, -0.3 and 3 x).")
        timed = {r: np.mean([c["rows"][r]["seconds"] for c in group if r in c["rows"]]) for r in present}
        lines.append("Mean seconds a cell (a busy shared machine; benchmarks/bench_handheld.py times them properly): "
                     + ", ".join(f"{r} {t:.1f}" for r, t in timed.items())
                     + (f", classical's assemble {np.mean([c['rows']['classical']['assemble_s'] for c in group if 'classical' in c['rows']]):.1f}"
                        if "classical" in present else "") + ".")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    raise SystemExit(main())
