"""``hbis reconstruct STACK... --out-dir DIR``: many stacks in one process.

One process pays the start-up (imports) once and opens the learned method's model once (its
session is cached per file, :func:`hbis_torch.reconstruct.learned.method.learned_sr`), where a
shell loop over ``hbis reconstruct --out`` pays both for every stack. Stacks run side by side
on a pool of ``--jobs`` threads, each stack on one thread (torch and onnxruntime release the
interpreter lock in their kernels): for small stacks that keeps every core busy, which one
stack's own threading does not. Every output is ``DIR/STEM.METHOD.tif``.

Checked before any work, in one line each (exit 2): no stack found, a stack named twice, an
output that exists already (unless ``--overwrite``, the rule of ``--out`` too), an output folder
that cannot be written.
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
    """``out_dir/STEM.METHOD.tif`` for each stack; HbisInputError if two stacks share a stem or
    (unless ``overwrite``) an output exists already."""
    outs = named_outputs(stacks, out_dir, f"{method}.tif")
    existing = [out for out in outs if os.path.lexists(out) and not (overwrite and os.path.isfile(out))]
    if existing:
        more = f" (and {len(existing) - 1} more)" if len(existing) > 1 else ""
        how = "it is not a regular file" if overwrite else "pass --overwrite to replace it"
        raise HbisInputError(f"--out-dir: {existing[0]}{more} exists already; {how}")
    return outs


def run_batch(args, prepare, reconstruct_one) -> int:
    """Reconstruct every stack of ``args.stack`` into ``args.out_dir`` (see the module's docstring).

    ``prepare(args)`` and ``reconstruct_one(args, path, prepared)`` are ``hbis reconstruct``'s
    (:mod:`hbis_torch.cli.cmd_reconstruct`): the same work as for one stack."""
    from hbis_torch.io_utils import check_output_dir
    from hbis_torch.progress import progress, progress_enabled, set_progress

    if args.out is not None:
        raise HbisInputError("give --out or --out-dir, not both")
    check_output_dir(args.out_dir, "--out-dir")
    stacks = expand_stacks(args.stack)
    missing = [path for path in stacks if not path.is_file()]
    if missing:
        raise HbisInputError(f"stack {missing[0]} not found" + (f" (and {len(missing) - 1} more)" if len(missing) > 1 else ""))
    outs = output_paths(stacks, args.out_dir, args.method, getattr(args, "overwrite", False))
    cpus = len(os.sched_getaffinity(0))
    jobs = args.jobs or (1 if args.threads is not None else min(cpus, len(stacks)))
    kw, calibration = prepare(args)
    if jobs > 1 and "threads" not in kw and _takes_threads(args.method):
        kw["threads"] = 1  # each stack on one thread: the pool keeps the cores busy
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
        with bar, ThreadPoolExecutor(max_workers=jobs) as pool:
            futures = [pool.submit(_one, reconstruct_one, args, stack, out, prepared)
                       for stack, out in zip(stacks, outs)]
            for i, future in enumerate(futures):
                codes[i] = future.result()
                bar.update()
    finally:
        set_progress(None if inner else False)
        torch.set_num_threads(torch_threads)
    failed = [(stack, code) for stack, code in zip(stacks, codes) if code]
    print(f"reconstructed {len(stacks) - len(failed)} of {len(stacks)} stacks into {args.out_dir} in "
          f"{time.monotonic() - started:.1f} s ({jobs} at once)")
    for stack, code in failed:
        print(f"  exit {code}: {stack}")
    return max(codes)


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
