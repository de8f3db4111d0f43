"""``hbis figures``: draw the paper's figures as PNG files."""

from __future__ import annotations

import importlib
import pkgutil
from pathlib import Path

from hbis_torch import figures
from hbis_torch.cli import examples
from hbis_torch.cli.common import add_system_args, system_from_args

# The figure sets by name, from the module names alone: a set's module (matplotlib, torch) is
# imported only when it is drawn (figure_set).
FIGURE_SET_NAMES = sorted(m.name[: -len("_figures")] for m in pkgutil.iter_modules(figures.__path__)
                          if m.name.endswith("_figures"))


#: The paper's figures the sets draw (files ``figN_*.png``), written out so that ``hbis --help``
#: imports no figure module; tests/test_cli_polish.py checks them against the modules and the README.
PAPER_FIGURES = (3, 4, 5, 6, 10)


def figure_set(name: str):
    """The ``make_figures(out_dir, system, ...)`` function of figure set ``name``."""
    return importlib.import_module(f"{figures.__name__}.{name}_figures").make_figures

# Every module hbis_torch/figures/<set>_figures.py with a function
# make_figures(out_dir, system) -> list[Path] is one figure set, found automatically.


def figure_set_names(text: str) -> list[str]:
    """The ``type=`` of a figure-set option (``hbis figures --only``, ``hbis demo --figure-sets``):
    one name or a comma list, each a set of :data:`FIGURE_SET_NAMES`; with ``action="extend"``
    the option is repeatable too."""
    import argparse

    names = [n.strip() for n in text.split(",")]
    bad = [n for n in names if n not in FIGURE_SET_NAMES]
    if bad:
        raise argparse.ArgumentTypeError(f"no figure set {bad[0]!r}; the sets are {', '.join(FIGURE_SET_NAMES)}")
    return names


def add_figure_sets_arg(parser, flag: str) -> None:
    """The figure-set option, in one form for every command that takes one."""
    parser.add_argument(flag, type=figure_set_names, action="extend", metavar="SET[,SET...]",
                        help=f"draw only these figure sets, repeatable or a comma list: {', '.join(FIGURE_SET_NAMES)} "
                        "(default: all)")


def register(sub) -> None:
    p = sub.add_parser(
        "figures",
        help=f"draw the paper's figures ({', '.join(map(str, PAPER_FIGURES))}) as PNG files",
        description="Reproduce the paper's figures with matplotlib. Sets: " + ", ".join(FIGURE_SET_NAMES),
        epilog=examples("hbis figures --out figures", "hbis figures --only scan --out figures"),
    )
    add_system_args(p)
    p.add_argument("--out", default="figures", help="output folder (default: ./figures)")
    add_figure_sets_arg(p, "--only")
    p.set_defaults(func=run)


def run(args) -> int:
    from hbis_torch.io_utils import check_output_dir
    from hbis_torch.progress import progress_enabled

    check_output_dir(args.out)
    system = system_from_args(args)
    for name in dict.fromkeys(args.only or FIGURE_SET_NAMES):
        for path in figure_set(name)(Path(args.out), system, progress=progress_enabled()):
            print(path)
    return 0
