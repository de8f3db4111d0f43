"""splat_on_lattice's second pass from the batches its caller holds (second_pass.py), and
node_batch on positions given per sample: the same numbers as computing them again."""

import torch

from hbis_torch.reconstruct.classical.lattice import NodeBatch, node_batch
from hbis_torch.reconstruct.classical.splat import splat_on_lattice

SHAPE = (30, 36)


def burst_batches(count: int = 3, per_batch: int = 4000, seed: int = 0) -> list[NodeBatch]:
    """Batches of samples at random offsets, some beyond the lattice (and its one-node frame),
    some of weight 0."""
    g = torch.Generator().manual_seed(seed)
    rows, cols = SHAPE
    out = []
    for _ in range(count):
        x = torch.rand(per_batch, generator=g, dtype=torch.float64) * (cols + 6) - 3
        y = torch.rand(per_batch, generator=g, dtype=torch.float64) * (rows + 6) - 3
        xn, yn = torch.round(x), torch.round(y)
        values = (0.5 + 0.3 * torch.sin(0.4 * x) * torch.cos(0.3 * y)).float()
        weights = torch.rand(per_batch, generator=g)
        weights[::7] = 0
        out.append(NodeBatch(values, xn.to(torch.int32), yn.to(torch.int32), (xn - x).float(), (yn - y).float(),
                             weights, float(max((xn - x).abs().max(), (yn - y).abs().max()))))
    return out


def test_the_second_pass_from_held_batches_has_the_same_bits():
    parts = burst_batches()
    calls = []

    def batches():
        calls.append(1)
        return iter(parts)

    again = splat_on_lattice(batches, SHAPE, 0.45, mixed_offsets=True)  # a generator: computed again
    assert len(calls) == 2
    held = splat_on_lattice(lambda: calls.append(1) or list(parts), SHAPE, 0.45, mixed_offsets=True)
    assert len(calls) == 3  # the caller's list: its batches (and their node indices) kept
    assert torch.equal(held[0], again[0]) and torch.equal(held[1], again[1]) and held[2] == again[2]
    # the second pass moved the samples (the test can fail)
    still = splat_on_lattice(lambda: [p._replace(dx=p.dx * 0, dy=p.dy * 0) for p in parts], SHAPE, 0.45,
                             mixed_offsets=True)
    assert float((held[0] - still[0]).abs().max()) > 1e-3


def test_node_batch_of_positions_is_the_plain_expression():
    g = torch.Generator().manual_seed(1)
    frames = torch.rand(3, 5, 7, generator=g)
    positions = torch.rand(3, 5, 7, 2, generator=g, dtype=torch.float64) * 12 - 3
    positions[0, 0, 0] = torch.tensor([1.25, 2.75], dtype=torch.float64)  # exact halves at h = 2
    weights = torch.rand(3, 5, 7, generator=g)
    h, offset = 2, (0.0, -0.3)
    part = (slice(0, 3), slice(1, 4))
    got = node_batch(frames, positions, part, h, offset, weights)
    where = positions[part]
    for axis, (node, gap) in enumerate(((got.col, got.dx), (got.row, got.dy))):
        coord = ((where[..., axis] + 0.5) * h - 0.5) - offset[axis]
        nearest = torch.round(coord)
        assert torch.equal(gap, (nearest - coord).to(torch.float32).reshape(-1))
        assert torch.equal(node, nearest.clamp(-2, 1 << 30).to(torch.int32).reshape(-1))  # a node beyond: -2
    assert got.reach == float(torch.maximum(got.dx.abs(), got.dy.abs()).max())
    assert torch.equal(got.values, frames[part].reshape(-1)) and torch.equal(got.weights, weights[part].reshape(-1))
