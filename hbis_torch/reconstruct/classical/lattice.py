"""The samples' places on the h-times lattice, a batch of samples at a time: each sample's
nearest node (integers) and its offset from it (float32), which is all that the splat onto the
lattice (:func:`~hbis_torch.reconstruct.classical.splat.splat_on_lattice`) needs.

The HR coordinate of a sample is x = h (u + 0.5) - 0.5 (docs/design.md, section 1). Positions
given as spline nodes (:class:`~hbis_torch.optics.NodePositions`) are never summed in float64:
x = h c + C + h d for the pixel's column c, a float64 constant C per frame (its mean
displacement) and the float32 spline of the displacement's variation d
(:func:`~hbis_torch.optics.interpolate_displacements`), so only the small fractional part
frac(C) + h d is computed, in float32 (rounding about 1e-7 of it: some 1e-6 HR px).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

from hbis_torch.optics import NodePositions, interpolate_displacements
from hbis_torch.reconstruct.classical.splat import offset_from_sums


class NodeBatch(NamedTuple):
    """A batch of N samples and their nearest lattice nodes.

    Attributes
    ----------
    values : Tensor, shape (N,), float32
    col, row : Tensor, shape (N,), int32
        The nearest node (column, row), possibly outside the lattice.
    dx, dy : Tensor, shape (N,), float32
        Node minus sample position, HR px (within half a node).
    weights : Tensor, shape (N,), float32, or None
    reach : float
        The largest abs(dx) or abs(dy).
    """

    values: Tensor
    col: Tensor
    row: Tensor
    dx: Tensor
    dy: Tensor
    weights: Tensor | None
    reach: float = 0.0


def batch_slices(count: int, height: int, width: int, samples: int) -> list[tuple[slice, slice]]:
    """(frames, rows) slices of a (count, height, width) stack, of about ``samples`` samples at
    most: a band of rows of every frame, or where one row of every frame has more, one row of a
    few frames at a time.

    Bands, not whole frames: the frames of a scan or a burst overlay the same scene, so a band's
    samples meet the same few rows of the lattice, which the splat's scatter-adds then find in
    the cache. A full frame at h = 7, in process: the scatter-adds took 0.29 s against 0.76 s
    frame by frame, the gathers 0.23 s against 0.44 s, the classical method 4.4-4.6 s against
    5.3-5.5 s.
    """
    if count * width <= samples:
        rows = min(height, samples // (count * width))
        return [(slice(0, count), slice(r, r + rows)) for r in range(0, height, rows)]
    step = max(1, samples // width)
    return [(slice(k, k + step), slice(r, r + 1)) for r in range(height) for k in range(0, count, step)]


def every_nth_row(part: tuple[slice, slice], row_step: int) -> slice:
    """The rows of ``part`` (frames, rows) whose index in the frame is a multiple of ``row_step``,
    as a slice of the part's rows: the same rows whichever way the stack is cut in batches."""
    return slice((-(part[1].start or 0)) % row_step, None, row_step)


class _Axis(NamedTuple):
    """One axis of a batch's HR coordinates from the node splines (:func:`_spline_parts`): the
    coordinate less the pixel's h c is ``whole + rest``."""

    whole: Tensor  # (f, 1, 1) int32: the integer part of the per-frame constant
    rest: Tensor  # (f, rows, cols) float32: the constant's fractional part plus h times the variation
    variation: Tensor  # (f, rows, cols) float32: the spline of the displacement's variation, LR px
    mean: Tensor  # (f,) float64: the frame's mean displacement, LR px
    first: float  # the first pixel's LR coordinate


def _spline_parts(positions: NodePositions, part: tuple[slice, slice], h: int, offset: tuple[float, float],
                  row_step: int = 1) -> list[_Axis]:
    """Frames and rows ``part`` of the nodes' splines, per axis (x, then y), on the lattice whose
    nodes sit at ``offset`` (HR px) from the output grid's. Rows: those of ``part[1]`` that are
    multiples of ``row_step`` (:func:`every_nth_row`)."""
    rows = np.arange(positions.height)[part[1]][every_nth_row(part, row_step)]
    variation, mean = interpolate_displacements(positions._replace(values=positions.values[part[0]]), rows=rows)
    out = []
    for axis, first in enumerate((float(positions.u[0]), float(positions.v[0]))):
        constant = (first + mean[:, axis] + 0.5) * h - 0.5 - offset[axis]  # (f,) float64
        whole = torch.floor(constant)
        rest = torch.mul(variation[:, axis], h).add_((constant - whole).to(torch.float32)[:, None, None])
        out.append(_Axis(whole.to(torch.int32)[:, None, None], rest, variation[:, axis], mean[:, axis], first))
    return out


# Samples this close to halfway between two nodes (in float32's rest) have their node chosen from
# the float64 coordinate, as the code before lattice.py did: float32's rounding (1e-6 of the rest)
# could otherwise pick the other node, and exact ties (a frame on the pixel grid, a lattice
# offset of 0 at even h) would break the other way.
TIE_MARGIN = 1e-3


CLUSTERED = 0.7
"""A burst's samples whose phases in the reference's pixel have a resultant length (the circular
mean's, 1 for one phase) of at least this along an axis cluster within about 0.2 LR px of one
phase (a tripod's shake, a steady hand: phases uniform within +-0.22 px give 0.7). Their common
offset on the lattice, a scan's rule, would put every sample on one node in S along that axis and
leave the others to the hole fit; the output grid instead places the cluster about the
reference's phase (between two nodes at even S, on one at odd S), with samples on both sides of
every node. On development bursts (``training/eval_still_bursts.py --photos training --seeds 12 13
14 --spreads 0.15 0.2 0.3``: benchmarks/results/dev_clustered_bursts.json, 640 x 480, S = 2 to 4,
8 and 16 frames), it placed 24 of 36 bursts' lattices (all with shifts up to 0.15 or 0.2 px, one
of 0.3) and moved classical by -0.07 to +4.04 dB: from as low as 2.1 dB under bicubic to at least
0.75 dB over it. Shifts up to 0.3 px (resultant lengths about 0.35 to 0.77) moved by -0.36 to
+1.10 dB with the output grid (measured once, seeds 12 and 13), so the threshold sits above most
of them."""
PHASE_SAMPLES = 1 << 14
"""At most about this many samples of a batch's rows taken for the offset (evenly spaced among
them) have their phases in the reference's pixel read for :data:`CLUSTERED`: a sixteenth of the
cosines the offset's own sums take on a full batch (all of them doubled the offset's time, a few
hundredths of a second on 16 frames of 640 x 480); a burst's phases vary from frame to frame, not
sample to sample."""


def _nearest_node(axis: _Axis, pixel: Tensor, dim: int, h: int, shift: float) -> tuple[Tensor, Tensor, float]:
    """The nearest node (int32) along one axis of every sample of ``axis`` (frames, rows, cols),
    node minus sample (float32, HR px) and its largest magnitude; ``pixel`` (int32) is the
    samples' column (``dim`` 2) or row (``dim`` 1) indices, ``shift`` the lattice's offset
    along the axis."""
    nearest = torch.round(axis.rest)
    shape = [1, 1, 1]
    shape[dim] = -1
    node = nearest.to(torch.int32).add_(pixel.view(shape) * h + axis.whole)
    gap = nearest.sub_(axis.rest)
    low, high = torch.aminmax(gap)
    reach = max(-float(low), float(high))
    if reach > 0.5 - TIE_MARGIN:  # some samples near halfway (none where they sit near nodes)
        ties = torch.nonzero(gap.abs() > 0.5 - TIE_MARGIN, as_tuple=True)
        # the earlier float64 sum: variation + (pixel coordinate + mean), then x = (u + 0.5) h - 0.5
        place = axis.variation[ties].double() + ((axis.first + pixel[ties[dim]].double()) + axis.mean[ties[0]])
        coord = ((place + 0.5) * h - 0.5) - shift
        rounded = torch.round(coord)
        node[ties] = rounded.to(torch.int32)
        gap[ties] = (rounded - coord).to(torch.float32)
        reach = float(gap.abs().max())
    return node, gap, reach


def common_offset_of(positions, part_list, h: int, weights: Tensor | None, row_step: int,
                     mixed_offsets: bool = False) -> tuple[float, float]:
    """The samples' common sub-pixel offset (x, y) on the lattice, HR px, from every
    ``row_step``-th row of the batches ``part_list``: the circular mean of the coordinates'
    fractional parts (:func:`~hbis_torch.reconstruct.classical.splat.offset_from_sums`).

    With ``mixed_offsets`` (a burst), an axis along which the samples cluster in the reference's
    pixel (:data:`CLUSTERED`) keeps the output grid (offset 0) instead."""
    sums = [[0.0, 0.0, 0], [0.0, 0.0, 0]]
    pixel_sums = [[0.0, 0.0, 0], [0.0, 0.0, 0]]  # of the phases in the reference's pixel (mixed_offsets)
    height = positions.height if isinstance(positions, NodePositions) else positions.shape[1]
    for part in part_list:
        if not range(height)[part[1]][every_nth_row(part, row_step)]:
            continue  # a batch of rows none of which is taken
        keep = None
        if weights is not None:
            keep = weights[part][:, every_nth_row(part, row_step)].reshape(-1) > 0
        spline = taken = None
        if isinstance(positions, NodePositions):
            spline = _spline_parts(positions, part, h, (0.0, 0.0), row_step)
        else:  # only the rows taken (a burst's positions are computed where they are read)
            rows = range(height)[part[1]][every_nth_row(part, row_step)]
            taken = positions[part[0], slice(rows.start, rows.stop, rows.step)]
        for axis in (0, 1):
            if spline is not None:
                rest = spline[axis].rest.reshape(-1)
                rest = rest.sub_(torch.round(rest))  # the integer part adds nothing to the angle
            else:
                coord = (taken[..., axis].reshape(-1) + 0.5) * h - 0.5
                rest = coord.sub_(torch.round(coord)).to(torch.float32)
            _add_angles(sums[axis], rest, keep)
            if mixed_offsets and taken is not None:  # a spread of the batch's samples tells the cluster
                place = taken[..., axis].reshape(-1)
                step = max(1, place.numel() // PHASE_SAMPLES)
                _add_angles(pixel_sums[axis], place[::step].sub(torch.round(place[::step])).to(torch.float32),
                            None if keep is None else keep[::step])
    offset = [offset_from_sums(*sums[axis]) for axis in (0, 1)]
    for axis in (0, 1):
        cos_sum, sin_sum, count = pixel_sums[axis]
        if count and math.hypot(cos_sum, sin_sum) / count >= CLUSTERED:
            offset[axis] = 0.0
    return offset[0], offset[1]


def _add_angles(sums: list, rest: Tensor, keep: Tensor | None) -> None:
    """Adds the cosines and sines of 2 pi ``rest`` (float32, the fractional parts; those ``keep``
    marks, where given) and their count to ``sums`` ([cos, sin, count]), in float64."""
    if keep is not None:
        rest = rest[keep]
    # the fractional part in float32: its cosine and sine are the same to 1e-7, the sums in float64
    angle = rest.mul_(2 * math.pi)
    sums[0] += float(torch.cos(angle).sum(dtype=torch.float64))
    sums[1] += float(torch.sin(angle).sum(dtype=torch.float64))
    sums[2] += angle.numel()


def node_batch(frames: Tensor, positions, part: tuple[slice, slice], h: int, offset: tuple[float, float],
               weights: Tensor | None = None) -> NodeBatch:
    """The samples of frames and rows ``part`` (:func:`batch_slices`) on the lattice whose
    nodes sit at ``offset`` (HR px) from the output grid's.

    Parameters
    ----------
    frames : Tensor, shape (F, H, W)
    positions : Tensor, shape (F, H, W, 2), float64, or NodePositions or BurstPositions
        The samples' ROI-local reference LR coordinates (or the nodes they are interpolated from,
        or a burst's motions: ``positions[part]`` computes the part's).
    part : (slice, slice)
    h : int
    offset : (float, float)
    weights : Tensor, shape (F, H, W), optional

    Returns
    -------
    NodeBatch
    """
    cols = torch.arange(frames.shape[2], dtype=torch.int32)
    rows = torch.arange(frames.shape[1], dtype=torch.int32)[part[1]]
    if not isinstance(positions, NodePositions):
        nodes, gaps, reach = _nodes_of_positions(positions, part, frames.shape, h, offset)
    else:
        spline = _spline_parts(positions, part, h, offset)
        nodes, gaps, reach = [], [], 0.0
        for axis, (pixel, dim) in enumerate(((cols, 2), (rows, 1))):
            node, gap, far = _nearest_node(spline[axis], pixel, dim, h, offset[axis])
            nodes.append(node.reshape(-1))
            gaps.append(gap.reshape(-1))
            reach = max(reach, far)
    values = frames[part].reshape(-1).to(torch.float32)
    w = None if weights is None else weights[part].reshape(-1).to(torch.float32)
    return NodeBatch(values, nodes[0], nodes[1], gaps[0], gaps[1], w, reach)


#: Samples of a batch whose positions and nearest nodes :func:`_nodes_of_positions` computes at a
#: time: each piece's float64 temporaries (512 kB an axis) stay in the cache through the ten or
#: so passes over them, and no batch-sized temporary is made.
PIECE_SAMPLES = 1 << 16


def _nodes_of_positions(positions, part: tuple[slice, slice], shape: tuple, h: int,
                        offset: tuple[float, float]) -> tuple[list, list, float]:
    """:func:`node_batch`'s nearest nodes ([col, row], int32 (N,) each), gaps ([dx, dy], float32
    (N,) each) and reach of the samples of ``part`` whose positions (a tensor or a
    :class:`~hbis_torch.reconstruct.positions.BurstPositions`) are read a piece of a frame's rows
    at a time (:data:`PIECE_SAMPLES`): the same operations on each sample, so the same bits as
    the whole batch's, in a third less time."""
    count, height, width = shape[:3]
    frame_ids = range(count)[part[0]]
    row_ids = range(height)[part[1]]
    step = max(1, PIECE_SAMPLES // max(width, 1))
    size = len(frame_ids) * len(row_ids) * width
    nodes = [torch.empty(size, dtype=torch.int32) for _ in range(2)]
    gaps = [torch.empty(size, dtype=torch.float32) for _ in range(2)]
    reach, start = 0.0, 0
    for k in frame_ids:
        for first in range(0, len(row_ids), step):
            piece = row_ids[first:first + step]
            where = positions[k, slice(piece.start, piece.stop, piece.step)]
            stop = start + where.shape[0] * where.shape[1]
            for axis in (0, 1):
                # ((u + 0.5) h - 0.5) - offset in one float64 array written in place, and the gap
                # nearest - coord over it (the same bits as the expression's temporaries)
                coord = torch.add(where[..., axis], 0.5).mul_(h).sub_(0.5).sub_(offset[axis])
                nearest = torch.round(coord)
                gap = gaps[axis][start:stop]
                gap.copy_(torch.sub(nearest, coord, out=coord).reshape(-1))
                if gap.numel():
                    low, high = torch.aminmax(gap)
                    reach = max(reach, -float(low), float(high))
                # beyond the lattice by more than a node is as good as anywhere beyond it (and fits int32)
                nodes[axis][start:stop].copy_(nearest.clamp_(-2, 1 << 30).reshape(-1))
            start = stop
    return nodes, gaps, reach
