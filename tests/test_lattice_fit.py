"""The burst lattice's holes filled from the samples around them (reconstruct/classical/lattice_fit.py)."""

import math

import torch

from hbis_torch.reconstruct.classical import lattice_fit
from hbis_torch.reconstruct.classical.lattice import NodeBatch
from hbis_torch.reconstruct.classical.holes import fill_holes
from hbis_torch.reconstruct.classical.splat import splat_on_lattice

SIGMA = 0.45
ROWS, COLS = 48, 64


def scene(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """A smooth scene below the LR pixels' Nyquist frequency (HR px coordinates)."""
    return 0.5 + 0.2 * torch.sin(2 * math.pi * 0.13 * x) * torch.cos(2 * math.pi * 0.09 * y) \
        + 0.15 * torch.sin(2 * math.pi * (0.05 * x + 0.11 * y))


def clustered_batch(dtype=torch.float32) -> NodeBatch:
    """Eight frames of LR pixels (2 HR px apart) whose shifts cluster within 0.4 HR px of three
    of the lattice's four node classes, as a burst of 8 frames at S = 2 can: the nodes of odd
    row and odd column get no sample of their own."""
    xs, ys = [], []
    for fx, fy in ((0.0, 0.0), (0.4, -0.3), (1.0, 0.4), (0.6, -0.3), (1.4, 0.0), (0.3, 1.0), (-0.3, 0.6),
                   (0.4, 1.4)):
        y, x = torch.meshgrid(torch.arange(0, ROWS, 2, dtype=torch.float64) + fy,
                              torch.arange(0, COLS, 2, dtype=torch.float64) + fx, indexing="ij")
        xs.append(x.reshape(-1))
        ys.append(y.reshape(-1))
    x, y = torch.cat(xs), torch.cat(ys)
    col, row = torch.round(x), torch.round(y)
    values = scene(x, y).to(dtype)
    return NodeBatch(values, col.to(torch.int32), row.to(torch.int32), (col - x).to(dtype), (row - y).to(dtype),
                     None, float(max((col - x).abs().max(), (row - y).abs().max())))


def splat_image(batch: NodeBatch):
    num, den, typical = splat_on_lattice(lambda: [batch], (ROWS, COLS), SIGMA, mixed_offsets=True)
    return fill_holes(num, den, typical, in_place=True), den, typical


def truth() -> torch.Tensor:
    """The scene at the framed lattice's nodes, spread like the splat's image."""
    y, x = torch.meshgrid(torch.arange(-1, ROWS + 1, dtype=torch.float64),
                          torch.arange(-1, COLS + 1, dtype=torch.float64), indexing="ij")
    return lattice_fit._spread(scene(x, y), SIGMA)


def test_holes_come_closer_to_the_scene():
    batch = clustered_batch()
    image, den, typical = splat_image(batch)
    holes = (den < lattice_fit.HOLE_SHARE * typical)[4:-4, 4:-4]
    assert holes.float().mean() > 0.2, float(holes.float().mean())  # the odd-odd nodes
    before = (image.double() - truth())[4:-4, 4:-4][holes].abs().mean()
    filled = lattice_fit.fill_holes_from_samples(image.clone(), den, typical, lambda: [batch], SIGMA)
    after = (filled.double() - truth())[4:-4, 4:-4][holes].abs().mean()
    # the samples between the nodes pin the holes down (0.0157 -> 0.0120 here)
    assert after < 0.85 * before, (float(before), float(after))


def test_nodes_with_samples_keep_their_bits(monkeypatch):
    monkeypatch.setattr(lattice_fit, "HOLE_SHARE", 0.5)  # (at the default 2 this lattice has no such node)
    batch = clustered_batch()
    image, den, typical = splat_image(batch)
    filled = lattice_fit.fill_holes_from_samples(image.clone(), den, typical, lambda: [batch], SIGMA)
    kept = den >= lattice_fit.HOLE_SHARE * typical
    assert kept.any()
    assert torch.equal(filled[kept], image[kept])


def test_a_lattice_without_holes_is_not_fitted(monkeypatch):
    def no_fit(*args, **kwargs):
        raise AssertionError("a lattice without holes was fitted")

    monkeypatch.setattr(lattice_fit, "fit_lattice", no_fit)
    image = torch.rand(ROWS, COLS)
    before = image.clone()
    every_node = torch.full((ROWS, COLS), lattice_fit.HOLE_SHARE)  # each at the share of the typical weight 1
    out = lattice_fit.fill_holes_from_samples(image, every_node, 1.0, lambda: [clustered_batch()], SIGMA)
    assert out is image and torch.equal(out, before)


def test_float32_fit_agrees_with_float64():
    batch = clustered_batch()
    image, _, _ = splat_image(batch)
    low = lattice_fit.fit_lattice(image, lambda: [batch], SIGMA)
    high = lattice_fit.fit_lattice(image.double(), lambda: [clustered_batch(torch.float64)], SIGMA,
                                   dtype=torch.float64)
    assert low.dtype == torch.float32
    assert float((low.double() - high).abs().max()) < 1e-4


def test_normal_equations_match_the_bilinear_matrix():
    """The stencil and right-hand side equal A^T W A and A^T W v of the explicit matrix."""
    batch = clustered_batch(torch.float64)
    small = NodeBatch(*(t[:40] if isinstance(t, torch.Tensor) else t for t in batch))
    rows, cols = ROWS, COLS
    rhs, stencil = lattice_fit.normal_equations(lambda: [small], (rows, cols), torch.float64)
    base, beta, weight = lattice_fit._corners(small, rows, cols, torch.float64)
    n = (rows + 2) * (cols + 2)
    a = torch.zeros(len(weight), n, dtype=torch.float64)
    for (cx, cy), b in zip(lattice_fit._CORNERS, beta):
        a[torch.arange(len(weight)), base + cx + cy * (cols + 2)] += b
    ata = a.T @ (weight[:, None] * a)
    assert torch.allclose(rhs.reshape(-1), a.T @ (weight * small.values), atol=1e-12)
    for k, (ox, oy) in enumerate(lattice_fit.HALF_STENCIL):
        node = torch.arange(n)
        other = node + oy * (cols + 2) + ox
        ok = (other >= 0) & (other < n)
        assert torch.allclose(stencil[k].reshape(-1)[ok], ata[node[ok], other[ok]], atol=1e-12)


def test_samples_of_no_weight_change_nothing():
    batch = clustered_batch()
    image, den, typical = splat_image(batch)
    weightless = batch._replace(weights=torch.zeros_like(batch.values))
    before = image.clone()
    out = lattice_fit.fill_holes_from_samples(image, den, typical, lambda: [weightless], SIGMA)
    assert torch.equal(out, before)


def dense_batch_with_a_gap() -> NodeBatch:
    """Sixteen frames whose shifts put about four samples at every node, but none of weight in a
    square of 12 x 12 nodes (as where a moving object was rejected): holes in one place only."""
    generator = torch.Generator().manual_seed(3)
    xs, ys = [], []
    for _ in range(16):
        fx, fy = (torch.rand(2, generator=generator, dtype=torch.float64) * 2).tolist()
        y, x = torch.meshgrid(torch.arange(-2, ROWS, 2, dtype=torch.float64) + fy,
                              torch.arange(-2, COLS, 2, dtype=torch.float64) + fx, indexing="ij")
        xs.append(x.reshape(-1))
        ys.append(y.reshape(-1))
    x, y = torch.cat(xs), torch.cat(ys)
    col, row = torch.round(x), torch.round(y)
    weights = 1.0 - (((x - 30).abs() < 6) & ((y - 24).abs() < 6)).to(torch.float32)
    return NodeBatch(scene(x, y).to(torch.float32), col.to(torch.int32), row.to(torch.int32),
                     (col - x).to(torch.float32), (row - y).to(torch.float32), weights, 0.5)


def test_solving_near_the_holes_matches_the_whole_lattice(monkeypatch):
    monkeypatch.setattr(lattice_fit, "HOLE_SHARE", 0.5)  # only the gap's nodes take the fit
    batch = dense_batch_with_a_gap()
    image, den, typical = splat_image(batch)
    share = (1 - den / (lattice_fit.HOLE_SHARE * typical)).clamp(0, 1)
    assert 0.02 < float((share > 0).float().mean()) < 0.2
    whole = lattice_fit.fit_lattice(image, lambda: [batch], SIGMA)
    expected = image + share * (whole - image)
    read = []
    cell_terms = lattice_fit._cell_terms

    def counted(part, rows, cols, dtype, columns):
        if len(columns) == len(lattice_fit._TERMS):  # (the ridge's scale reads every sample's diagonal)
            read.append(len(part.values))
        return cell_terms(part, rows, cols, dtype, columns)

    monkeypatch.setattr(lattice_fit, "_cell_terms", counted)
    near = lattice_fit.fill_holes_from_samples(image.clone(), den, typical, lambda: [batch], SIGMA)
    assert sum(read) < 0.8 * len(batch.values)  # the samples far from the gap were not read
    assert float((near - expected).abs().max()) < 1e-3
    assert not torch.equal(near, image)


def test_dilate_matches_a_max_pool():
    nodes = torch.rand(37, 53, generator=torch.Generator().manual_seed(0)) > 0.97
    for radius in (1, 3):
        pooled = torch.nn.functional.max_pool2d(nodes.float()[None, None], 2 * radius + 1, 1, radius)[0, 0] > 0
        assert torch.equal(lattice_fit._dilate(nodes, radius), pooled)


def test_data_weights_are_the_stencils_diagonal():
    batch = dense_batch_with_a_gap()
    _, stencil = lattice_fit.normal_equations(lambda: [batch], (ROWS, COLS))
    assert torch.equal(lattice_fit.data_weights(lambda: [batch], (ROWS, COLS)), stencil[0])


def test_the_diagonal_of_every_sample_reads_again_only_near_what_was_not_read(monkeypatch):
    """The ridge's scale needs every sample's diagonal: where the samples read for the fit hold
    all of a node's, their sums are taken as they are (the same bits) and only the samples near the
    others are read again; where they hold every node's, no sample is read twice."""
    batch = dense_batch_with_a_gap()
    shape = (ROWS, COLS)
    every = lattice_fit.data_weights(lambda: [batch], shape)
    read_again = []
    cell_terms = lattice_fit._cell_terms

    def counted(part, rows, cols, dtype, columns):
        read_again.append(len(part.values))
        return cell_terms(part, rows, cols, dtype, columns)

    for share in (0.4, 0.7, 1.0):  # a corner of the lattice, half of it, all of it
        read = torch.zeros(ROWS + 2, COLS + 2, dtype=torch.bool)
        read[: int(share * (ROWS + 2)), : int(share * (COLS + 2)) + 1] = True
        _, stencil = lattice_fit.normal_equations(lambda: [batch], shape, read=read)
        read_again.clear()
        monkeypatch.setattr(lattice_fit, "_cell_terms", counted)
        diagonal = lattice_fit._every_samples_diagonal(lambda: [batch], shape, torch.float32, read, stencil[0])
        monkeypatch.setattr(lattice_fit, "_cell_terms", cell_terms)
        assert torch.equal(diagonal.view(torch.int32), every.view(torch.int32))
        if share == 1.0:
            assert read_again == []
        else:
            assert 0 < sum(read_again) < (1 - 0.5 * share * share) * len(batch.values)


def test_the_stencil_applies_as_the_matrix():
    batch = clustered_batch(torch.float64)
    rhs, stencil = lattice_fit.normal_equations(lambda: [batch], (ROWS, COLS), torch.float64)
    n = (ROWS + 2) * (COLS + 2)
    matrix = torch.zeros(n, n, dtype=torch.float64)
    node = torch.arange(n)
    for k, (ox, oy) in enumerate(lattice_fit.HALF_STENCIL):
        other = node + oy * (COLS + 2) + ox
        ok = (other >= 0) & (other < n)
        matrix[node[ok], other[ok]] = stencil[k].reshape(-1)[ok]
        matrix[other[ok], node[ok]] = stencil[k].reshape(-1)[ok]
    g = torch.rand(ROWS + 2, COLS + 2, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    lam = 0.7
    applied = lattice_fit._apply(stencil, stencil[0] + lam, g)
    assert torch.allclose(applied.reshape(-1), matrix @ g.reshape(-1) + lam * g.reshape(-1), atol=1e-12)
