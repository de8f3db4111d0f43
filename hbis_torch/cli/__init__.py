"""The ``hbis`` command line. Each subcommand lives in its own module ``cmd_<name>.py`` beside
this file, with a ``register(subparsers)`` function; modules are found automatically.

Exit codes: 0 success, 2 bad arguments or bad input (one line on stderr), 1 anything else.
"""

from __future__ import annotations

import argparse
import importlib
import pkgutil
import sys

from hbis_torch.errors import HbisInputError

COMMANDS = sorted(m.name[4:] for m in pkgutil.iter_modules(__path__) if m.name.startswith("cmd_"))


class OneLineParser(argparse.ArgumentParser):
    """argparse that reports a usage error as one line (and exit code 2)."""

    def error(self, message):  # noqa: D401 - argparse API
        self.exit(2, f"{self.prog}: error: {message} (see --help)\n")


def build_parser() -> argparse.ArgumentParser:
    parser = OneLineParser(
        prog="hbis",
        description="Risley-prism foveated imaging (the hybrid bionic image sensor): design, "
        "scanning, simulation and super-resolution. Numbers default to the paper's Table 1.",
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND",
                                parser_class=OneLineParser)
    for name in COMMANDS:
        importlib.import_module(f"{__package__}.cmd_{name}").register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except HbisInputError as exc:
        print(f"hbis {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"hbis {args.command}: interrupted", file=sys.stderr)
        return 1
    except Exception as exc:  # noqa: BLE001 - a CLI reports, it does not dump a traceback
        print(f"hbis {args.command}: {type(exc).__name__}: {exc}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
