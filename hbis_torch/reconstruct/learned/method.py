"""The learned method on a whole stack: :func:`learned_sr`, and :func:`reconstruct_learned`,
the ``"learned"`` entry of :data:`hbis_torch.reconstruct.registry.METHODS`."""

from __future__ import annotations

import numpy as np

from hbis_torch.errors import HbisInputError
from hbis_torch.reconstruct.learned.runtime import LearnedSR
from hbis_torch.reconstruct.positions import stack_sample_positions


def learned_sr(stack, model=None, positions=None, threads: int | None = None,
               registration: str = "optics", messages: list | None = None,
               provider: str = "auto") -> np.ndarray:
    """Super-resolve a captured or simulated stack with an ONNX model (onnxruntime, no torch).

    Parameters
    ----------
    stack : hbis_torch.stack_io.Stack
    model : path, optional
        Defaults to the shipped model for the stack's h (:func:`default_model_path`).
    positions : array (F, H, W, 2), optional
        Sample positions in ROI-local reference LR pixels; by default the layer's policy
        (:func:`~hbis_torch.reconstruct.positions.stack_sample_positions`, node splines), in which
        the frames the registration could not trust keep their optical positions: the network
        needs every frame.
    threads : int, optional
        onnxruntime intra-op threads.
    registration : {"optics", "data", "auto"}
        Where the positions come from when they are not given. The default here is ``"optics"``
        (this function's behaviour from before registration was offered, and right for the
        simulated stacks its direct callers pass); :func:`hbis_torch.reconstruct.reconstruct`
        and ``hbis reconstruct`` default to ``"auto"`` (:mod:`hbis_torch.reconstruct.positions`).
    messages : list, optional
        Receives the registration's warnings.
    provider : {"auto", "openvino", "cpu"}
        onnxruntime execution provider (:func:`execution_providers`).

    Returns
    -------
    ndarray, shape (h H, h W), float32 in [0, 1]
    """
    runner = LearnedSR(model=model, h=None if model is not None else stack.h, threads=threads,
                       provider=provider)
    if runner.h != stack.h:
        raise HbisInputError(f"model {runner.path.name} is for h = {runner.h}, the stack has h = {stack.h}")
    frames = stack.to_float()
    if positions is None:
        positions, trusted = stack_sample_positions(stack, registration, frames=frames, messages=messages)
        if messages is not None and not bool(trusted.all()):
            messages.append(f"kept the optical positions of {int((~trusted).sum())} frame(s) the "
                            "registration could not trust")
    positions = np.asarray(positions.detach().cpu() if hasattr(positions, "detach") else positions)
    frames = np.asarray(frames.detach().cpu() if hasattr(frames, "detach") else frames)
    return runner(frames, positions)


def reconstruct_learned(stack, registration: str = "auto", *, model=None, messages: list | None = None,
                        threads: int | None = None, provider: str = "auto") -> np.ndarray:
    """The ``"learned"`` entry of :data:`hbis_torch.reconstruct.registry.METHODS` (``hbis reconstruct``).

    Unlike :func:`learned_sr`, the registration defaults to ``"auto"``, as for every method of
    :func:`hbis_torch.reconstruct.reconstruct`.
    """
    return learned_sr(stack, model=model, threads=threads, registration=registration, messages=messages,
                      provider=provider)
