"""``hbis figures``: draw the paper's figures as PNG files."""

from __future__ import annotations

from pathlib import Path

from .common import add_system_args, system_from_args

# Each entry: a function (out_dir, system) -> list of paths. Other issues add their figures here.
FIGURE_SETS = {}


def _design(out_dir, system):
    from ..figures.design_figures import design_figures

    return design_figures(out_dir, system)


FIGURE_SETS["design"] = _design


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
