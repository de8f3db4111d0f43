"""The command line's side of the engine: ``--scheduler`` and many inputs for ``hbis reconstruct``,
``hbis assemble --burst``, ``hbis validate`` and ``hbis simulate`` (docs/scale-out.md).

Each command calls :func:`add_scheduler_argument` once when it builds its parser and branches
once in its handler (:func:`run_reconstruct`, :func:`run_many`); everything else is here.

* ``hbis reconstruct STACK... --out-dir DIR --scheduler S``: one task per stack, to
  ``DIR/STEM.METHOD.tif`` (without ``--scheduler``, the in-process batch of
  :mod:`hbis_torch.cli.reconstruct_batch` runs, as before).
* ``hbis assemble --burst --scale S BURST... --out-dir DIR [--scheduler S]``: each BURST a video
  file or a multi-page TIFF, to ``DIR/STEM.burst.tif``.
* ``hbis validate STACK... --out-dir DIR [--scheduler S]``: to ``DIR/STEM.validate.json``, the
  object ``hbis validate --json`` prints.
* ``hbis simulate --scene SCENE... --seed N... --out-dir DIR [--with-truth] [--scheduler S]``: one
  stack per scene and seed, to ``DIR/SCENE.seedN.tif`` (and its truth, ``.truth.tif``).

Checked before any work (exit 2, one line): no input, a missing one, one named twice, two
inputs with one output, an output that is an input, an output folder that cannot be written,
``--scheduler`` without ``--out-dir``. Outputs that exist are skipped (a rerun resumes; the
in-process ``hbis reconstruct --out-dir`` does the same), ``--overwrite`` replaces them. An
input that fails is named in one line and the others go on; the exit code is the worst input's
(2 bad input, 1 other), the summary names each failure. A lost scheduler is exit 3.
"""

from __future__ import annotations

import argparse
import functools
import sys
from pathlib import Path

from hbis_torch.errors import HbisInputError

SCHEDULER_HELP = ("run one task per input on a Dask cluster: a scheduler's ADDRESS (tcp://host:8786), or "
                  "local[:N] for N worker processes on this machine (default N: its CPUs); needs --out-dir and "
                  "the [cluster] extra; outputs that exist are skipped, so a rerun resumes (docs/scale-out.md)")


def _scheduler(text: str):
    from hbis_torch.cluster.engine import parse_scheduler

    try:
        return parse_scheduler(text)
    except HbisInputError as exc:
        raise argparse.ArgumentTypeError(str(exc).removeprefix("--scheduler ").removeprefix("--scheduler: ")) from None


def add_scheduler_argument(parser: argparse.ArgumentParser, many: str | None = None) -> None:
    """Add ``--scheduler ADDRESS|local[:N]`` to a command's parser.

    ``many``: for a command that takes one input today (``hbis validate``'s ``stack``) or writes
    one output (``hbis assemble``'s ``--out``), the destination of its positional input: it then
    takes any number, ``--out`` stops being required (:func:`run_many` asks for it where one
    output is written) and ``--out-dir DIR`` is added."""
    parser.add_argument("--scheduler", type=_scheduler, metavar="ADDRESS|local[:N]", help=SCHEDULER_HELP)
    if many is None:
        return
    for action in parser._actions:  # noqa: SLF001 - argparse keeps no public handle on added arguments
        if action.dest == many and action.nargs in (None, 1):
            action.nargs = "+"
        if action.dest == "out":
            action.required = False
    parser.add_argument("--out-dir", type=Path, metavar="DIR",
                        help="many inputs, one output each in DIR (see --scheduler; without it, side by side on "
                        "threads of this process); outputs that exist are skipped (--overwrite replaces them); an "
                        "input that fails is named in one line and the others go on")


def _warm_worker(warm=None) -> None:
    """A worker's set-up before its first task: freed memory kept in the heap, as the ``hbis``
    program keeps it (:func:`hbis_torch.cli.keep_freed_memory`), then the job's imports."""
    from hbis_torch.cli import keep_freed_memory

    keep_freed_memory()
    if warm is not None:
        warm()


def _inputs_and_outputs(items, out_dir: Path, suffix: str, overwrite: bool = False) -> tuple[list[Path], list[Path]]:
    """The inputs (paths, globs, @LIST) and ``out_dir/STEM.SUFFIX`` for each, checked (with
    ``overwrite``, existing outputs must be regular files)."""
    from hbis_torch.cli.reconstruct_batch import check_replaceable, expand_stacks, named_outputs
    from hbis_torch.io_utils import check_output_dir

    check_output_dir(out_dir, "--out-dir")
    sources = expand_stacks(items)
    missing = [path for path in sources if not path.is_file()]
    if missing:
        raise HbisInputError(f"{missing[0]} not found" + (f" (and {len(missing) - 1} more)" if len(missing) > 1 else ""))
    outputs = named_outputs(sources, out_dir, suffix)
    inputs = {path.resolve() for path in sources}
    clash = [out for out in outputs if out.resolve() in inputs]
    if clash:
        raise HbisInputError(f"{clash[0]} is an input and would be an output; choose another --out-dir")
    check_replaceable(outputs, overwrite)
    return sources, outputs


def _execute(job, sources, outputs, args, *, desc: str, prefix: str, threads: int = 1):
    """Run the tasks on ``args.scheduler`` (or here when it is None); the Summary."""
    from hbis_torch.cluster.engine import connect, dashboard_link, run_tasks, worker_plugin

    overwrite = getattr(args, "overwrite", False)  # validate has no --overwrite
    if args.scheduler is None:
        return run_tasks(job, sources, outputs, desc=desc, prefix=prefix, out_dir=args.out_dir, overwrite=overwrite)
    with connect(args.scheduler) as client:
        client.register_plugin(worker_plugin(threads, functools.partial(_warm_worker, getattr(job, "warm", None))))
        link = dashboard_link(client)
        if link:
            print(f"{prefix}: Dask dashboard at {link}", file=sys.stderr)
        return run_tasks(job, sources, outputs, client=client, desc=desc, prefix=prefix, out_dir=args.out_dir,
                         overwrite=overwrite)


def _finish(summary, verb: str, noun: str, out_dir) -> int:
    for line in summary.lines(verb, noun, out_dir):
        print(line)
    return summary.code


def run_reconstruct(args, prepare, reconstruct_one) -> int:
    """``hbis reconstruct ... --out-dir DIR --scheduler S`` (``prepare`` and ``reconstruct_one``:
    :mod:`hbis_torch.cli.cmd_reconstruct`'s)."""
    from hbis_torch.cli.jobs import ReconstructJob, plain_args
    from hbis_torch.reconstruct.registry import METHODS

    if args.out_dir is None:
        raise HbisInputError("--scheduler needs --out-dir DIR (one output per stack)")
    if args.jobs is not None:
        raise HbisInputError("--jobs is for the in-process --out-dir; with --scheduler the workers run the stacks")
    sources, outputs = _inputs_and_outputs(args.stack, args.out_dir, f"{args.method}.tif", args.overwrite)
    kw, calibration = prepare(args)
    threads = args.threads or 1  # a worker has one thread: as each stack in the in-process pool
    if METHODS[args.method].threads and "threads" not in kw:
        kw["threads"] = threads
    job = ReconstructJob(plain_args(args), (kw, calibration), threads, reconstruct_one)
    summary = _execute(job, sources, outputs, args, desc="reconstruct", prefix="hbis reconstruct", threads=threads)
    return _finish(summary, "reconstructed", "stacks", args.out_dir)


def run_many(args, command: str) -> int | None:
    """``hbis assemble --burst`` or ``hbis validate`` (``command``) on many inputs into
    ``--out-dir``; None where the command's one-input path should run (``args`` then holds one
    input, as it did before, and ``--out`` where the command needs it)."""
    if args.out_dir is None:
        if args.scheduler is not None:
            raise HbisInputError("--scheduler needs --out-dir DIR (one output per input)")
        if command == "validate":
            if len(args.stack) != 1:
                raise HbisInputError(f"{len(args.stack)} stacks given: give --out-dir DIR to validate many")
            args.stack = args.stack[0]
        elif args.out is None:
            raise HbisInputError("--out is required (or --burst --out-dir DIR for many bursts)")
        return None
    if command == "validate":
        return _run_validate(args)
    return _run_bursts(args)


def _run_bursts(args) -> int:
    from hbis_torch.cli.jobs import BurstJob, plain_args

    if not args.burst:
        raise HbisInputError("--out-dir is for bursts (--burst --scale S): each FRAME one burst file")
    if args.out is not None:
        raise HbisInputError("give --out or --out-dir, not both")
    if args.scale is None:
        raise HbisInputError("--burst needs --scale S (the output scale: 2, 3, 4, ...)")
    refused = [flag for flag, dest in (("--phases", "phases"), ("--cfa", "cfa"), ("--dark", "dark"),
                                       ("--flat", "flat"), ("--bad-pixels", "bad_pixels"),
                                       ("--black-level", "black_level"), ("--system", "system"),
                                       ("--calibration", "calibration")) if getattr(args, dest, None) is not None]
    if refused:
        raise HbisInputError(f"{', '.join(refused)} do(es) not apply to a burst (--burst)")
    sources, outputs = _inputs_and_outputs(args.frames, args.out_dir, "burst.tif", args.overwrite)
    summary = _execute(BurstJob(plain_args(args)), sources, outputs, args, desc="assemble", prefix="hbis assemble")
    return _finish(summary, "assembled", "bursts", args.out_dir)


def _run_validate(args) -> int:
    from hbis_torch.cli.validate_report import method_names
    from hbis_torch.cli.method_options import keywords_for_methods
    from hbis_torch.cli.jobs import ValidateJob, plain_args
    from hbis_torch.reconstruct.registry import METHODS

    if args.json:
        raise HbisInputError("--json prints one stack's report; with --out-dir each is written as DIR/STEM.validate.json")
    names = method_names(args.method)
    options = keywords_for_methods(args, names, METHODS)
    sources, outputs = _inputs_and_outputs(args.stack, args.out_dir, "validate.json")
    summary = _execute(ValidateJob(plain_args(args), names, options), sources, outputs, args,
                       desc="validate", prefix="hbis validate")
    return _finish(summary, "validated", "stacks", args.out_dir)


def run_simulations(args, simulate_one, check_common, scenes) -> int:
    """``hbis simulate --scene A B ... --seed 0 1 ... --out-dir DIR [--scheduler S]``: one task
    per scene and seed, to ``DIR/SCENE.seedN.tif`` (``simulate_one``, ``check_common`` and the
    built-in ``scenes``: :mod:`hbis_torch.cli.cmd_simulate`'s, passed in: it imports this module)."""
    from hbis_torch.cli.jobs import SCENE_SEED, SimulateJob, plain_args
    from hbis_torch.cli.reconstruct_batch import check_replaceable
    from hbis_torch.io_utils import check_output_dir

    if args.out is not None or args.truth is not None:
        raise HbisInputError("give --out (and --truth) or --out-dir (and --with-truth), not both")
    check_output_dir(args.out_dir, "--out-dir")
    unknown = [scene for scene in args.scene if scene not in scenes and not Path(scene).is_file()]
    if unknown:
        raise HbisInputError(f"--scene {unknown[0]}: neither a built-in scene nor a file")
    stems = [Path(scene).stem if Path(scene).is_file() else scene for scene in args.scene]
    if len(set(stems)) < len(stems) or len(set(args.seed)) < len(args.seed):
        raise HbisInputError("two scenes (or seeds) would have one output: give each once, with distinct file names")
    check_common(args)
    sources = [f"{scene}{SCENE_SEED}{seed}" for scene in args.scene for seed in args.seed]
    outputs = [args.out_dir / f"{stem}.seed{seed}.tif" for stem in stems for seed in args.seed]
    check_replaceable(outputs, args.overwrite)
    job = SimulateJob(plain_args(args), simulate_one)
    summary = _execute(job, sources, outputs, args, desc="simulate", prefix="hbis simulate")
    return _finish(summary, "simulated", "stacks", args.out_dir)
