"""Subsets of a stack's frames: :func:`select_frames`, and which frames cross-validation holds
out (:func:`holdout_frames`)."""

from __future__ import annotations

import copy

import numpy as np

from hbis_torch.errors import HbisInputError

#: Meta keys that hold one entry per frame (scan stacks: phases; bursts: the registration's).
PER_FRAME_KEYS = ("phases_deg", "motions", "confidence", "motion_models", "gain_offset")


def _kept_indices(count: int, reference: int, keep) -> list[int]:
    try:
        wanted = [int(k) for k in np.atleast_1d(np.asarray(keep)).ravel()]
    except (TypeError, ValueError):
        raise HbisInputError(f"keep must be frame indices, got {keep!r}") from None
    bad = [k for k in wanted if not -count <= k < count]
    if bad:
        raise HbisInputError(f"frame index {bad[0]} is not one of the stack's {count} frames (0..{count - 1})")
    return sorted({k % count for k in wanted} | {reference})


def select_frames(stack, keep):
    """The stack of frames ``keep`` only, the reference frame always among them.

    Every per-frame entry of the JSON (:data:`PER_FRAME_KEYS` that the stack has: ``phases_deg``
    of a scan stack; ``motions``, ``confidence``, ``motion_models``, ``gain_offset`` of a burst,
    and its ``local_motion.offsets``; the simulator's ``simulation.true_phases_deg``) is cut to
    the same frames, and ``reference_index`` points at the reference frame in the new order. The
    frames stay in the stack's order and keep the reference frame's grid, so a reconstruction of
    the subset lies on the same output grid as one of the whole stack.

    Parameters
    ----------
    stack : hbis_torch.stack_io.Stack
        F frames, (F, H, W) or (F, H, W, 3).
    keep : iterable of int
        Indices of the frames to keep (negative ones count from the end; repeats are ignored).

    Returns
    -------
    hbis_torch.stack_io.Stack
        A new stack (frames copied, JSON deep-copied) of the kept frames, validated.

    Raises
    ------
    HbisInputError
        An index outside the stack.

    Examples
    --------
    >>> import numpy as np
    >>> from hbis_torch import FoveaSystem
    >>> from hbis_torch.scan.plan import plan_scan
    >>> from hbis_torch.stack_io import Stack, make_meta
    >>> system = FoveaSystem()
    >>> plan = plan_scan(system, 2)
    >>> meta = make_meta(system, 2, (600, 400, 8, 6), plan.phases_deg, reference_index=plan.reference_index)
    >>> stack = Stack(np.zeros((4, 6, 8), np.uint8), meta)
    >>> part = select_frames(stack, [0, 1])   # the reference, frame 3, joins
    >>> len(part.frames), part.reference_index, part.phases_deg.tolist() == plan.phases_deg[[0, 1, 3]].tolist()
    (3, 2, True)
    """
    count = len(stack.frames)
    reference = stack.reference_index
    kept = _kept_indices(count, reference, keep)
    meta = copy.deepcopy(stack.meta)
    for key in PER_FRAME_KEYS:
        if key in meta:
            _cut(meta, key, kept, count)
    simulation = meta.get("simulation")
    if isinstance(simulation, dict) and "true_phases_deg" in simulation:
        _cut(simulation, "true_phases_deg", kept, count)
    local = meta.get("local_motion")  # a burst's local shifts, each frame's grid of tiles
    if isinstance(local, dict) and "offsets" in local:
        _cut(local, "offsets", kept, count)
    meta["reference_index"] = kept.index(reference)
    return type(stack)(np.ascontiguousarray(stack.frames[kept]), meta).validate("selected frames")


def _cut(block: dict, key: str, kept: list[int], count: int) -> None:
    values = block[key]
    if not isinstance(values, (list, tuple)) or len(values) != count:
        raise HbisInputError(f"the stack's {key} must have one entry per frame ({count})")
    block[key] = [values[k] for k in kept]


def holdout_frames(count: int, reference: int, holdout: int, trusted=None) -> list[int]:
    """Which frames cross-validation leaves out, one at a time: ``holdout`` frames spread evenly
    over the stack's order, never the reference; frames whose positions the registration could
    not trust (``trusted`` False) only when there are too few others.

    Parameters
    ----------
    count : int
        Frames in the stack.
    reference : int
        The reference frame's index.
    holdout : int
        How many frames to hold out, 1 to count - 1.
    trusted : sequence of bool, optional
        Per frame: can its sample positions be trusted.

    Returns
    -------
    list of int
        Sorted frame indices (deterministic).

    Examples
    --------
    >>> holdout_frames(16, 10, 3)
    [2, 7, 13]
    >>> holdout_frames(4, 3, 3)
    [0, 1, 2]
    """
    if count < 2:
        raise HbisInputError("cross-validation needs a stack of at least 2 frames (one to hold out, the "
                             "reference to keep)")
    if not 1 <= holdout <= count - 1:
        raise HbisInputError(f"holdout must be from 1 to {count - 1} (the frames besides the reference), "
                             f"got {holdout}")
    others = [k for k in range(count) if k != reference]
    if trusted is not None:
        good = [k for k in others if bool(trusted[k])]
        others = good + [k for k in others if k not in good] if len(good) < holdout else good
    chosen = [others[int(round((i + 0.5) * len(others) / holdout - 0.5))] for i in range(holdout)]
    return sorted(set(chosen))
