"""The two tiers of the learned method, end to end: ``--model fast`` against ``--model best``.

    python benchmarks/bench_tiers.py                  # h = 4, 256 x 256, 5 rounds
    python benchmarks/bench_tiers.py --h 2 4 7 --repeats 3

The stack is what ``hbis simulate --scene camera --h H`` writes (its default 256 x 256 ROI), made
once into ``--work`` with its ground truth. Each measurement runs in a fresh Python process, the
methods in turn within each round, ``--repeats`` rounds; the table gives medians of the end-to-end
time as ``hbis reconstruct --method M [--model T]`` spends it (read the stack,
:func:`hbis_torch.reconstruct.reconstruct` with registration "auto", write the TIFF; the
interpreter's start and imports are not in it), its CPU seconds (user + system, all threads), and
the PSNR of the output against the truth. Both tiers run at both precisions (``--precision fp32``
and ``int8``, the int8 files of export/quantize_int8.py); the ratio best / fast at each precision is
measured side by side in the same run (the goal: at most 2.5 at h = 4, both in int8). Writes ``--out`` (Markdown).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
ROWS = (("classical", None, None), ("learned", "fast", "fp32"), ("learned", "best", "fp32"),
        ("learned", "fast", "int8"), ("learned", "best", "int8"))  # method, --model, --precision

CHILD = r"""
import json, sys, time
method, tier, precision, stack_path, out_path = sys.argv[1:6]
import tifffile
from hbis_torch.stack_io import read_stack
from hbis_torch.reconstruct.registry import reconstruct
kw = {} if tier == "-" else {"model": tier, "precision": precision}
t0, c0 = time.perf_counter(), time.process_time()
image = reconstruct(read_stack(stack_path), method=method, registration="auto", **kw)
tifffile.imwrite(out_path, image, photometric="minisblack")
print(json.dumps({"seconds": time.perf_counter() - t0, "cpu_seconds": time.process_time() - c0}))
"""


def env() -> dict:
    e = dict(os.environ)
    e["PYTHONPATH"] = str(REPO) + os.pathsep + e.get("PYTHONPATH", "")
    return e


def stack_for(work: Path, h: int) -> tuple[Path, Path]:
    stack, truth = work / f"camera_h{h}_256.tif", work / f"camera_h{h}_256_truth.tif"
    if not (stack.exists() and truth.exists()):
        work.mkdir(parents=True, exist_ok=True)
        subprocess.run([sys.executable, "-m", "hbis_torch", "simulate", "--scene", "camera", "--h", str(h),
                        "--out", str(stack), "--truth", str(truth), "--overwrite"], check=True, cwd=REPO,
                       env=env())
    return stack, truth


def measure(method: str, tier: str | None, precision: str | None, stack: Path, out: Path) -> dict:
    done = subprocess.run([sys.executable, "-c", CHILD, method, tier or "-", precision or "-", str(stack), str(out)],
                          cwd=REPO, env=env(), capture_output=True, text=True)
    if done.returncode != 0:
        raise RuntimeError(f"{method} {tier} failed:\n{done.stderr}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--h", type=int, nargs="+", default=[4], choices=[2, 4, 7])
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--work", type=Path, default=Path("/tmp/hbis_bench_tiers"))
    p.add_argument("--out", type=Path, default=None, help="write the table here (Markdown)")
    args = p.parse_args(argv)
    import numpy as np
    import tifffile

    from hbis_torch.metrics import psnr

    lines = [f"Load average {os.getloadavg()[0]:.1f} at the start; {os.cpu_count()} CPUs; medians of "
             f"{args.repeats} rounds, each measurement in its own process.", "",
             "| h | method | e2e s | CPU s | PSNR dB |", "| --- | --- | ---: | ---: | ---: |"]
    ratios = []
    for h in args.h:
        stack, truth_path = stack_for(args.work, h)
        truth = tifffile.imread(truth_path)
        runs = {row: [] for row in ROWS}
        for _ in range(args.repeats):
            for method, tier, precision in ROWS:
                out = args.work / f"out_h{h}_{method}_{tier}_{precision}.tif"
                runs[method, tier, precision].append(measure(method, tier, precision, stack, out))
        med = {}
        for (method, tier, precision), rs in runs.items():
            image = tifffile.imread(args.work / f"out_h{h}_{method}_{tier}_{precision}.tif")
            med[tier, precision] = m = [statistics.median(r[k] for r in rs) for k in ("seconds", "cpu_seconds")]
            name = method if tier is None else f"{method} --model {tier} --precision {precision}"
            lines.append(f"| {h} | {name} | {m[0]:.2f} | {m[1]:.2f} | "
                         f"{psnr(np.clip(image, 0, 1), truth):.2f} |")
        for precision in ("fp32", "int8"):
            best, fast = med["best", precision], med["fast", precision]
            ratios.append(f"h = {h}, {precision}: best / fast end to end {best[0] / fast[0]:.2f}x "
                          f"(CPU {best[1] / fast[1]:.2f}x)")
    lines += [""] + ratios
    text = "\n".join(lines) + "\n"
    print(text)
    if args.out is not None:
        from hbis_torch.provenance import write_results

        write_results(args.out, text, argv=argv)
    return 0


if __name__ == "__main__":
    sys.exit(main())
