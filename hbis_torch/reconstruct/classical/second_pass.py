"""What :func:`~hbis_torch.reconstruct.classical.splat.splat_on_lattice`'s first pass over the
samples keeps for its second one, so that the second need not compute it again.

The second pass (the samples moved to their nodes) reads each batch's samples and their node
indices and weights. Batches that the caller holds in memory anyway (a list: a burst of up to
``KEEP_SAMPLES`` samples, :mod:`~hbis_torch.reconstruct.classical.sr`) are kept with their node
indices and weights (4 to 8 bytes a sample more); otherwise only a single batch is kept, and the
batches are computed again. The sums have the same bits either way.

Keeping a 12 MP burst's batches too (values, offsets, node index and weight: 20 bytes a sample,
3.8 GB) was measured and dropped: its lattice image took 28.6-46.4 s CPU against 33.7-39.1 s
computing them again (one thread, a loaded machine), the new pages costing what the positions did.
"""

from __future__ import annotations

from torch import Tensor


class FirstPass:
    """The first pass's batches (iterate it) and what it keeps (:meth:`keep`) for the second
    (:meth:`second`).

    Parameters
    ----------
    batches : callable
        () -> iterable of NodeBatch, as :func:`splat_on_lattice` takes it.
    one_pass : bool
        The splat needs no second pass (nothing is kept).
    """

    def __init__(self, batches, one_pass: bool):
        self.batches, self.first = batches, batches()
        self.held = isinstance(self.first, (list, tuple)) and not one_pass
        self.one_pass = one_pass
        self.kept, self.seen = [], 0

    def __iter__(self):
        return iter(self.first)

    def keep(self, batch, idx: Tensor, w: Tensor | None) -> None:
        """The batch just summed, with its node indices and weights
        (:meth:`~hbis_torch.reconstruct.classical.splat.NodeSums.node_index`)."""
        self.seen += 1
        if self.held:
            self.kept.append((batch, idx, w))
        elif not self.one_pass:
            self.kept = [(batch, idx, w)] if self.seen == 1 else []

    def second(self, node_index):
        """(batch, idx, w) of every batch for the second pass: those kept, else the batches again
        with ``node_index`` (col, row, weights) -> (idx, w)."""
        if self.kept:
            yield from self.kept
            return
        for b in self.batches():
            yield (b, *node_index(b.col, b.row, b.weights))
