"""The classical method on a whole stack: the ``"classical"`` entry of
:data:`hbis_torch.reconstruct.registry.METHODS`."""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from hbis_torch.errors import HbisInputError
from hbis_torch.reconstruct.classical.sr import classical_sr
from hbis_torch.reconstruct.classical.transfer import optics_cutoff
from hbis_torch.reconstruct.positions import check_registration, stack_sample_nodes


def _stack_frames(stack) -> Tensor:
    frames = stack.to_float()
    if frames.ndim != 3:
        raise HbisInputError(f"the stack's frames must be (F, H, W), got {tuple(frames.shape)}")
    return frames


def stack_fill_factor(stack) -> float:
    """The sensor's fill factor recorded in a stack's JSON (``sensor.fill_factor``, or the
    simulator's ``simulation.sensor.fill_factor``), else 1."""
    for block in (stack.meta.get("sensor"), (stack.meta.get("simulation") or {}).get("sensor")):
        if isinstance(block, dict) and "fill_factor" in block:
            value = block["fill_factor"]
            if isinstance(value, (int, float)) and not isinstance(value, bool) and 0 < value <= 1:
                return float(value)
            raise HbisInputError(f"the stack's fill_factor must be a number in (0, 1], got {value!r}")
    return 1.0


def reconstruct_classical(stack, registration: str = "auto", *, deblur: bool = True,
                          messages: list | None = None, fill_factor: float | None = None,
                          **kw) -> np.ndarray:
    """Classical super-resolution of a stack (see :func:`hbis_torch.reconstruct.reconstruct`).

    The samples' positions follow the layer's policy
    (:func:`~hbis_torch.reconstruct.positions.stack_sample_positions`, node splines, evaluated a
    few frames at a time: :func:`~hbis_torch.reconstruct.positions.stack_sample_nodes`);
    with ``registration="data"`` the frames the registration could not trust get weight 0 (left
    out, with a message), with ``"auto"`` they are used at their optical positions.

    Parameters
    ----------
    stack : hbis_torch.stack_io.Stack
    registration : {"optics", "data", "auto"}
    deblur : bool
        Apply the Wiener deblurring (:func:`classical_sr`).
    messages : list, optional
        Receives the registration's warnings.
    fill_factor : float, optional
        Default: the stack's own (:func:`stack_fill_factor`).
    **kw
        :func:`classical_sr`'s keywords.

    Returns
    -------
    np.ndarray, shape (h*H, h*W), float32 in [0, 1]
    """
    check_registration(registration)
    frames = _stack_frames(stack)
    positions, trusted = stack_sample_nodes(stack, registration, frames=frames, messages=messages)
    weights = None
    if registration == "data" and frames.shape[0] > 1:
        weights = trusted.to(torch.float64)
        if messages is not None and not bool(trusted.all()):
            messages.append(f"left out {int((~trusted).sum())} frame(s) the registration could not trust")
    if fill_factor is None:
        fill_factor = stack_fill_factor(stack)
    image = classical_sr(frames, positions, stack.h, deblur, weights=weights,
                         cutoff=optics_cutoff(stack.system), fill_factor=fill_factor, **kw)
    return image.numpy()
