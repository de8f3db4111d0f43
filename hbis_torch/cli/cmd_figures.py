"""``hbis figures``: draw the paper's figures as PNG files."""

from __future__ import annotations

import importlib
import pkgutil
from pathlib import Path

from hbis_torch import figures
from hbis_torch.cli.common import add_system_args, system_from_args

# Every module hbis_torch/figures/<set>_figures.py with a function
# make_figures(out_dir, system) -> list[Path] is one figure set, found automatically.
FIGURE_SETS = {
    m.name[: -len("_figures")]: importlib.import_module(f"{figures.__name__}.{m.name}").make_figures
    for m in pkgutil.iter_modules(figures.__path__)
    if m.name.endswith("_figures")
}


def register(sub) -> None:
    p = sub.add_parser(
        "figures",
        help="draw the paper's figures (4, 6, 10 and more) as PNG files",
        description="Reproduce the paper's figures with matplotlib. Sets: " + ", ".join(FIGURE_SETS),
    )
    add_system_args(p)
    p.add_argument("--out", default="figures", help="output folder (default: ./figures)")
    p.add_argument("--only", choices=sorted(FIGURE_SETS), action="append",
                   help="draw only this set (repeatable; default: all)")
    p.set_defaults(func=run)


def run(args) -> int:
    system = system_from_args(args)
    for name in args.only or list(FIGURE_SETS):
        for path in FIGURE_SETS[name](Path(args.out), system):
            print(path)
    return 0
