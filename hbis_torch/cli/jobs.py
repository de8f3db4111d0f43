"""The jobs of the commands that take many inputs: one input in, one whole output file out.

Each is a small picklable object (the command's options, nothing heavy) called as
``job(source, staging) -> messages`` by :func:`hbis_torch.cluster.engine.run_task`, on a Dask
worker or in this process; ``job.warm()`` imports what it needs, once per worker, before the
first task (:func:`hbis_torch.cluster.engine.worker_plugin`). Each does what the command does for one input, with the same
library calls, so that the outputs are the same bit for bit.
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path


def plain_args(args: argparse.Namespace) -> argparse.Namespace:
    """``args`` without the handler function (``func``), for pickling to the workers."""
    return argparse.Namespace(**{k: v for k, v in vars(args).items() if k != "func"})


@dataclass
class ReconstructJob:
    """``hbis reconstruct``'s work on one stack: :func:`hbis_torch.cli.cmd_reconstruct.reconstruct_one`,
    then :func:`hbis_torch.stack_io.write_image` (the output is ``STEM.METHOD.tif``).

    ``prepared`` is ``cmd_reconstruct.prepare``'s (the method's keywords, the calibration frames);
    ``threads`` torch's threads for the stack (1 on a worker of one thread, as in the in-process
    batch's pool)."""

    args: argparse.Namespace
    prepared: tuple
    threads: int
    reconstruct_one: Callable  # cmd_reconstruct.reconstruct_one (passed in: the command imports this module)

    def warm(self) -> None:
        """Import what a task needs (once per worker, before the first task): the method's
        modules, the registration's, kornia; a second or more per worker on a cold start."""
        import importlib

        from hbis_torch.reconstruct.registry import METHODS

        method = METHODS[self.args.method]
        for target in (method.run, method.raw_bayer, getattr(method, "burst", None)):
            if isinstance(target, str):
                importlib.import_module(target.partition(":")[0])
        for name in ("hbis_torch.cli.cmd_reconstruct", "hbis_torch.stack_io", "hbis_torch.registration.stack",
                     "hbis_torch.capture.calibration", "kornia", "tifffile"):
            importlib.import_module(name)

    def __call__(self, source, staging) -> list[str]:
        from hbis_torch.cluster.engine import output_of
        from hbis_torch.reconstruct.raw_output import check_raw_outputs
        from hbis_torch.stack_io import write_image

        out = output_of(staging)
        check_raw_outputs(source, out, getattr(self.args, "overwrite", False))  # as the in-process batch
        image, messages, meta, pixel_um = self.reconstruct_one(self.args, Path(source), self.prepared, threads=self.threads)
        if "raw" in meta:  # a raw burst: linear 16-bit TIFF and an sRGB preview beside it, as in process
            write_raw_staged(staging, out, image, meta)
        else:
            write_image(staging, image, meta, pixel_size_um=pixel_um)
        return messages


def write_raw_staged(staging, out, image, meta) -> None:
    """A raw burst's reconstruction: the linear TIFF into ``staging`` (the engine publishes it as
    ``out``) and its sRGB preview moved, whole, to ``out``'s preview name
    (:func:`hbis_torch.reconstruct.raw_output.preview_path`) before the output is published, so
    that an output found by a rerun has its preview."""
    import os

    from hbis_torch.reconstruct.raw_output import preview_path, write_raw_outputs

    written = write_raw_outputs(staging, image, meta)  # staging ends in .tmp: the TIFF, not a DNG
    os.replace(written[-1], preview_path(out))


@dataclass
class BurstJob:
    """``hbis assemble --burst``'s work on one burst (a video file or a multi-page TIFF): read the
    frames, measure their motions (:func:`hbis_torch.capture.burst.assemble_burst`), write the
    burst stack."""

    args: argparse.Namespace

    def warm(self) -> None:
        """Import what a task needs (once per worker, before the first task)."""
        import hbis_torch.capture.burst  # noqa: F401

    def __call__(self, source, staging) -> list[str]:
        from hbis_torch.capture import read_frames
        from hbis_torch.capture.burst import assemble_burst
        from hbis_torch.stack_io import write_stack

        a = self.args
        frames, names = read_frames([source])
        stack, messages = assemble_burst(frames, a.scale, a.reference, a.motion, roi=a.roi,
                                         bit_depth=a.bit_depth, names=names)
        write_stack(staging, stack)
        return messages


@dataclass
class ValidateJob:
    """``hbis validate``'s work on one stack, written as the JSON object ``hbis validate --json``
    prints (``STEM.validate.json``). ``names`` are the methods scored, ``options`` their keywords
    (``cmd_validate.method_names`` and ``method_options.keywords_for_methods``, checked before
    any work)."""

    args: argparse.Namespace
    names: list
    options: dict

    def warm(self) -> None:
        """Import what a task needs (once per worker, before the first task)."""
        import hbis_torch.reconstruct.registry  # noqa: F401
        import hbis_torch.validate.cross  # noqa: F401

    def __call__(self, source, staging) -> list[str]:
        from hbis_torch.stack_io import read_stack
        from hbis_torch.validate.cross import DEFAULT_HOLDOUT, cross_validate
        from hbis_torch.validate.forward import DEFAULT_BLUR_PX
        from hbis_torch.validate.frames import holdout_frames
        from hbis_torch.validate.score import DEFAULT_BORDER_PX

        a = self.args
        stack = read_stack(source)
        count = len(stack.frames)
        holdout = min(DEFAULT_HOLDOUT, max(1, count - 1)) if a.holdout is None else a.holdout
        holdout_frames(count, stack.reference_index, holdout)
        messages: list[str] = []
        result = cross_validate(stack, self.names, holdout, registration=a.registration,
                                border_px=DEFAULT_BORDER_PX if a.border is None else a.border,
                                blur_px=DEFAULT_BLUR_PX if a.blur is None else a.blur,
                                method_options=self.options, messages=messages)
        messages += [f"{name}: {line}" for name, scores in result.methods.items() for line in scores.messages]
        from hbis_torch.cli.validate_report import json_report

        report = json_report(result, Path(source).name, stack.kind)
        Path(staging).write_text(json.dumps(report, indent=1) + "\n")
        return messages


SCENE_SEED = "#seed="
"""Between the scene and the seed in a simulation's input name (``SCENE#seed=N``)."""


@dataclass
class SimulateJob:
    """``hbis simulate``'s work on one scene at one seed (the input ``SCENE#seed=N``): the stack,
    and with ``--with-truth`` its truth, moved whole to ``STEM.truth.tif`` before the stack is
    published, so that a stack a rerun finds has its truth."""

    args: argparse.Namespace
    simulate_one: Callable  # cmd_simulate.simulate_one (passed in: the command imports this module)

    def warm(self) -> None:
        """Import what a task needs (once per worker, before the first task)."""
        import hbis_torch.simulate  # noqa: F401

    def __call__(self, source, staging) -> list[str]:
        import os

        from hbis_torch.cluster.engine import output_of

        scene, _, seed = str(source).rpartition(SCENE_SEED)
        out = Path(output_of(staging))
        truth = None
        if self.args.with_truth:
            truth = truth_path(out)
            temporary = truth.with_name(f".{truth.name}.{os.getpid()}.tmp")
        self.simulate_one(self.args, scene, int(seed), Path(staging), temporary if truth else None, out.name)
        if truth:
            os.replace(temporary, truth)
        return []


def truth_path(out: Path) -> Path:
    """Where ``--with-truth`` puts the truth of the stack ``out`` (``STEM.truth.tif``)."""
    return out.with_name(out.name.removesuffix(".tif") + ".truth.tif")
