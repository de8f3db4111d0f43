"""The ``hbis`` command line. Each subcommand lives in its own module ``cmd_<name>.py`` beside
this file, with a ``register(subparsers)`` function; modules are found automatically.

Conventions (docs/design.md, "CLI contract"): exit codes 0 success, 2 bad arguments or bad
input (one line on stderr), 3 a device that failed (the motor controller timed out, vanished,
went silent, raised an alarm; one line), 1 anything else; ``--version``; ``-v``/``-q`` set the level of the
``hbis_torch`` loggers (the library logs, this module configures; a command's own lines go the
same way, :func:`hbis_torch.cli.common.tell`) and ``-q`` hides the progress bars and Python's
warnings; a closed pipe ends the command quietly. A ``cmd_`` module imports only light modules at
the top and its heavy ones (torch, matplotlib, pyserial) inside the function that runs it, so that
``hbis --help`` and each ``--help`` start fast (``benchmarks/bench_cli_start.py``;
``tests/test_architecture.py`` checks what they load).
"""

from __future__ import annotations

import argparse
import gc
import logging
import os
import pkgutil
import sys
import warnings

from hbis_torch import __version__
from hbis_torch.errors import HbisError

COMMANDS = sorted(m.name[4:] for m in pkgutil.iter_modules(__path__) if m.name.startswith("cmd_"))

class HelpFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """Shows every option's default (the Table 1 values among them); help texts that already
    name their default are left as written. A description or epilog keeps its paragraphs (split
    at blank lines), each wrapped to the terminal's width; a paragraph with an indented line (the
    examples) is kept as written."""

    def _get_help_string(self, action):
        text = action.help or ""
        if "default" in text.lower() or action.default in (None, False, argparse.SUPPRESS):
            return text
        return super()._get_help_string(action)

    def _fill_text(self, text, width, indent):
        import textwrap

        out = []
        for paragraph in text.split("\n\n"):
            if any(line[:1].isspace() for line in paragraph.splitlines()):
                out.append("\n".join(indent + line for line in paragraph.splitlines()))
            else:
                out.append(textwrap.fill(" ".join(paragraph.split()), width, initial_indent=indent,
                                         subsequent_indent=indent))
        return "\n\n".join(out)


class RawDescriptionFormatter(HelpFormatter, argparse.RawDescriptionHelpFormatter):
    """:class:`HelpFormatter` that keeps the description's line breaks."""

    _fill_text = argparse.RawDescriptionHelpFormatter._fill_text


def examples(*lines: str) -> str:
    """A help text's epilog: the ``examples:`` heading and one command a line."""
    return "example" + ("s" if len(lines) > 1 else "") + ":\n" + "\n".join(f"  {line}" for line in lines)


class OneLineParser(argparse.ArgumentParser):
    """argparse that reports a usage error as one line (and exit code 2), with a hint where an
    option belongs to another level of the command (``hbis motors scan --port X``)."""

    def __init__(self, *args, **kwargs):
        formatter = kwargs.get("formatter_class")
        if formatter is argparse.RawDescriptionHelpFormatter:
            kwargs["formatter_class"] = RawDescriptionFormatter
        elif formatter in (None, argparse.HelpFormatter):
            kwargs["formatter_class"] = HelpFormatter
        super().__init__(*args, **kwargs)

    def error(self, message):  # noqa: D401 - argparse API
        self.exit(2, f"{self.prog}: error: {message}{_misplaced_hint(self, message)} (see --help)\n")


def _chain(root: argparse.ArgumentParser, argv: list[str]) -> list[argparse.ArgumentParser]:
    """The parsers ``argv`` walks through: ``hbis``, ``hbis motors``, ``hbis motors scan``."""
    chain = [root]
    for word in argv:
        children = {name: p for a in chain[-1]._actions if isinstance(a, argparse._SubParsersAction)
                    for name, p in a.choices.items()}
        if word in children:
            chain.append(children[word])
    return chain


def _misplaced_hint(parser: argparse.ArgumentParser, message: str) -> str:
    """'; --port is an option of 'hbis motors': put it before 'scan'' for an unrecognised option
    that a parser higher up the command takes."""
    argv = getattr(parser, "argv", None)
    if argv is None or not message.startswith("unrecognized arguments:"):
        return ""
    chain = _chain(parser, argv)
    hints = []
    for option in dict.fromkeys(w.split("=")[0] for w in message.split(":", 1)[1].split() if w.startswith("-")):
        for level, owner in enumerate(chain[:-1]):
            if option in owner._option_string_actions:
                below = chain[level + 1].prog.removeprefix(owner.prog).strip()
                hints.append(f"{option} is an option of '{owner.prog}': put it before '{below}'")
                break
    return ("; " + "; ".join(hints)) if hints else ""


def _finish(parser: argparse.ArgumentParser) -> None:
    """Give every sub-parser, down to the actions, the global ``-v``/``-q`` (default SUPPRESS,
    so that one given before the subcommand is not reset by the sub-parser's default)."""
    for child in (p for a in parser._actions if isinstance(a, argparse._SubParsersAction) for p in a.choices.values()):
        _add_verbosity(child, argparse.SUPPRESS)
        _finish(child)


def _add_verbosity(parser: argparse.ArgumentParser, default) -> None:
    """``-v``/``-q`` in an "output" group, listed right after the parser's own options (before
    groups of options that only some runs take, such as a method's)."""
    group = parser.add_argument_group("output")
    motors = parser.prog.split()[1:2] == ["motors"]
    debug = ("-vv: debug, with the GRBL serial traffic" if motors else
             "-vv: debug" + ("; on motor commands with the GRBL serial traffic" if parser.prog == "hbis" else ""))
    group.add_argument("-v", "--verbose", action="count", default=0 if default is None else default,
                       help=f"more messages on stderr: what each step did and found ({debug})")
    group.add_argument("-q", "--quiet", action="store_true", default=False if default is None else default,
                       help="only errors on stderr: no warnings, no progress bars")
    groups = parser._action_groups
    groups.insert(2, groups.pop())  # after the positionals and the options


def build_parser(argv: list[str] | None = None) -> argparse.ArgumentParser:
    """The ``hbis`` parser. A ``cmd_`` module with a ``SUMMARY`` line builds its whole parser
    (which may import heavy modules, for the lists in its help) only when ``argv`` runs it;
    otherwise it is listed with that line (``argv`` None: every parser is built)."""
    import importlib

    parser = OneLineParser(
        prog="hbis",
        description="Risley-prism foveated imaging (the hybrid bionic image sensor): design, "
        "scanning, simulation and super-resolution. Numbers default to the paper's Table 1.",
        epilog="exit codes: 0 success; 2 bad arguments or bad input (one line on stderr); 3 a device "
        "failed (the motor controller timed out, vanished, went silent, is held or raised an alarm: "
        "fix the bench and retry); 1 anything else\n\n"
        + examples("hbis demo --out hbis-out", "hbis simulate --scene camera --h 4 --out stack.tif",
                   "hbis reconstruct stack.tif --method learned --out sr.tif", "hbis COMMAND --help"),
    )
    parser.add_argument("--version", action="version", version=f"hbis {__version__}")
    _add_verbosity(parser, None)
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND",
                                parser_class=OneLineParser)
    chosen = next((word for word in argv if word in COMMANDS), None) if argv is not None else None
    for name in COMMANDS:
        module = importlib.import_module(f"{__package__}.cmd_{name}")
        if argv is not None and name != chosen and hasattr(module, "SUMMARY"):
            sub.add_parser(name, help=module.SUMMARY)
        else:
            module.register(sub)
    _finish(parser)
    return parser


def configure_logging(verbose: int = 0, quiet: bool = False) -> None:
    """Messages of the ``hbis_torch`` loggers (the GRBL driver's among them) on stderr:
    warnings by default, info with ``-v``, debug with ``-vv``, errors only with ``-q``; ``-q``
    also hides the progress bars."""
    from hbis_torch.progress import set_progress

    level = logging.ERROR if quiet else {0: logging.WARNING, 1: logging.INFO}.get(verbose, logging.DEBUG)
    logger = logging.getLogger("hbis_torch")
    logger.setLevel(level)
    handler = next((h for h in logger.handlers if getattr(h, "_hbis_cli", False)), None)
    if handler is None:
        handler = _StderrHandler()
        handler._hbis_cli = True
        logger.addHandler(handler)
    handler.setFormatter(_LineFormatter("hbis: %(message)s" if level >= logging.INFO
                                        else "hbis: %(name)s: %(message)s"))
    set_progress(False if quiet else None)


class _StderrHandler(logging.StreamHandler):
    """A handler that writes to whatever ``sys.stderr`` is when a record comes (a test's
    capture, a redirected stream), not to the stream of the first command run in the process."""

    def __init__(self):
        super().__init__(sys.stderr)

    @property
    def stream(self):
        return sys.stderr

    @stream.setter
    def stream(self, value):
        pass


class _LineFormatter(logging.Formatter):
    """The handler's format, except for a command's own lines (:func:`hbis_torch.cli.common.tell`),
    which carry their ``hbis COMMAND:`` prefix already."""

    def format(self, record):
        if getattr(record, "hbis_line", False):
            return record.getMessage()
        return super().format(record)


def _quiet_broken_pipe() -> int:
    """The reader went away (``hbis design --json | head -1``): say nothing, exit as a program
    killed by SIGPIPE would (141), and keep Python from complaining at shutdown."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
    except (OSError, ValueError):
        pass
    return 141


# The garbage collector's thresholds while a command runs. Start-up is mostly imports, and torch
# alone makes objects by the hundred thousand that live as long as the process: Python's defaults
# (700, 10, 10) scan them over and over (a 32 x 32 learned reconstruct: 431 collections, 0.13 s
# of 1.1 s in process), these make it 5 collections and 0.04 s. Cycles are still collected, later.
GC_THRESHOLDS = (50_000, 20, 20)


def main(argv: list[str] | None = None) -> int:
    """Run one ``hbis`` command line (``argv``, default ``sys.argv[1:]``); returns the exit code.
    The collector's thresholds are :data:`GC_THRESHOLDS` meanwhile, and restored after (main may
    run in another program's process)."""
    before = gc.get_threshold()
    gc.set_threshold(*GC_THRESHOLDS)
    try:
        return _main(argv)
    finally:
        gc.set_threshold(*before)


# glibc's mallopt parameters (<malloc.h>)
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD, _M_MMAP_MAX = -1, -3, -4
# Jobs of more samples than this (frames x pixels x channels) map their large blocks fresh again
# (:func:`map_large_arrays`): 16 frames of 12 MP are 192M, of 640 x 480 5M, a full h = 7 scan 60M.
LARGE_JOB_SAMPLES = 1 << 27
# The block size from which :func:`map_large_arrays` maps blocks: glibc's own largest threshold.
LARGE_BLOCK_BYTES = 32 * 2**20
_kept = {"freed": False}


def _mallopt():
    """glibc's ``mallopt`` through ctypes, or None (macOS, Windows, musl)."""
    try:
        import ctypes

        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError, TypeError):
        return None
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    return mallopt


def keep_freed_memory() -> bool:
    """Have glibc's malloc serve every block from its heap and keep what is freed there.

    By default a block of 32 MB or more is a fresh mapping of its own, returned to the system
    when freed, so each image-sized array (78 MB at h = 4, 240 MB at h = 7 for a full frame) is
    paid for again in page faults, which are slow on virtual machines. Kept in the heap, the
    memory of one step serves the next: a full-frame learned reconstruct at h = 7 spent 0.85-0.96 s
    of system time against 2.13-2.16 s, and took 9.16-9.28 s against 10.05-10.32 s (2 cores, a
    VM); its peak RSS stayed under 2 GB. The process keeps its peak until it exits, which is why only
    the ``hbis`` program asks for this (:func:`entry_point`), not :func:`main` or the library; a
    job too large to gain from it maps its large blocks again (:func:`map_large_arrays`).

    Returns
    -------
    bool
        Whether it applied: False without glibc's ``mallopt`` (macOS, Windows, musl).
    """
    mallopt = _mallopt()
    if mallopt is None:
        return False
    _kept["freed"] = bool(mallopt(_M_MMAP_MAX, 0)) and bool(mallopt(_M_TRIM_THRESHOLD, 2**31 - 1))
    return _kept["freed"]


def map_large_arrays(samples: int) -> bool:
    """Where the program keeps freed memory (:func:`keep_freed_memory`) and a job holds more than
    :data:`LARGE_JOB_SAMPLES` samples, serve blocks of :data:`LARGE_BLOCK_BYTES` or more as fresh
    mappings again, returned to the system when freed. Kept in the heap, the arrays of a 16-frame
    12 MP burst's classical reconstruct (hundreds of MB each) raised its peak by about a GB for a
    sixth less time: 5.1 against 4.0 GiB (29.5 against 34.9 s), in RGB 6.5 against 5.5 GiB, past
    the 6 GB such a burst should fit in (``/usr/bin/time hbis reconstruct``, one thread, the burst
    of benchmarks/bench_burst_budget.py); their page faults are a small share of their work. ``hbis
    assemble --burst``, ``hbis reconstruct`` and ``hbis validate`` call it once they know the job's size.

    Parameters
    ----------
    samples : int
        The job's frames x pixels x channels.

    Returns
    -------
    bool
        Whether it changed anything.
    """
    if not _kept["freed"] or samples <= LARGE_JOB_SAMPLES:
        return False
    mallopt = _mallopt()
    applied = bool(mallopt(_M_MMAP_THRESHOLD, LARGE_BLOCK_BYTES)) and bool(mallopt(_M_MMAP_MAX, 65536))
    _kept["freed"] = not applied
    return applied


def entry_point():
    """The ``hbis`` program (and ``python -m hbis_torch``): :func:`main`, then exit with its code.

    First, freed memory stays in the process for the next array (:func:`keep_freed_memory`).
    Before exiting, the objects alive are frozen (``gc.freeze``), so that the interpreter's
    last collection at shutdown skips them: torch's objects by the hundred thousand took it
    0.3 s (a 32 x 32 learned reconstruct: 1.47-1.54 s end to end, 1.20-1.23 s frozen). The
    atexit handlers still run, and everything the commands write is closed by then.
    """
    keep_freed_memory()
    code = main()
    gc.freeze()
    sys.exit(code)


def _main(argv: list[str] | None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser(argv)
    parser.argv = argv
    args = parser.parse_args(parser.argv)
    args.argv = ["hbis", *argv]  # the command line, for outputs that record it (the demo's report)
    configure_logging(args.verbose, args.quiet)
    try:
        with warnings.catch_warnings():
            if args.quiet:  # Python's warnings (a dependency's among them) are messages too
                warnings.simplefilter("ignore")
            code = int(args.func(args) or 0)
        sys.stdout.flush()  # a closed pipe shows here for short outputs
        return code
    except BrokenPipeError:
        return _quiet_broken_pipe()
    except HbisError as exc:  # 2: bad input, 3: a device failed, 1: anything else raised on purpose
        print(f"hbis {args.command}: error: {exc}", file=sys.stderr)
        return int(exc.exit_code)
    except KeyboardInterrupt:
        print(f"hbis {args.command}: interrupted", file=sys.stderr)
        return 1
    except Exception as exc:  # noqa: BLE001 - a CLI reports, it does not dump a traceback
        print(f"hbis {args.command}: {type(exc).__name__}: {exc}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    entry_point()
