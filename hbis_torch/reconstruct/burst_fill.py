"""The burst's samples tallied on the output lattices: the coverage, the fill and the scale to run at.

:func:`~hbis_torch.reconstruct.burst.reconstruct_burst` hands every frame's positions and weights
to a :class:`Tally` as the robustness weights are made (each frame's positions once). It adds up
how much the other frames put into each reference pixel (the *coverage*, which the output's blend
with the single frame follows) and which nodes of the S-times lattices samples land on (the *fill*,
:func:`scale_to_run`: a burst whose samples leave whole sub-pixel phases empty runs at a coarser
scale, or leans on the single frame). A still frame (a tripod's) brings no new phase: where most
frames are still their samples count as the reference's (:data:`STILL_SPACING`).

Positions (H, W, 2) float64 in the reference's LR px; weights (H, W) in [0, 1].
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

from hbis_torch.notices import act

# Share of the output lattice's nodes near a pixel that samples land on: below NO_FILL the output is
# the single-frame estimate, from FULL_FILL up the method's alone.
NO_FILL, FULL_FILL = 0.4, 0.8
# A burst is reconstructed at the largest scale (from S down to 2) where the mean of that share
# reaches this (:func:`scale_to_run`). A method's burst function with an attribute ``fill_blend_to``
# gets the fill's blend only for bursts asked at scales up to it (the classical method's: 2), or
# where no scale's lattice reaches RUN_FILL; above it, the run scale's choice guards the lattice (it
# is filled on average) and the coverage's blend the frame's edges. On the training simulator
# (photographs, 640 x 480, lens blur 0.3 LR px given / estimated, shifts to 2 px and turns to
# 0.5 deg, 3 seeds) leaving it out there gained the classical method +1.15 / +0.88 dB at S = 3 with
# F = 8, +0.10 / +0.11 with F = 16, +0.92 / +0.88 and +1.00 / +1.00 at S = 4 with F = 8 and 16, and
# +0.6 to +1.0 dB at S = 3 with F = 4 (run at S = 2), never less; with shifts alone (whole sub-pixel
# phases empty) +0.03 to +1.05 dB in every burst: the deblurred lattice beats its blend with the
# enlarged reference even where a third of the nodes are empty. At S = 2 itself it is kept: on
# 40 x 40 px bursts of 3 to 6 frames it gains 0.4 to 1.1 dB (benchmarks/bench_few_frames.py).
RUN_FILL = 0.5
# In a burst whose frames are at least STILL_BURST_SHARE still (a tripod's: STILL_FRAME_SHARE of a
# frame's samples within STILL_SPACING of the S lattice's node spacing of the reference's, both
# axes), the still frames' samples count for the fill as landing on the reference's nodes. At even
# S the reference's samples lie halfway between nodes, and a still frame's fell on either side by
# their noise and seemed to fill every node: the lattice was deblurred from one phase. On the
# training simulator (photographs, 640 x 480, S = 2, 8 frames) frames still to 0.0 / 0.1 LR px gave
# 1.25 / 0.70 dB under the single frame, with it +0.00 / +0.17. A few still frames among moving ones
# count where they land, as before: the rule is for bursts that hardly moved (applied to every still
# frame, it moved the held-out hand-held cells that hold one to three by -0.25 to +0.14 dB). Those
# figures, and the spacing of 0.2 they chose, predate the clustered shifts' lattice placement
# (classical.lattice.CLUSTERED), which mended much of the same failure: since, a burst whose frames
# moved 0.05 to 0.1 LR px gains over the single frame, and 0.2 gave it the single frame. On
# development bursts (training/eval_still_bursts.py --photos training --seeds 12 13 14 --spreads 0
# 0.02 0.05 0.1 --no-learned --still-spacings 0.1 0.05 0.02: benchmarks/results/dev_still_spacing.json,
# 640 x 480, S = 2 to 4, 48 bursts) classical - bicubic averaged +0.17 / +0.48 / +0.60 / +0.60 dB at
# spacings 0.2 / 0.1 / 0.05 / 0.02, none under it, and +0.64 with no rule at all; but small bursts of
# frames that did not move at all still need it (the tests' 40 px camera image, six identical frames,
# noise 0.005, S = 2 to 4, three seeds: with no rule 0.02 to 0.65 dB under the single frame in seven
# of nine, measured once). 0.05 keeps 0.02's figures (two bursts differ, by up to 0.2 dB) with more
# room for a still frame's registration error: 0.025 LR px at S = 2, 0.0125 at S = 4.
STILL_SPACING, STILL_FRAME_SHARE, STILL_BURST_SHARE = 0.05, 0.9, 0.5
# The raw path (:func:`still_run_scale`) splats on the output grid and has no such placement: without
# its rule, bursts that moved up to 0.1 LR px at S = 2 fell 0.8 to 1.0 dB under the demosaicked
# reference (benchmarks/results/eval_still_bursts_raw.json), and each colour's samples lie two
# pixels apart, so frames that moved a little more still fill few of its phases. On development
# raw bursts (training/eval_still_bursts.py --raw --photos training --seeds 12 13 14 --spreads 0 0.1
# 0.2 0.3 0.5 --still-spacings 0.3 0.4: benchmarks/results/dev_raw_still_spacing.json, 60 bursts)
# the joint path less the demosaicked reference averaged +1.68 / +1.86 / +1.85 dB at 0.2 / 0.3 /
# 0.4: 0.3 moved every burst by -0.01 to +3.06 dB (shifts up to 0.2 px at S = 2 had fallen 1.8 dB
# under it), 0.4 lost up to 0.58 dB at shifts of 0.2 px (S = 3) and 0.3 px (S = 2).
RAW_STILL_SPACING = 0.3

# Samples :meth:`Tally.add` takes at a time (a piece of rows): a 12 MP frame's indices in one go
# are 96 MB of fresh pages each, which on this project's benchmark machine cost more to fault in
# than the sums themselves (the same sums either way).
TALLY_PIECE_SAMPLES = 1 << 16


def _phase_offset(where: Tensor) -> Tensor:
    """How far each position (..., 2) lies from the reference's pixel grid, the larger axis's, LR px (...)."""
    rest = (where - where.round()).abs_()
    return torch.maximum(rest[..., 0], rest[..., 1])  # (amax over the last axis of two: twice the time)


class Tally:
    """What :func:`coverage` and :func:`scale_to_run` add up over the frames, a frame at a time
    (its positions and weights), for frames of ``shape`` (H, W) and the output scales ``scales``."""

    def __init__(self, shape: tuple[int, int], reference: int, scales=()):
        H, W = shape
        self.shape, self.reference = shape, reference
        # framed by one node each way (:meth:`_framed_index`)
        self.cover = torch.zeros((H + 2) * (W + 2), dtype=torch.float64)
        self.hits = {s: torch.zeros((s * H + 2) * (s * W + 2), dtype=torch.bool) for s in scales}
        self.added = 0  # frames added
        self.still: dict[int, list] = {s: [] for s in scales}  # still frames per scale (:meth:`_still_scales`)
        self.still_hits: dict[int, Tensor] = {}  # the nodes still frames' samples land on unmoved, per scale
        self.others = 0  # frames other than the reference added

    def add(self, k: int, where: Tensor, weight: Tensor) -> None:
        """Frame ``k``'s positions (H, W, 2) and weights (H, W).

        Samples beyond the grid go to a one-node frame around it (indices clamped), which is
        dropped, and samples that add nothing (weight 0, or at most 0.1 for the fill) to one
        node of it: no boolean selection of the samples (a third of the time), the same sums
        (a weight of 0 adds nothing, and the others are added in the same order). A piece of
        :data:`TALLY_PIECE_SAMPLES` samples at a time, in row order: the same sums, in the same
        order, with temporaries that stay small enough to be reused rather than paged in fresh."""
        self.added += 1
        self.others += k != self.reference
        rows = max(1, TALLY_PIECE_SAMPLES // self.shape[1])
        still = self._still_scales(k, where, weight, rows)
        for r in range(0, where.shape[0], rows):
            self._add_rows(k, where[r:r + rows], weight[r:r + rows], still)

    def _still_scales(self, k: int, where: Tensor, weight: Tensor, rows: int) -> tuple:
        """The scales s on whose lattice frame ``k`` is still: :data:`STILL_FRAME_SHARE` of its
        samples of weight > 0.1 within :data:`STILL_SPACING` of the s lattice's node spacing of the
        reference's phase (and ``still[s]`` names it); none for the reference. A piece of rows at
        a time, as :meth:`add`."""
        if k == self.reference or not self.hits:
            return ()
        count, near = 0, dict.fromkeys(self.hits, 0)
        for r in range(0, where.shape[0], rows):
            offset, landed = _phase_offset(where[r:r + rows]), weight[r:r + rows] > 0.1
            count += int(landed.sum())
            for s in self.hits:
                near[s] += int((offset < STILL_SPACING / s).logical_and_(landed).sum())
        still = tuple(s for s in self.hits if count and near[s] >= STILL_FRAME_SHARE * count)
        for s in still:
            self.still[s].append(k)
        return still

    def _add_rows(self, k: int, where: Tensor, weight: Tensor, still: tuple) -> None:
        """:meth:`add` for a piece of the frame's rows (``still``: :meth:`_still_scales`')."""
        H, W = self.shape
        if not math.isfinite(float(where.sum())):  # (a degenerate motion) such samples land nowhere
            keep = torch.isfinite(where).all(-1)
            where, weight = torch.where(keep[..., None], where, -2.0), weight * keep
        if k != self.reference:  # coverage: the other frames' weights in the pixel each sample lands in
            index = self._framed_index(where, 1, H, W)
            self.cover.index_add_(0, index, weight.reshape(-1).to(torch.float64))
        landed = weight.reshape(-1) > 0.1
        offset = _phase_offset(where) if still else None
        for s, hit in self.hits.items():  # the lattice nodes that samples of weight > 0.1 land on
            at = where
            if s in still:  # where a still frame's land, kept apart; moved to the reference's
                if s not in self.still_hits:
                    self.still_hits[s] = torch.zeros_like(hit)
                self.still_hits[s][torch.where(landed, self._framed_index(where, s, s * H, s * W), 0)] = True
                at = torch.where((offset < STILL_SPACING / s)[..., None], where.round(), where)
            hit[torch.where(landed, self._framed_index(at, s, s * H, s * W), 0)] = True

    @staticmethod
    def _framed_index(where: Tensor, s: int, rows: int, cols: int) -> Tensor:
        """Flat index (N,) int64 in a (rows + 2, cols + 2) grid framed by one node of the node
        nearest each position (H, W, 2) on the s-times grid, clamped to the frame."""
        # both axes at once, and the index formed in float64 (exact below 2^53 nodes), converted
        # once: the same indices as each axis's apart in int64, in half the time
        node = where.round() if s == 1 else torch.add(where, 0.5).mul_(s).sub_(0.5).round_()
        u, v = node[..., 0].clamp(-1, cols), node[..., 1].clamp(-1, rows)
        return torch.add(u, v, alpha=cols + 2).add_(cols + 3).to(torch.int64).reshape(-1)

    def coverage(self) -> np.ndarray:
        H, W = self.shape
        return self.cover.reshape(H + 2, W + 2)[1:-1, 1:-1].numpy().copy()

    def mostly_still(self, s: int) -> bool:
        """Whether at least :data:`STILL_BURST_SHARE` of the frames added (but the reference) are
        still on the ``s``-times lattice (:meth:`_still_scales`)."""
        return bool(self.still.get(s)) and len(self.still[s]) >= STILL_BURST_SHARE * self.others

    def fill(self, s: int) -> np.ndarray:
        """The method's share (S H, S W) float32 at scale ``s`` from how the samples fill the output
        lattice: the share of output pixels near each (within S px) that a sample of weight > 0.1
        lands on; 1 from :data:`FULL_FILL` up, 0 at :data:`NO_FILL` and below. A few frames leave
        whole sub-pixel phases empty, and deblurring the filled-in lattice then costs more than it
        gains (4 random frames at S = 2: 2 to 4 dB under the single frame on simulated bursts; 8:
        5 dB over it). Where most frames are still (:meth:`mostly_still`), theirs land on the
        reference's nodes."""
        H, W = self.shape
        size = 2 * s + 1
        hit = self.hits[s]
        if s in self.still_hits and not self.mostly_still(s):  # a few still frames count as they land
            hit = hit | self.still_hits[s]
        hit = hit.reshape(s * H + 2, s * W + 2)[1:-1, 1:-1].to(torch.float32)
        fill = torch.nn.functional.avg_pool2d(hit.reshape(1, 1, s * H, s * W), size, 1, size // 2,
                                              count_include_pad=False)[0, 0]
        return ((fill - NO_FILL) / (FULL_FILL - NO_FILL)).clamp(0, 1).numpy()

    def run_scale(self, scale: int) -> tuple[int, np.ndarray]:
        """:func:`scale_to_run` from the hits at ``scale`` down to 2."""
        first = None
        for s in range(scale, 1, -1):
            fill = self.fill(s)
            first = fill if first is None else first
            if float(fill.mean()) >= RUN_FILL:
                return s, fill
        return scale, first


def tally_frames(positions, weights: Tensor, reference: int, scales=()) -> Tally:
    """:class:`Tally` of every frame with any weight (a frame's positions computed once)."""
    F, H, W = weights.shape
    tally = Tally((H, W), reference, scales)
    for k in range(F):
        if bool((weights[k] > 0).any()):
            tally.add(k, positions[k], weights[k])
    return tally


def coverage(positions, weights: Tensor, reference: int) -> np.ndarray:
    """How much the frames other than the reference put into each reference pixel: the sum of
    their samples' weights over the pixel each lands in, (H, W) float64. ``positions`` as
    :func:`~hbis_torch.reconstruct.burst.robustness_weights`'; weights (F, H, W)."""
    return tally_frames(positions, weights, reference).coverage()


def scale_to_run(positions, weights: Tensor, scale: int, reference: int = -1) -> tuple[int, np.ndarray]:
    """The scale a burst is reconstructed at: the largest s from ``scale`` down to 2 whose lattice
    the samples fill (the mean of :meth:`Tally.fill` at s at least :data:`RUN_FILL`), else
    ``scale`` (the fallback's blend then leans on the single frame); and :meth:`Tally.fill` at
    it. A scale the samples do not fill leaves whole sub-pixel phases empty; at a coarser one the
    same samples still add what they resolve, and the image is enlarged to the scale asked for.
    ``positions`` as :func:`~hbis_torch.reconstruct.burst.robustness_weights`'; weights (F, H, W).
    ``reference``: the reference frame's index, which the still test leaves out as
    :func:`~hbis_torch.reconstruct.burst.reconstruct_burst` does (-1: every frame is tested, the
    reference, still by definition, with them)."""
    if scale == 1:  # the reference's own grid: nothing to fill
        return 1, np.ones((weights.shape[1], weights.shape[2]), dtype=np.float32)
    return tally_frames(positions, weights, reference, range(scale, 1, -1)).run_scale(scale)


def still_frames(positions, trusted, reference: int, scale: int) -> list[int]:
    """The trusted frames but the reference that are still on the ``scale``-times lattice by the
    fill's rule (:meth:`Tally._still_scales`) with :data:`RAW_STILL_SPACING`, read on three bands of
    four rows (top, middle, bottom): for a burst path without a tally (raw bursts). ``positions``: a
    :class:`~hbis_torch.reconstruct.positions.BurstPositions` or (F, H, W, 2) float64."""
    F, H = positions.shape[:2]
    rows = sorted({0, max(0, H // 2 - 2), max(0, H - 4)})
    out = []
    for k in range(F):
        if k != reference and bool(trusted[k]):
            offset = torch.cat([_phase_offset(positions[k, r:r + 4]).reshape(-1) for r in rows])
            if float((offset < RAW_STILL_SPACING / scale).double().mean()) >= STILL_FRAME_SHARE:
                out.append(k)
    return out


def still_run_scale(positions, trusted, reference: int, scale: int, notes: list) -> int:
    """``scale``, or 1 where at least :data:`STILL_BURST_SHARE` of the trusted frames but the
    reference are still (:func:`still_frames`), with a line that asks the user to act: for a burst
    path without a fill test (raw bursts, fused at the frames' own size and enlarged)."""
    moved = int(np.sum(np.asarray(trusted, dtype=bool))) - 1
    if scale == 1 or moved < 1:
        return scale
    still = still_frames(positions, trusted, reference, scale)
    if len(still) < STILL_BURST_SHARE * moved:
        return scale
    notes.append(act(f"the frames hardly moved against the reference ({len(still)} of {moved}, within "
                     f"{RAW_STILL_SPACING / scale:.2f} px of its pixel grid): they hold little detail beyond its "
                     f"own, so they were fused at their own size and enlarged to S = {scale} (bicubic); for "
                     "super-resolution move the camera a little between frames"))
    return 1


def report_still(tally: Tally, notes: list) -> None:
    """A line naming the frames that hardly moved against the reference (:meth:`Tally._still_scales`
    on the coarsest lattice tried, S = 2, the loosest test); one that asks the user to act where
    most of the frames (:data:`STILL_BURST_SHARE`) are so."""
    scale = min(tally.still, default=None)
    still = [] if scale is None else sorted(tally.still[scale])
    if not still:
        return
    within = f"within {STILL_SPACING / scale:.3g} LR px of its pixel grid"
    if not tally.mostly_still(scale):
        notes.append(f"frame(s) {still} hardly moved against the reference ({within}): they add no new "
                     "sub-pixel samples, only less noise")
        return
    which = f"all {len(still)}" if len(still) == tally.others else f"{len(still)} of {tally.others}: {still}"
    notes.append(act(f"the frames hardly moved against the reference ({which}, {within}): they hold little "
                     "detail beyond the reference's, so the output leans on the reference enlarged; for "
                     "super-resolution move the camera a little between frames (a hand-held burst moves enough)"))


def report_unfilled(tally: Tally, fill: np.ndarray, scale: int, notes: list) -> None:
    """A line that asks for more frames where the samples fill no lattice from ``scale`` down to 2
    (``fill``, :meth:`Tally.run_scale`'s, under :data:`RUN_FILL` on average), so that the output
    leans on the reference enlarged; a burst that hardly moved has :func:`report_still`'s instead."""
    if float(fill.mean()) >= RUN_FILL or tally.mostly_still(min(tally.still)):
        return
    coarser = " (or any coarser one down to S = 2)" if scale > 2 else ""
    notes.append(act(f"the {tally.added} frames' samples fill too little of the S = {scale} lattice{coarser} to "
                     "reconstruct it whole: where they leave sub-pixel phases empty, the output leans on the "
                     "reference frame enlarged (bicubic); for more detail capture more frames"))
