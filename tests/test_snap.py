"""The first-order move of samples onto their lattice nodes (snap_to_lattice, and its batched
form in splat_on_lattice): where each sample reads the pilot's gradient, for a scan (one sample
per node) and for a burst (many samples at different offsets share a node)."""

import importlib
import math

import torch

from hbis_torch.reconstruct.classical.lattice import NodeBatch
from hbis_torch.reconstruct.classical.splat import snap_to_lattice, splat, splat_on_lattice

SHAPE = (40, 48)


def scene(x, y):
    """A smooth field with curvature, on lattice coordinates."""
    return 0.5 + 0.2 * torch.sin(0.45 * x + 0.3) * torch.cos(0.35 * y - 0.2)


def burst_samples(per_node: int, seed: int = 0):
    """``per_node`` samples around every node, at uniform random offsets within half a node."""
    g = torch.Generator().manual_seed(seed)
    rows, cols = SHAPE
    y, x = torch.meshgrid(torch.arange(rows, dtype=torch.float64), torch.arange(cols, dtype=torch.float64),
                          indexing="ij")
    x = x.reshape(-1).repeat(per_node) + torch.rand(rows * cols * per_node, generator=g, dtype=torch.float64) - 0.5
    y = y.reshape(-1).repeat(per_node) + torch.rand(rows * cols * per_node, generator=g, dtype=torch.float64) - 0.5
    return scene(x, y), x, y


def inner_error(values, xn, yn) -> float:
    """RMS of the moved values against the scene at their nodes, two nodes in from the border."""
    rows, cols = SHAPE
    inner = (xn >= 2) & (xn <= cols - 3) & (yn >= 2) & (yn <= rows - 3)
    return float((values - scene(xn, yn))[inner].pow(2).mean().sqrt())


def test_a_scan_reads_the_gradient_at_the_node_with_either_setting():
    # one sample per node, all at the same offset (a scan's phase error): the pilot's bias is
    # the sample's own offset, so reading at x + bias is reading at the node
    rows, cols = SHAPE
    y, x = torch.meshgrid(torch.arange(rows, dtype=torch.float64), torch.arange(cols, dtype=torch.float64),
                          indexing="ij")
    x, y = x.reshape(-1) + 0.3, y.reshape(-1) - 0.2
    values = scene(x, y)
    plain, xn, yn = snap_to_lattice(values, x, y, SHAPE, 0.45)
    mixed, _, _ = snap_to_lattice(values, x, y, SHAPE, 0.45, mixed_offsets=True)
    assert torch.allclose(plain, mixed, atol=1e-9)
    assert inner_error(plain, xn, yn) < 0.15 * inner_error(values, xn, yn)  # the move is corrected


def test_a_burst_reads_the_gradient_where_the_pilot_stands():
    # two samples per node at random offsets: the pilot averages them, so its value at a node
    # belongs near the node, and the gradient at a sample is the pilot's near the sample (0.77
    # of the error of reading it at the node; 0.92 with six samples per node, whose mean offset
    # is nearer 0)
    values, x, y = burst_samples(2)
    raw = inner_error(values, torch.round(x), torch.round(y))
    at_node = inner_error(*snap_to_lattice(values, x, y, SHAPE, 0.45))
    measured = inner_error(*snap_to_lattice(values, x, y, SHAPE, 0.45, mixed_offsets=True))
    assert measured < at_node < raw
    assert measured < 0.85 * at_node


def test_the_batched_splat_matches_snap_then_splat():
    values, x, y = burst_samples(3, seed=1)
    weights = 0.5 + 0.5 * torch.rand(len(values), generator=torch.Generator().manual_seed(2), dtype=torch.float64)
    for mixed in (False, True):
        moved, xn, yn = snap_to_lattice(values, x, y, SHAPE, 0.45, weights, mixed_offsets=mixed)
        want_num, want_den = splat(moved, xn, yn, SHAPE, 0.45, weights)
        batch = NodeBatch(values.float(), xn.to(torch.int32), yn.to(torch.int32), (xn - x).float(), (yn - y).float(),
                          weights.float(), float(max((xn - x).abs().max(), (yn - y).abs().max())))
        # two batches, as a stack too large for one arrives
        half = len(values) // 2
        parts = [NodeBatch(*(t[:half] if torch.is_tensor(t) else t for t in batch)),
                 NodeBatch(*(t[half:] if torch.is_tensor(t) else t for t in batch))]
        num, den, _ = splat_on_lattice(lambda: iter(parts), SHAPE, 0.45, mixed_offsets=mixed)
        assert torch.allclose(den.double(), want_den, rtol=1e-5, atol=1e-6)
        assert torch.allclose(num.double(), want_num, rtol=1e-4, atol=1e-5), (mixed, float((num - want_num).abs().max()))
        assert math.isfinite(float(num.sum()))


def test_one_pass_over_a_scan_gives_the_two_passes_sums(monkeypatch):
    # a scan's samples read the gradient at their node, so the first-order terms sum per node
    # (one pass, the offsets' sums beside the values'); samples a node beyond the lattice land on
    # the one-node frame, which takes its border node's gradient either way
    splat_module = importlib.import_module("hbis_torch.reconstruct.classical.splat")  # the package names a function so

    g = torch.Generator().manual_seed(3)
    rows, cols = SHAPE
    y, x = torch.meshgrid(torch.arange(-1, rows + 1, dtype=torch.float64),
                          torch.arange(-1, cols + 1, dtype=torch.float64), indexing="ij")
    x = x.reshape(-1) + 0.3 * torch.rand(x.numel(), generator=g, dtype=torch.float64) - 0.15
    y = y.reshape(-1) + 0.3 * torch.rand(y.numel(), generator=g, dtype=torch.float64) - 0.15
    xn, yn = torch.round(x), torch.round(y)
    weights = 0.5 + 0.5 * torch.rand(len(x), generator=g)
    batch = NodeBatch(scene(x, y).float(), xn.to(torch.int32), yn.to(torch.int32), (xn - x).float(), (yn - y).float(),
                      weights, float(max((xn - x).abs().max(), (yn - y).abs().max())))
    one = splat_on_lattice(lambda: iter([batch]), SHAPE, 0.45)
    monkeypatch.setattr(splat_module, "ONE_PASS_NODES", 0)
    two = splat_on_lattice(lambda: iter([batch]), SHAPE, 0.45)
    assert torch.equal(one[1], two[1]) and one[2] == two[2]  # the same weights
    assert torch.allclose(one[0], two[0], rtol=1e-6, atol=1e-6), float((one[0] - two[0]).abs().max())
    moved = one[0] - splat_on_lattice(lambda: iter([batch._replace(dx=batch.dx * 0, dy=batch.dy * 0)]), SHAPE, 0.45)[0]
    assert float(moved.abs().max()) > 1e-3  # the slope terms moved the sums (the test can fail)
