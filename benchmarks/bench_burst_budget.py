"""Peak memory and time of hand-held bursts through the hbis program, beside its up-front estimates.

    python benchmarks/bench_burst_budget.py [--cases 640x480:grey:2:classical 4000x3000:rgb:2:classical ...]
        [--threads 1] [--cache DIR] [--json benchmarks/results/bench_burst_budget.json]

Each case is SIZE:grey|rgb|raw:S:METHOD. Its burst (:func:`hbis_torch.training.handheld_render.render_burst`,
motion ``translation``, 16 frames, seed 0; an RGB burst's channels the grey frames times
bench_handheld.py's ``COLOUR_GAINS``) is written as a multi-page TIFF (a raw burst as 16 DNG files of an
RGGB mosaic, 12 bits over a black level of 256, as benchmarks/bench_raw_burst.py makes it; its output is
RGB at S times the mosaic's size), then ``hbis assemble --burst --scale S``
and ``hbis reconstruct --method METHOD`` run as a user runs them: ``python -m hbis_torch`` in a
fresh process each (so the program's own settings apply, glibc's malloc and the decoding limit
among them), with ``--force`` (so that an estimate too large cannot stop the measurement). Each
process's peak resident set (``ru_maxrss``, read in the process at its end) and wall seconds are
printed beside :mod:`hbis_torch.budget`'s estimates for
the same job (:func:`~hbis_torch.budget.estimate_assemble_burst`,
:func:`~hbis_torch.budget.estimate_reconstruct_burst`) and the ratio estimated / measured, which
the estimates are meant to keep between about 0.7 and 2 (they tell 1 GB from 40 GB before any
work, not the nearest 10 %), and what the scan stack's terms, which bursts were estimated by
before they had their own, said of the reconstruct. ``--threads`` sets OMP_NUM_THREADS (default 1: the memory does not
depend on it, and one thread keeps the seconds from a busy machine's contention).

``--cache DIR`` keeps the rendered bursts (a 12 MP one takes a minute or two to render).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_CASES = ("640x480:grey:2:classical", "640x480:grey:2:learned", "640x480:grey:4:classical",
                 "640x480:grey:4:learned", "640x480:rgb:2:classical", "640x480:rgb:2:learned",
                 "640x480:rgb:4:classical", "4000x3000:grey:2:classical", "4000x3000:rgb:2:classical")
FRAMES = 16
METHODS = ("classical", "learned")
# Runs one hbis command line in this process as the hbis program does (python -m hbis_torch),
# then prints its peak resident set and seconds.
_CHILD = """
import resource, runpy, sys, time
sys.argv = ["hbis", *sys.argv[1:]]
t = time.perf_counter()
try:
    runpy.run_module("hbis_torch", run_name="__main__")
    code = 0
except SystemExit as exc:
    code = exc.code or 0
print("RESULT", code, time.perf_counter() - t, resource.getrusage(resource.RUSAGE_SELF).ru_maxrss, flush=True)
"""


KINDS = ("grey", "rgb", "raw")
BLACK, WHITE = 256, 4095  # a raw burst's levels (12 bits in a 16-bit container)


def parse_case(text: str) -> tuple[int, int, str, int, str]:
    """SIZE:grey|rgb|raw:S:METHOD -> (width, height, kind, S, method); ValueError if malformed."""
    size, kind, scale, method = text.split(":")
    width, height = (int(v) for v in size.lower().split("x"))
    if min(width, height) < 64 or kind not in KINDS or int(scale) not in (2, 3, 4) or method not in METHODS:
        raise ValueError(text)
    return width, height, kind, int(scale), method


def burst_files(folder: Path, width: int, height: int, kind: str) -> list[Path]:
    """The burst's files in ``folder`` (one TIFF; a raw burst's DNGs), made where they are not there yet."""
    if kind == "raw":
        frames = folder / f"budget_translation_{width}x{height}_F{FRAMES}_raw"
        if not frames.exists():
            grey = burst_files(folder, width, height, "grey")[0]
            code = ("import sys, numpy as np, tifffile; from pathlib import Path\n"
                    "from hbis_torch.capture.dng import write_mosaic_dng\n"
                    "out = Path(sys.argv[2] + '.part'); out.mkdir()\n"
                    "for k, page in enumerate(tifffile.TiffFile(sys.argv[1]).pages):\n"
                    "    frame = page.asarray()\n"
                    f"    mosaic = np.round({BLACK} + frame.astype(np.float32) * (({WHITE} - {BLACK}) / 65535))\n"
                    f"    write_mosaic_dng(out / f'f{{k:02d}}.dng', mosaic.astype(np.uint16), 'RGGB',\n"
                    f"                     {BLACK}, {WHITE})\n"
                    "out.rename(sys.argv[2])\n")
            subprocess.run([sys.executable, "-c", code, str(grey), str(frames)], check=True, env=_env())
        return sorted(frames.glob("*.dng"))
    colour = kind == "rgb"
    path = folder / f"budget_translation_{width}x{height}_F{FRAMES}{'_rgb' * colour}.tif"
    if not path.exists():
        from bench_handheld import COLOUR_GAINS  # benchmarks/ is the script's folder: its colour bursts

        code = ("import sys, numpy as np, tifffile; from hbis_torch.training.handheld_render import render_burst\n"
                f"f = render_burst('translation', 2, {FRAMES}, {width}, {height}, seed=0).frames\n"
                "with tifffile.TiffWriter(sys.argv[1] + '.part', bigtiff=True) as w:\n"
                "    for frame in f:\n"
                f"        w.write(np.round(frame[..., None] * np.array({COLOUR_GAINS})).astype(np.uint16) "
                f"if {colour} else frame, photometric={'rgb' if colour else 'minisblack'!r})\n")
        subprocess.run([sys.executable, "-c", code, str(path)], check=True, env=_env())
        Path(str(path) + ".part").rename(path)
    return [path]


def _env(threads: int | None = None) -> dict:
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])))
    if threads:
        env["OMP_NUM_THREADS"] = str(threads)
    return env


def run_hbis(argv: list[str], threads: int) -> dict:
    """One hbis command line in a fresh process: its exit code, seconds and peak RSS (MiB)."""
    done = subprocess.run([sys.executable, "-c", _CHILD, *argv], capture_output=True, text=True, env=_env(threads))
    line = [x for x in done.stdout.splitlines() if x.startswith("RESULT ")]
    if not line:
        return {"failed": done.stderr.strip().splitlines()[-1:]}
    _, code, seconds, peak_kb = line[-1].split()
    out = {"exit_code": int(code), "seconds": float(seconds), "peak_rss_mib": int(peak_kb) / 1024}
    if int(code) != 0:
        out["stderr"] = done.stderr.strip().splitlines()[-1:]
    return out


def run_case(case: str, folder: Path, work: Path, threads: int) -> dict:
    """Assemble and reconstruct one case's burst; measured and estimated, side by side."""
    from hbis_torch.budget import estimate_assemble_burst, estimate_reconstruct, estimate_reconstruct_burst

    width, height, kind, scale, method = parse_case(case)
    frames = burst_files(folder, width, height, kind)
    stack, image = work / "stack.tif", work / "image.tif"
    channels = 3 if kind == "rgb" else 1
    row = {"case": case, "frames": FRAMES, "width": width, "height": height, "channels": channels, "scale": scale,
           "method": method, "raw": kind == "raw"}
    row["assemble"] = run_hbis(["assemble", "--burst", *map(str, frames), "--scale", str(scale), "--out", str(stack),
                                "--overwrite", "--force", "-q"], threads)
    row["reconstruct"] = run_hbis(["reconstruct", str(stack), "--method", method, "--out", str(image), "--overwrite",
                                   "--force", "-q"], threads)
    pixels = FRAMES * width * height
    estimates = {"assemble": estimate_assemble_burst(pixels * channels * 2, pixels),
                 "reconstruct": estimate_reconstruct_burst(FRAMES, width, height, channels, scale, method,
                                                           raw=kind == "raw")}
    # what the scan stack's terms, which every stack was estimated by before bursts had their own, said
    as_scan = estimate_reconstruct(FRAMES, width, height, channels)
    row["reconstruct"]["as_scan_estimated_mib"] = as_scan.memory_bytes / 2**20
    for step, estimate in estimates.items():
        measured = row[step]
        measured["estimated_mib"] = estimate.memory_bytes / 2**20
        measured["estimated_s"] = estimate.seconds
        if "peak_rss_mib" in measured:
            measured["memory_estimated_over_measured"] = measured["estimated_mib"] / measured["peak_rss_mib"]
            measured["time_estimated_over_measured"] = estimate.seconds / measured["seconds"]
    return row


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0], epilog=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--cases", nargs="+", default=list(DEFAULT_CASES), help="SIZE:grey|rgb|raw:S:METHOD (default: "
                   "640 x 480 grey and RGB at S = 2 and 4, both methods; 4000 x 3000 grey and RGB, classical, S = 2)")
    p.add_argument("--threads", type=int, default=1, help="OMP_NUM_THREADS of the hbis processes (default 1)")
    p.add_argument("--cache", type=Path, help="folder that keeps the rendered bursts")
    p.add_argument("--json", type=Path, help="results file")
    args = p.parse_args(argv)
    problem = None
    for case in args.cases:
        try:
            parse_case(case)
        except ValueError:
            problem = (f"--cases {case!r}: give SIZE:grey|rgb|raw:S:METHOD (64 px or more, S 2 to 4, classical or "
                       "learned)")
            break
    if problem is None and args.threads < 1:
        problem = "--threads takes 1 or more"
    elif problem is None and args.cache is not None and not args.cache.is_dir():
        problem = f"--cache {args.cache}: the folder does not exist"
    elif problem is None and args.json is not None and not args.json.parent.is_dir():
        problem = f"--json {args.json}: the folder does not exist"
    if problem:
        print(f"bench_burst_budget: {problem}", file=sys.stderr)
        return 2
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        folder = args.cache or Path(tmp)
        for case in args.cases:
            started = time.perf_counter()
            row = run_case(case, folder, Path(tmp), args.threads)
            row["case_s"] = time.perf_counter() - started
            rows.append(row)
            print(line(row), flush=True)
    if args.json is not None:
        from hbis_torch.provenance import write_results

        write_results(args.json, {"rows": rows, "threads": args.threads},
                      argv=sys.argv[1:] if argv is None else argv)
    return 0


def line(row: dict) -> str:
    """One case: each step's peak and seconds, measured and estimated."""
    parts = [row["case"]]
    for step in ("assemble", "reconstruct"):
        r = row[step]
        if "peak_rss_mib" not in r:
            parts.append(f"{step} failed: {r.get('failed')}")
            continue
        parts.append(f"{step} {r['peak_rss_mib']:.0f} MiB (estimated {r['estimated_mib']:.0f}) in {r['seconds']:.1f} s "
                     f"(estimated {r['estimated_s']:.0f})")
    return "; ".join(parts)


if __name__ == "__main__":
    raise SystemExit(main())
