"""How fast ``hbis`` starts, against ``import torch``, side by side in one run.

Each round runs, in fresh interpreters and in turn: ``python -c "import torch"``,
``python -m hbis_torch --help`` and ``python -m hbis_torch <command> --help`` for every
subcommand. Prints the median and least wall time of each over the rounds, and each one's
ratio to ``import torch`` (the goal: ``hbis --help`` <= 0.5x). Run from the repository root:

    python benchmarks/bench_cli_start.py --rounds 7
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import time
from pathlib import Path

from hbis_torch.cli import COMMANDS
from hbis_torch.provenance import run_recorded


def _time(argv: list[str]) -> float:
    t0 = time.perf_counter()
    subprocess.run(argv, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return time.perf_counter() - t0


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=7)
    parser.add_argument("--out", type=Path, default=None,
                        help="also write what is printed to this file (.txt/.md, or .json), with its provenance")
    args = parser.parse_args(argv)
    return run_recorded("bench_cli_start", measure, args, argv)


def measure(args):
    """Run the benchmark and print its result."""
    py = sys.executable
    cases = {"import torch": [py, "-c", "import torch"], "hbis --help": [py, "-m", "hbis_torch", "--help"]}
    cases.update({f"hbis {c} --help": [py, "-m", "hbis_torch", c, "--help"] for c in COMMANDS})
    times: dict[str, list[float]] = {name: [] for name in cases}
    for name, command in cases.items():  # warm the file cache
        _time(command)
    for _ in range(args.rounds):
        for name, command in cases.items():
            times[name].append(_time(command))
    torch_median = statistics.median(times["import torch"])
    rows = []
    for name, values in times.items():
        median = statistics.median(values)
        rows.append({"case": name, "median_s": round(median, 3), "least_s": round(min(values), 3),
                     "ratio_to_import_torch": round(median / torch_median, 3)})
        print(f"{name:28s} median {median:6.3f} s  least {min(values):6.3f} s  x{median / torch_median:5.2f}")
    print(json.dumps({"rounds": args.rounds, "results": rows}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
