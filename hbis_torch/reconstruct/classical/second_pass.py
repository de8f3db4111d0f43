"""What :func:`~hbis_torch.reconstruct.classical.splat.splat_on_lattice`'s first pass over the
samples keeps for its second one, so that the second need not compute the batches again.

The second pass (the samples moved to their nodes) reads each sample's value, weight, node and
offset from it. A burst's batches come from its motions, computed where they are read
(:class:`~hbis_torch.reconstruct.positions.BurstPositions`): computing them again (the positions,
then the nodes) was about a seventh of a 12 MP burst's classical reconstruct. So:

* batches the caller holds anyway (a list) are kept with their node indices and weights (8 bytes
  a sample at most);
* a burst's (``mixed_offsets``) batches computed on the fly are kept in a compact form, their
  values, offsets, node indices and weights (20 bytes a sample; the node's column and row are
  taken from the index again), up to :data:`KEEP_BYTES` in all: beyond that nothing is kept and
  the batches are computed again;
* otherwise (a scan on a large lattice) only a single batch is kept, as before.

The second pass reads the same numbers either way: the sums have the same bits.
"""

from __future__ import annotations

from typing import NamedTuple

from torch import Tensor

# A burst's first-pass samples (20 bytes each) are kept for the second pass up to this size:
# 16 frames of 12 MP take 3.8 GB.
KEEP_BYTES = 1 << 32


class _Compact(NamedTuple):
    """The fields of a NodeBatch that the second pass reads (col and row from the index)."""

    values: Tensor
    col: Tensor | None
    row: Tensor | None
    dx: Tensor
    dy: Tensor


class FirstPass:
    """The first pass's batches (iterate it) and what it keeps (:meth:`keep`) for the second
    (:meth:`second`).

    Parameters
    ----------
    batches : callable
        () -> iterable of NodeBatch, as :func:`splat_on_lattice` takes it.
    one_pass : bool
        The splat needs no second pass (nothing is kept).
    mixed_offsets : bool
        A burst: keep its batches in compact form (module docstring).
    """

    def __init__(self, batches, one_pass: bool, mixed_offsets: bool):
        self.batches, self.first = batches, batches()
        self.held = isinstance(self.first, (list, tuple)) and not one_pass
        self.compact = mixed_offsets and not one_pass and not self.held
        self.one_pass = one_pass
        self.kept, self.seen, self.size = [], 0, 0

    def __iter__(self):
        return iter(self.first)

    def keep(self, batch, idx: Tensor, w: Tensor | None) -> None:
        """The batch just summed, with its node indices and weights
        (:meth:`~hbis_torch.reconstruct.classical.splat.NodeSums.node_index`)."""
        self.seen += 1
        if self.held:
            self.kept.append((batch, idx, w))
        elif self.compact and self.kept is not None:
            self.size += sum(t.element_size() * t.numel() for t in (batch.values, batch.dx, batch.dy, idx)
                             if t is not None) + (0 if w is None else w.element_size() * w.numel())
            if self.size > KEEP_BYTES:
                self.kept = None  # too many: computed again
            else:
                self.kept.append((_Compact(batch.values, None, None, batch.dx, batch.dy), idx, w))
        elif not self.one_pass:
            self.kept = [(batch, idx, w)] if self.seen == 1 else []

    def second(self, node_index, cols: int):
        """(batch, idx, w) of every batch for the second pass: those kept, else the batches again
        with ``node_index`` (col, row, weights) -> (idx, w); ``cols`` is the lattice's width (a
        compact batch's col and row are taken from its index in the framed layout)."""
        if self.kept:
            for batch, idx, w in self.kept:
                if isinstance(batch, _Compact):
                    row = idx.div(cols + 2, rounding_mode="floor")
                    col = idx - row * (cols + 2)
                    batch = batch._replace(col=col.sub_(1), row=row.sub_(1))
                yield batch, idx, w
            return
        for b in self.batches():
            yield (b, *node_index(b.col, b.row, b.weights))
