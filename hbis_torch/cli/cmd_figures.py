"""``hbis figures``: draw the paper's figures as PNG files."""

from __future__ import annotations

import importlib
import pkgutil
from pathlib import Path

from hbis_torch import figures
from hbis_torch.cli.common import add_system_args, system_from_args

# The figure sets by name, from the module names alone: a set's module (matplotlib, torch) is
# imported only when it is drawn (figure_set).
FIGURE_SET_NAMES = sorted(m.name[: -len("_figures")] for m in pkgutil.iter_modules(figures.__path__)
                          if m.name.endswith("_figures"))


def figure_set(name: str):
    """The ``make_figures(out_dir, system, ...)`` function of figure set ``name``."""
    return importlib.import_module(f"{figures.__name__}.{name}_figures").make_figures

# Every module hbis_torch/figures/<set>_figures.py with a function
# make_figures(out_dir, system) -> list[Path] is one figure set, found automatically.


def register(sub) -> None:
    p = sub.add_parser(
        "figures",
        help="draw the paper's figures (4, 6, 10 and more) as PNG files",
        description="Reproduce the paper's figures with matplotlib. Sets: " + ", ".join(FIGURE_SET_NAMES),
    )
    add_system_args(p)
    p.add_argument("--out", default="figures", help="output folder (default: ./figures)")
    p.add_argument("--only", choices=FIGURE_SET_NAMES, action="append",
                   help="draw only this set (repeatable; default: all)")
    p.set_defaults(func=run)


def run(args) -> int:
    from hbis_torch.io_utils import check_output_dir
    from hbis_torch.progress import progress_enabled

    check_output_dir(args.out)
    system = system_from_args(args)
    for name in args.only or FIGURE_SET_NAMES:
        for path in figure_set(name)(Path(args.out), system, progress=progress_enabled()):
            print(path)
    return 0
