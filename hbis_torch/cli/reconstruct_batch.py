"""``hbis reconstruct STACK... --out-dir DIR``: many stacks in one process.

One process pays the start-up (imports) once and opens the learned method's model once (its
session is cached per file, :func:`hbis_torch.reconstruct.learned.method.learned_sr`), where a
shell loop over ``hbis reconstruct --out`` pays both for every stack. Stacks run side by side
on a pool of ``--jobs`` threads, each stack on one thread (torch and onnxruntime release the
interpreter lock in their kernels): for small stacks that keeps every core busy, which one
stack's own threading does not. Every output is ``DIR/STEM.METHOD.tif``.

Checked before any work, in one line each (exit 2): no stack found, a stack named twice, two
stacks with one output, an output folder that cannot be written (or, with ``--overwrite``, an
output that is not a regular file). A stack whose output exists already is skipped, so the same
command run again after an interruption finishes the rest and nothing written is overwritten
(``--overwrite`` replaces them instead); the rule of ``--scheduler`` (:mod:`hbis_torch.cli.many`)
too. The command holds the folder's lock (:func:`hbis_torch.run_lock.lock_dir`) while it runs.
A stack that fails while it runs (an unreadable file, a stack the method refuses) is named in
one line on stderr and the others go on; the summary at the end gives each stack's exit code
(0 written, 2 bad input, 1 other error), and the command's is the largest.
"""

from __future__ import annotations

import glob
import os
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from hbis_torch.errors import HbisInputError


def expand_stacks(items) -> list[Path]:
    """The stacks named on the command line: paths, glob patterns (``*``, ``?``, ``[``) and
    ``@LIST`` files (one path a line; blank lines and ``#`` comments skipped; relative paths
    are relative to the list's folder).

    Raises
    ------
    HbisInputError
        A pattern that matches nothing, a missing list file, no stack at all, or a stack named twice.
    """
    stacks: list[Path] = []
    for item in map(str, items):
        if item.startswith("@"):
            listing = Path(item[1:])
            if not listing.is_file():
                raise HbisInputError(f"list file {listing} not found")
            lines = [line.strip() for line in listing.read_text().splitlines()]
            stacks += [listing.parent / line for line in lines if line and not line.startswith("#")]
        elif any(c in item for c in "*?["):
            matches = sorted(glob.glob(item))
            if not matches:
                raise HbisInputError(f"no stack matches {item!r}")
            stacks += map(Path, matches)
        else:
            stacks.append(Path(item))
    if not stacks:
        raise HbisInputError("no stack given")
    seen: dict[Path, Path] = {}
    for path in stacks:
        key = path.resolve()
        if key in seen:
            raise HbisInputError(f"{path} is named twice (also as {seen[key]}); its output would be written twice")
        seen[key] = path
    return stacks


def named_outputs(sources: list[Path], out_dir: Path, suffix: str) -> list[Path]:
    """``out_dir/STEM.SUFFIX`` for each input; HbisInputError if two inputs share a stem."""
    outs = [out_dir / f"{path.name.split('.')[0]}.{suffix}" for path in sources]
    by_name: dict[Path, Path] = {}
    for source, out in zip(sources, outs):
        if out in by_name:
            raise HbisInputError(f"{source} and {by_name[out]} would both be written to {out}; rename one")
        by_name[out] = source
    return outs


def output_paths(stacks: list[Path], out_dir: Path, method: str, overwrite: bool = False) -> list[Path]:
    """``out_dir/STEM.METHOD.tif`` for each stack; HbisInputError if two stacks share a stem or,
    with ``overwrite``, an output exists that is not a regular file (it could not be replaced)."""
    outs = named_outputs(stacks, out_dir, f"{method}.tif")
    inputs = {path.resolve() for path in stacks}
    clash = [out for out in outs if out.resolve() in inputs]
    if clash:
        raise HbisInputError(f"{clash[0]} is an input and would be an output; choose another --out-dir")
    check_replaceable(outs, overwrite)
    return outs


def check_replaceable(outs: list[Path], overwrite: bool) -> None:
    """With ``overwrite``, refuse (HbisInputError, before any work) outputs that exist and are not
    regular files; without it, existing outputs are skipped and need no check."""
    odd = [out for out in outs if overwrite and os.path.lexists(out) and not os.path.isfile(out)]
    if odd:
        more = f" (and {len(odd) - 1} more)" if len(odd) > 1 else ""
        raise HbisInputError(f"--out-dir: {odd[0]}{more} exists already and is not a regular file; "
                             "--overwrite cannot replace it")


def done_before(outs: list[Path], overwrite: bool = False) -> set[int]:
    """The indices of the outputs that exist already (none with ``overwrite``): skipped, so a
    rerun resumes and nothing written is overwritten."""
    return set() if overwrite else {i for i, out in enumerate(outs) if os.path.lexists(out)}


def run_batch(args, prepare, reconstruct_one) -> int:
    """Reconstruct every stack of ``args.stack`` into ``args.out_dir`` (see the module's docstring).

    ``prepare(args)`` and ``reconstruct_one(args, path, prepared)`` are ``hbis reconstruct``'s
    (:mod:`hbis_torch.cli.cmd_reconstruct`): the same work as for one stack."""
    from hbis_torch.io_utils import check_output_dir

    if args.out is not None:
        raise HbisInputError("give --out or --out-dir, not both")
    check_output_dir(args.out_dir, "--out-dir")
    stacks = expand_stacks(args.stack)
    missing = [path for path in stacks if not path.is_file()]
    if missing:
        raise HbisInputError(f"stack {missing[0]} not found" + (f" (and {len(missing) - 1} more)" if len(missing) > 1 else ""))
    overwrite = getattr(args, "overwrite", False)
    outs = output_paths(stacks, args.out_dir, args.method, overwrite)
    prepared = prepare(args)
    from hbis_torch.run_lock import lock_dir, remove_temp_files

    lock = lock_dir(args.out_dir)  # a second run on the folder is refused; a killed one's temp files go
    try:
        remove_temp_files(args.out_dir)
        skipped = done_before(outs, overwrite)
        todo = [i for i in range(len(stacks)) if i not in skipped]
        codes, jobs, seconds = _run_pool(args, prepared, reconstruct_one, stacks, outs, todo)
    finally:
        lock.close()
    failed = [(stack, code) for stack, code in zip(stacks, codes) if code]
    print(f"reconstructed {len(todo) - len(failed)} of {len(stacks)} stacks into {args.out_dir} in "
          f"{seconds:.1f} s ({jobs} at once)" + (f"; {len(skipped)} done before, skipped" if skipped else ""))
    for stack, code in failed:
        print(f"  exit {code}: {stack}")
    return max(codes, default=0)


def _run_pool(args, prepared, reconstruct_one, stacks, outs, todo) -> tuple[list[int], int, float]:
    """Reconstruct the stacks ``todo`` (indices) side by side on a pool of threads: each stack's
    exit code (0 for those not in ``todo``), the pool's size and the seconds it took."""
    from hbis_torch.progress import progress, progress_enabled, set_progress

    cpus = len(os.sched_getaffinity(0))
    # From all the stacks, not those left: a rerun that finishes the rest runs each stack on the
    # threads the whole run gave it (torch's thread count changes the last bits of some sums).
    jobs = args.jobs or (1 if args.threads is not None else min(cpus, len(stacks)))
    kw, calibration = prepared
    if jobs > 1 and "threads" not in kw and _takes_threads(args.method):
        kw = {**kw, "threads": 1}  # each stack on one thread: the pool keeps the cores busy
    prepared = (kw, calibration)
    import torch

    torch_threads = torch.get_num_threads()
    torch.set_num_threads(1 if jobs > 1 else (args.threads or torch_threads))
    codes: list[int] = [0] * len(stacks)
    started = time.monotonic()
    bar = progress(total=len(stacks), desc=f"reconstruct ({jobs} at once)", unit="stack")
    inner = progress_enabled()
    set_progress(False)  # no bars inside: stacks run side by side
    try:
        with bar, ThreadPoolExecutor(max_workers=max(1, min(jobs, len(todo)))) as pool:
            bar.update(len(stacks) - len(todo))
            futures = {i: pool.submit(_one, reconstruct_one, args, stacks[i], outs[i], prepared) for i in todo}
            for i, future in futures.items():
                codes[i] = future.result()
                bar.update()
    finally:
        set_progress(None if inner else False)
        torch.set_num_threads(torch_threads)
    return codes, jobs, time.monotonic() - started


def _takes_threads(method: str) -> bool:
    from hbis_torch.reconstruct.registry import METHODS

    return METHODS[method].threads


def _one(reconstruct_one, args, stack: Path, out: Path, prepared) -> int:
    """Reconstruct and write one stack; its exit code (a failure is named in one line on stderr)."""
    from hbis_torch.stack_io import write_image

    try:
        from hbis_torch.reconstruct.raw_output import check_raw_outputs

        check_raw_outputs(stack, out, getattr(args, "overwrite", False))  # a raw burst's preview too
        image, messages, meta, pixel_um = reconstruct_one(args, stack, prepared)
        from hbis_torch.cli.common import tell

        tell("reconstruct", messages, about=str(stack))
        if "raw" in meta:  # a raw burst: linear 16-bit TIFF and an sRGB preview, as with --out
            from hbis_torch.reconstruct.raw_output import write_raw_outputs

            write_raw_outputs(out, image, meta)
        else:
            write_image(out, image, meta, pixel_size_um=pixel_um)
        return 0
    except HbisInputError as exc:
        print(f"hbis reconstruct: {stack}: {exc}", file=sys.stderr)
        return 2
    except Exception as exc:  # noqa: BLE001 - one stack's failure must not stop the others
        print(f"hbis reconstruct: {stack}: {type(exc).__name__}: {exc}", file=sys.stderr)
        return 1
