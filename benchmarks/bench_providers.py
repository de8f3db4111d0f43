"""Time one shipped SR model in each runtime installed here, side by side in one run.

The runtimes are those of :class:`hbis_torch.reconstruct.learned.LearnedSR`: ``cpu``
(onnxruntime's own CPU kernels, the default install) and ``openvino`` (the ``openvino``
package's own ONNX reader, ``pip install 'hbis-torch[openvino]'``; or onnxruntime's OpenVINO
execution provider where the installed onnxruntime is Intel's build). Each timed call is one
network pass on a random ``--size`` x ``--size`` LR input, after a warm-up, each after a 0.2 s
pause; the runtimes take turns call by call, so that a change in the machine's load touches both.
Prints one JSON line per runtime (versions, median and least milliseconds) and the ratio.

    python benchmarks/bench_providers.py --h 4 --size 256 --repeats 15 --threads 2
"""

from __future__ import annotations

import argparse
import json
import time
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

import numpy as np

from hbis_torch.provenance import run_recorded
from hbis_torch.reconstruct.learned import LearnedSR, available_providers, default_model_path


def _version(name: str) -> str | None:
    try:
        return version(name)
    except PackageNotFoundError:
        return None


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--h", type=int, default=4, help="the shipped model's factor")
    parser.add_argument("--size", type=int, default=256, help="LR side of the square input (one pass)")
    parser.add_argument("--repeats", type=int, default=15)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--out", type=Path, default=None,
                        help="also write what is printed to this file (.txt/.md, or .json), with its provenance")
    args = parser.parse_args(argv)
    return run_recorded("bench_providers", measure, args, argv)


def measure(args):
    """Run the benchmark and print its result."""
    runners = {p: LearnedSR(default_model_path(args.h), threads=args.threads, provider=p) for p in available_providers()}
    h = args.h
    rng = np.random.default_rng(0)
    frames = rng.random((1, h * h, args.size, args.size), dtype=np.float32)  # the classical image's phases
    offsets = rng.random((1, 1, args.size, args.size), dtype=np.float32)  # the noise map
    outputs = {p: r.infer(frames, offsets) for p, r in runners.items()}  # warm-up
    times = {p: [] for p in runners}
    for _ in range(args.repeats):
        for p, r in runners.items():
            time.sleep(0.2)
            t0 = time.perf_counter()
            r.infer(frames, offsets)
            times[p].append(time.perf_counter() - t0)
    versions = {"onnxruntime": _version("onnxruntime"), "onnxruntime-openvino": _version("onnxruntime-openvino"),
                "openvino": _version("openvino")}
    for p, t in times.items():
        print(json.dumps({"runtime": p, "h": h, "size": args.size, "threads": args.threads, "repeats": args.repeats,
                          "median_ms": round(1e3 * float(np.median(t)), 1), "least_ms": round(1e3 * min(t), 1),
                          **versions}))
    if len(times) == 2:
        ratio = float(np.median(times["cpu"]) / np.median(times["openvino"]))
        diff = float(np.abs(outputs["cpu"] - outputs["openvino"]).max())
        print(json.dumps({"speed_up_openvino_over_cpu_median": round(ratio, 2), "max_abs_diff": diff}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
