"""The design numbers docs/reproduction.md compares with the paper, in one results file.

    python benchmarks/bench_design.py [--out benchmarks/results/bench_design.json]

Runs ``hbis design --json`` (Table 1 defaults) for the three cases the page quotes: the largest
inclinations with no blind zone ("limits"), the same at a wedge angle of 1 deg ("alpha_1"), and
the prototype's inclinations, 15 / 10 deg, at h = 4 ("prototype"). Deterministic: no timing;
``tests/test_design.py`` asserts the same numbers.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import sys
from pathlib import Path

from hbis_torch.provenance import write_results

REPO = Path(__file__).resolve().parents[1]
CASES = {"limits": [], "alpha_1": ["--alpha-deg", "1"],
         "prototype": ["--varphi-h-deg", "15", "--varphi-v-deg", "10", "--h", "4"]}


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "bench_design.json")
    args = parser.parse_args(argv)
    from hbis_torch.cli import main as hbis

    results = {}
    for name, extra in CASES.items():
        printed = io.StringIO()
        with contextlib.redirect_stdout(printed):
            if hbis(["design", "--json", *extra]) != 0:
                return 1
        results[name] = {"arguments": extra, "design": json.loads(printed.getvalue())}
    write_results(args.out, results, argv=argv)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
