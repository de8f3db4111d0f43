"""The classical method on a whole stack: the ``"classical"`` entry of
:data:`hbis_torch.reconstruct.registry.METHODS` (grey stacks, and raw Bayer frames demosaicked
jointly)."""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from hbis_torch.errors import HbisInputError
from hbis_torch.reconstruct.classical.sr import classical_sr
from hbis_torch.reconstruct.classical.transfer import optics_cutoff
from hbis_torch.reconstruct.colour import LUMA, gray_stack
from hbis_torch.reconstruct.positions import check_registration, stack_sample_nodes, stack_sample_positions
from hbis_torch.sensor import bayer_masks, demosaic


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


def reconstruct_classical_raw_bayer(stack, registration: str = "auto", *, messages: list | None = None,
                                    deblur: bool = True, fill_factor: float | None = None, **kw) -> np.ndarray:
    """Classical SR of raw Bayer frames, each colour from its own samples at their own positions.

    Each plane is the normalized-convolution interpolation of its samples alone; the Wiener step
    is left out: it assumes a sample at every node of the h-times lattice, while a colour's
    samples fill only half (G) or a quarter (R, B) of it, in blocks, and deblurring those planes
    cost 6 to 11 dB (benchmarks/bench_colour.py, docs/capture.md). The ``raw_bayer`` path of the
    ``"classical"`` entry of :data:`hbis_torch.reconstruct.registry.METHODS`.

    Parameters
    ----------
    stack : hbis_torch.stack_io.Stack
        Raw Bayer frames (F, H, W) with a ``cfa`` key.
    registration, messages, deblur, fill_factor, **kw
        As for :func:`reconstruct_classical` (``deblur`` only decides whether a message says
        that the planes are not deblurred).

    Returns
    -------
    np.ndarray, shape (h*H, h*W, 3): the R, G and B planes

    References
    ----------
    .. [1] B. Wronski et al., "Handheld multi-frame super-resolution", ACM Transactions on
       Graphics 38(4), SIGGRAPH 2019.
    """
    if deblur and messages is not None:
        messages.append("raw Bayer frames: joint demosaicking interpolates each colour without the Wiener "
                        "deblurring (a colour's samples do not fill the lattice it assumes)")
    check_registration(registration)
    raw = stack.to_float()
    cfa = stack.meta["cfa"]
    luma = torch.from_numpy((demosaic(raw.numpy(), cfa) @ LUMA.astype(np.float32)).astype(np.float32))
    proxy = gray_stack(stack, luma.numpy())  # registration sees a demosaicked luminance, not a mosaic
    positions, trusted = stack_sample_positions(proxy, registration, exact=True, frames=luma, messages=messages)
    frame_weight = torch.ones(raw.shape[0], dtype=torch.float64)
    if registration == "data" and raw.shape[0] > 1:
        frame_weight = trusted.to(torch.float64)
    if fill_factor is None:
        fill_factor = stack_fill_factor(stack)
    masks = torch.from_numpy(bayer_masks(cfa, *raw.shape[1:])).to(torch.float64)
    planes = [classical_sr(raw, positions, stack.h, False, weights=frame_weight[:, None, None] * m[None],
                           cutoff=optics_cutoff(stack.system), fill_factor=fill_factor, **kw).numpy()
              for m in masks]
    return np.stack(planes, axis=-1)
