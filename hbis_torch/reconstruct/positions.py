"""Where every sample of a stack lies on the reference frame's grid: one policy for every method.

**Policy: the optics, corrected by registration where the data is trusted.**

1. *The optics.* Sample (u, v) of frame k sees the object point its chief ray lands on at the
   frame's phases; the reference frame would image that point at
   ``sensor_position(system, point, phi_ref)``. :func:`hbis_torch.optics.sample_positions`
   computes this (docs/design.md, section 1), either tracing every pixel (``exact=True``, the
   contract's definition) or tracing nodes 32 px apart and interpolating with cubic splines
   (``exact=False``, the default of both methods: < 1e-6 px from the exact trace, and a
   full frame's positions in about a second instead of half a minute; tests/test_fullframe.py
   checks both the positions and the classical output against the exact trace).
   The stack's own ROI is traced, so a corner ROI gets the corner's geometry.
2. *The registration* (``"data"`` or ``"auto"``, stacks of more than one frame).
   :func:`~hbis_torch.registration.register_stack` measures each frame's homography H_k,
   starting from the optics' prediction P_k (a homography fitted to the traced positions); the
   data's correction C_k = H_k P_k^-1 is applied to the traced per-pixel positions, which keeps
   the optics' non-homographic part. (With ``exact=False`` the correction is applied on the
   nodes, before the one interpolation to every pixel: C_k is smooth too.
   :func:`stack_sample_nodes` stops at the nodes, for callers that interpolate a few frames at
   a time: the classical method, whose full-frame stacks' positions would take a gigabyte.)
3. *Untrusted frames* (those the registration cannot trust) keep their optical positions, and
   :func:`stack_sample_positions` says which frames those are (``trusted``). What to do with
   them is each method's own policy:

   * classical, ``"data"``: weight 0, i.e. left out of the reconstruction (message "left out N
     frame(s) the registration could not trust"); ``"auto"``: used at their optical positions,
     without a message.
   * learned: as the classical method, since it refines the classical image.

Burst stacks (``stack.kind == "burst"``) have no optics: their positions are the measured
``motions`` (homographies frame px -> reference px, found by ``hbis assemble --burst``) applied
to every pixel (:func:`burst_positions`), and the frames with a confidence of at least
:data:`BURST_MIN_CONFIDENCE` are the trusted ones; ``registration`` does not apply to them.

Defaults. :func:`hbis_torch.reconstruct.reconstruct`, ``hbis reconstruct --registration`` and both
methods' registry entries default to ``"auto"``: a captured stack's phases are only what the
motors were asked for, and "auto" corrects them where the data allows without dropping frames.
:func:`hbis_torch.reconstruct.learned.learned_sr`, the learned method's library call, keeps its
older default ``"optics"``: that is what it did before registration was offered, and its direct
callers (benchmarks, tests, training evaluation) pass simulated stacks whose phases are the true
ones, for which the tracer is exact and registration only costs time.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from hbis_torch.errors import HbisInputError
from hbis_torch.optics import interpolate_positions, node_positions, sample_positions
from hbis_torch.stack_io import BURST_MIN_CONFIDENCE

# Where the samples' positions come from (see the module docstring).
REGISTRATIONS = ("optics", "data", "auto")

# The exact tracer keeps some 200 bytes of temporaries per sample: larger stacks (a full frame
# at h = 4 and above) are traced a few frames per call, so that memory stays near 1 GB.
EXACT_SAMPLES_PER_CALL = 1 << 22
#: A burst's positions (16 bytes a sample) are kept once computed up to this size (256 MB:
#: 16 frames of 1 MP); larger bursts compute them where read (:class:`BurstPositions`).
CACHE_BYTES = 1 << 28
#: Whole frames' positions are computed this many samples at a time (:meth:`BurstPositions._band`).
PIECE_SAMPLES = 1 << 16


class BurstPositions:
    """Where the samples of a burst lie on the reference grid, computed a band at a time.

    A burst's positions are each frame's homography (and local shifts) applied to its pixel
    centres: 16 bytes a sample in float64, 3 GB for 16 frames of 12 MP. This object holds the
    motions alone and computes the positions of the frames and rows asked for, with the same
    bits as the whole array (:meth:`whole`): ``positions[k]`` is frame k's (H, W, 2),
    ``positions[frames, rows]`` (two slices, any step) the band's (f, r, W, 2), float64.
    The burst path (:func:`hbis_torch.reconstruct.burst.burst_samples` with ``lazy=True``) and
    the classical method's lattice take it wherever they take a positions tensor.

    A burst whose positions take at most :data:`CACHE_BYTES` (16 frames of up to 1 MP) keeps
    each frame's once computed, and reads after the first are views of them: the burst path
    reads every frame's positions three times and more (the robustness, the lens estimate's
    windows, the lattice's offset and its batches), which on a 640 x 480 burst was a sixth of
    the classical path's time. The bits are the same either way. Reads are not to be written
    to (none of the project's readers does: each makes its own coordinates from them).

    Parameters
    ----------
    motions : np.ndarray, shape (F, 3, 3), float64
        Frame px -> reference px.
    height, width : int
        The frames' size, px.
    offsets : Tensor, shape (F, rows, cols, 2), float64, or None
        Local shifts on top of each motion (:mod:`hbis_torch.registration.local`).
    tile : int
        Their tiles' side, px.
    keep : bool
        Keep a small burst's frames once computed (default); False computes every read afresh,
        for a reader of a few bands (a whole frame's positions are not made for them).
    """

    dtype = torch.float64
    #: What the classical method checks for (it does not import this package's modules).
    computed_where_read = True

    def __init__(self, motions: np.ndarray, height: int, width: int, offsets: Tensor | None = None,
                 tile: int = 32, keep: bool = True):
        self.motions = torch.as_tensor(np.asarray(motions, dtype=np.float64))
        self.offsets, self.tile = offsets, int(tile)
        self.shape = (len(self.motions), int(height), int(width), 2)
        count = self.shape[0] * self.shape[1] * self.shape[2]
        # each frame's positions once computed (small bursts: CACHE_BYTES; allocated at the first
        # read), and which frames they are
        self._keep, self._kept = keep and 16 * count <= CACHE_BYTES, None
        self._done = [False] * self.shape[0]

    def __len__(self) -> int:
        return self.shape[0]

    def __getitem__(self, index) -> Tensor:
        """``positions[frames]``, ``positions[frames, rows]`` or ``positions[frames, rows, cols]``,
        each an int or a slice (only those computed), as the whole array's indexing gives them."""
        index = index if isinstance(index, tuple) else (index,)
        if len(index) > 3 or not all(isinstance(i, (slice, int, np.integer)) for i in index):
            raise TypeError("BurstPositions takes up to three indices (frames, rows, columns), each an int or a slice")
        index = index + (slice(None),) * (3 - len(index))
        # ints as one-long slices, dropped again after
        as_slices = [slice(int(i), int(i) + 1 or None) if not isinstance(i, slice) else i for i in index]
        count, height, width, _ = self.shape
        for i, size in zip(index, (count, height, width)):
            if not isinstance(i, slice) and not -size <= int(i) < size:
                raise IndexError(f"index {int(i)} is out of bounds for size {size}")
        if self._keep:
            out = self._cached(*as_slices)
        else:
            out = self._band(as_slices[0], as_slices[1], as_slices[2])
        drop = tuple(0 if not isinstance(i, slice) else slice(None) for i in index)
        return out[drop]

    def _cached(self, frames: slice, rows: slice, cols: slice) -> Tensor:
        """The band from the kept frames (a view), computing the frames not yet kept, whole."""
        if self._kept is None:
            self._kept = torch.empty(self.shape, dtype=torch.float64)
        for k in range(self.shape[0])[frames]:
            if not self._done[k]:
                self._band(slice(k, k + 1), slice(None), out=self._kept[k:k + 1])
                self._done[k] = True
        return self._kept[frames, rows, cols]

    def _band(self, frames: slice, rows: slice, cols: slice = slice(None), out: Tensor | None = None) -> Tensor:
        """The positions of ``frames``, ``rows`` and ``cols``, (f, r, c, 2) float64, written into
        ``out`` if given (a kept frame's memory: no copy)."""
        from hbis_torch.registration import apply_homography_to_grid
        from hbis_torch.registration.local import add_offsets

        count, height, width, _ = self.shape
        picked = torch.arange(height, dtype=torch.float64)[rows]
        across = torch.arange(width, dtype=torch.float64)[cols]
        chosen = range(count)[frames]
        step = max(1, PIECE_SAMPLES // max(len(across), 1))
        if len(picked) <= step or len(across) != width:  # a band: at once
            positions = apply_homography_to_grid(self.motions[frames], picked, across, out=out)
            if self.offsets is not None:  # the smooth field of shifts on top of each homography
                add_offsets(self.offsets[frames], positions, self.tile)
            return positions
        # Whole frames a piece of rows at a time into the result: each pixel's sums are the
        # same, and the pieces' temporaries stay small (no 12 MP frame's 96 MB grid and field
        # in fresh pages) and in the cache.
        if out is None:
            out = torch.empty((len(chosen), len(picked), width, 2), dtype=torch.float64)
        for i, k in enumerate(chosen):
            for first in range(0, len(picked), step):
                piece = out[i:i + 1, first:first + step]
                apply_homography_to_grid(self.motions[k:k + 1], picked[first:first + step], across, out=piece)
                if self.offsets is not None:
                    add_offsets(self.offsets[k:k + 1], piece, self.tile)
        return out

    def whole(self) -> Tensor:
        """Every sample's position, (F, H, W, 2) float64: what the object stands for (a
        tensor of its own, which the caller may change)."""
        if self._keep:
            return self._cached(slice(None), slice(None), slice(None)).clone()
        return self._band(slice(None), slice(None))


def burst_positions(stack, lazy: bool = False) -> tuple[Tensor | BurstPositions, Tensor]:
    """Where every sample of a burst stack lies on the reference frame's grid.

    Parameters
    ----------
    stack : hbis_torch.stack_io.Stack
        A burst (``stack.kind == "burst"``).
    lazy : bool
        Return a :class:`BurstPositions`, which computes them a band at a time, instead of
        the whole array.

    Returns
    -------
    positions : Tensor, shape (F, H, W, 2), float64, or BurstPositions
        (u, v) of every sample in the reference frame's LR pixel coordinates: the frame's
        homography (``stack.motions``) applied to its pixel centres, plus the stack's local
        shifts there where it has them (``local_motion``, :mod:`hbis_torch.registration.local`).
    trusted : Tensor, shape (F,), bool
        Frames whose confidence is at least :data:`BURST_MIN_CONFIDENCE` (the reference always).
    """
    count, height, width = stack.frames.shape[:3]
    local = stack.meta.get("local_motion")
    offsets = None if local is None else torch.tensor(local["offsets"], dtype=torch.float64)
    positions = BurstPositions(stack.motions, height, width, offsets, 32 if local is None else int(local["tile_px"]))
    trusted = torch.from_numpy(stack.confidence >= BURST_MIN_CONFIDENCE)
    trusted[stack.reference_index] = True
    return (positions if lazy else positions.whole()), trusted


def check_registration(registration: str) -> str:
    """``registration`` if it is one of :data:`REGISTRATIONS`, else HbisInputError."""
    if registration not in REGISTRATIONS:
        raise HbisInputError(f"registration must be one of {REGISTRATIONS}, got {registration!r}")
    return registration


def optical_positions(stack, exact: bool = False) -> Tensor:
    """Where the optics put every sample of a stack: :func:`hbis_torch.optics.sample_positions`.

    Parameters
    ----------
    stack : hbis_torch.stack_io.Stack
    exact : bool
        Trace every pixel (a few frames per call for large stacks, each call with the reference
        frame's phases appended, which gives the same bits as one call); False traces nodes
        32 px apart and interpolates with cubic splines (< 1e-6 px from the exact trace).

    Returns
    -------
    Tensor, shape (F, H, W, 2), float64
        (u, v) in the reference frame's ROI-local LR pixel coordinates.
    """
    system, phases, ref, roi = stack.system, stack.phases_deg, stack.reference_index, stack.roi
    if not exact:
        return sample_positions(system, phases, ref, roi)
    phases = np.asarray(phases, dtype=np.float64)
    step = max(1, EXACT_SAMPLES_PER_CALL // max(1, int(roi[2]) * int(roi[3])))
    if step >= len(phases):
        return sample_positions(system, phases, ref, roi, exact=True)
    parts = []
    for start in range(0, len(phases), step):
        chunk = np.concatenate((phases[start:start + step], phases[ref:ref + 1]))
        parts.append(sample_positions(system, chunk, len(chunk) - 1, roi, exact=True)[:-1])
    return torch.cat(parts)


def optical_sample_positions(stack) -> Tensor:
    """Where every sample of every frame lies in the reference frame, from the exact tracer.

    Sample (u, v) of frame k sees the object point ``landing_map(system, phi_k, roi)[v, u]``;
    the reference frame would image that point at ``sensor_position(system, point, phi_ref)``.
    (The optics part of the policy with ``exact=True``: :func:`optical_positions`.)

    Parameters
    ----------
    stack : hbis_torch.stack_io.Stack

    Returns
    -------
    Tensor, shape (F, H, W, 2), float64
        (u, v) in the reference frame's ROI-local LR pixel coordinates.
    """
    return optical_positions(stack, exact=True)


def stack_sample_positions(stack, registration: str = "auto", *, exact: bool = False,
                           frames: Tensor | None = None,
                           messages: list | None = None) -> tuple[Tensor, Tensor]:
    """The sample positions of a stack under the layer's one policy (module docstring).

    Parameters
    ----------
    stack : hbis_torch.stack_io.Stack
    registration : {"optics", "data", "auto"}
        ``"optics"``: the tracer alone. ``"data"`` and ``"auto"``: the tracer corrected by
        registering the frames, for the frames the registration trusts (the two differ only in
        what the method does with the others).
    exact : bool
        Trace every pixel, or nodes and cubic splines (both methods' default); see
        :func:`optical_positions`.
    frames : Tensor, shape (F, H, W), optional
        The stack's frames as ``stack.to_float()`` gives them, if the caller has them already
        (only the registration reads them).
    messages : list, optional
        Receives the registration's warnings, one string each.

    Returns
    -------
    positions : Tensor, shape (F, H, W, 2), float64
        (u, v) of every sample in the reference frame's ROI-local LR pixel coordinates;
        untrusted frames keep their optical positions.
    trusted : Tensor, shape (F,), bool
        Frames whose positions the registration corrected (all True for ``"optics"`` and for
        one-frame stacks).
    """
    check_registration(registration)
    if getattr(stack, "kind", "hbis") == "burst":
        return burst_positions(stack)
    if not exact:
        nodes, trusted = stack_sample_nodes(stack, registration, frames=frames, messages=messages)
        return interpolate_positions(nodes), trusted
    positions = optical_positions(stack, exact)
    count = positions.shape[0]
    if registration == "optics" or count == 1:
        return positions, torch.ones(count, dtype=torch.bool)
    from hbis_torch.registration import apply_homography, homographies_from_positions

    predicted = homographies_from_positions(positions)
    correction, ok = _registration_correction(stack, frames, predicted, messages)
    corrected = apply_homography(correction, positions.reshape(count, -1, 2)).reshape(positions.shape)
    return torch.where(ok[:, None, None, None], corrected, positions), ok


def _registration_correction(stack, frames, predicted: Tensor, messages) -> tuple[Tensor, Tensor]:
    """The data's correction C_k = H_k P_k^-1 (F, 3, 3) of the optics' homographies
    ``predicted`` (P_k), and which frames the registration trusts (F,), bool."""
    from hbis_torch.registration import register_stack

    if frames is None:
        frames = stack.to_float()
    reg = register_stack(frames, stack.reference_index, prediction=predicted)
    if messages is not None:
        messages.extend(reg.messages)
    return reg.homographies @ torch.linalg.inv(predicted), reg.ok


def stack_sample_nodes(stack, registration: str = "auto", *, frames: Tensor | None = None,
                       messages: list | None = None):
    """:func:`stack_sample_positions` (``exact=False``) on the spline nodes only: every pixel's
    position is ``interpolate_positions(nodes)``, which a caller may evaluate a few frames at a
    time (``nodes._replace(values=nodes.values[part])``) instead of holding the whole stack's
    (16 bytes a sample: about 1 GB for a full frame at h = 7).

    The optics' prediction is fitted to the same pixels as with ``exact=True``
    (:func:`~hbis_torch.registration.fit_grid`, evaluated from the nodes), so the registration
    starts from the same homographies; its correction is then applied to the nodes.

    Parameters
    ----------
    stack, registration, frames, messages
        As :func:`stack_sample_positions`'s.

    Returns
    -------
    nodes : hbis_torch.optics.NodePositions
        ``values`` (F, n_v, n_u, 2), float64: (u, v) in the reference frame's ROI-local LR
        pixel coordinates of the samples at the nodes, corrected where trusted.
    trusted : Tensor, shape (F,), bool
    """
    check_registration(registration)
    nodes = node_positions(stack.system, stack.phases_deg, stack.reference_index, stack.roi)
    count = nodes.values.shape[0]
    if registration == "optics" or count == 1:
        return nodes, torch.ones(count, dtype=torch.bool)
    from hbis_torch.registration import (
        apply_homography,
        fit_grid,
        homographies_from_grid,
    )

    rows, cols = fit_grid(nodes.height, nodes.width)
    on_grid = interpolate_positions(nodes, rows.numpy(), cols.numpy())
    predicted = homographies_from_grid(on_grid, rows, cols, nodes.height, nodes.width)
    correction, ok = _registration_correction(stack, frames, predicted, messages)
    values = nodes.values
    corrected = apply_homography(correction, values.reshape(count, -1, 2)).reshape(values.shape)
    values = torch.where(ok[:, None, None, None], corrected, values)
    return nodes._replace(values=values), ok
