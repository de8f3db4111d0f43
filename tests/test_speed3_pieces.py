"""Computations done a piece of rows at a time give the bits of the whole computation.

The burst path computes whole frames' positions, their nearest lattice nodes, the warp onto the
reference, the local fit's shifted reference and the output's blend in pieces (small temporaries
that stay in the cache, no frame-sized fresh pages); affine motions skip the homography's
division by w = 1.
Each is checked here against the same computation at once (the piece size made larger than the
frame), bit for bit.
"""

import numpy as np
import pytest
import torch

from hbis_torch.reconstruct import positions as P
from hbis_torch.reconstruct.classical import lattice as L
from hbis_torch.registration import local as local_motion
from hbis_torch.registration import warp as W
from hbis_torch.registration.homography import apply_homography_to_grid


def _motions(kind: str, count: int, rng) -> np.ndarray:
    m = np.tile(np.eye(3), (count, 1, 1))
    m[1:, :2, 2] = rng.uniform(-2, 2, (count - 1, 2))
    m[1, :2, 2] = [0.5, -0.25]  # samples exactly halfway between nodes
    if kind != "translation":
        m[1:, :2, :2] += rng.uniform(-2e-3, 2e-3, (count - 1, 2, 2))
    if kind == "homography":
        m[1:, 2, :2] = rng.uniform(-1e-4, 1e-4, (count - 1, 2))
    return m


def _positions(kind: str, shape=(4, 70, 90), seed=0) -> P.BurstPositions:
    rng = np.random.default_rng(seed)
    count, height, width = shape
    offsets = torch.from_numpy(rng.uniform(-1, 1, (count, -(-height // 32), -(-width // 32), 2)))
    offsets[0] = 0
    return P.BurstPositions(_motions(kind, count, rng), height, width, offsets, 32)


@pytest.mark.parametrize("kind", ["translation", "similarity", "homography"])
def test_whole_frames_in_pieces_have_the_bits_of_one_band(kind, monkeypatch):
    positions = _positions(kind)
    monkeypatch.setattr(P, "PIECE_SAMPLES", 1 << 30)
    at_once = positions._band(slice(None), slice(None))
    monkeypatch.setattr(P, "PIECE_SAMPLES", 200)  # two rows of 90 a piece
    pieces = positions._band(slice(None), slice(None))
    assert torch.equal(pieces, at_once)
    out = torch.empty_like(at_once)
    assert positions._band(slice(1, 3), slice(None), out=out[1:3]) is not None
    assert torch.equal(out[1:3], at_once[1:3])


def test_affine_motions_skip_only_a_division_by_one():
    rng = np.random.default_rng(1)
    m = torch.from_numpy(_motions("similarity", 3, rng))
    rows, cols = torch.arange(5, dtype=torch.float64), torch.arange(7, dtype=torch.float64)
    got = apply_homography_to_grid(m, rows, cols)
    for k in range(3):  # a u + (b v + c): the sums the general path makes before dividing by w
        for axis in (0, 1):
            plain = (m[k, axis, 1] * rows + m[k, axis, 2])[:, None] + (m[k, axis, 0] * cols)[None, :]
            assert torch.equal(got[k, ..., axis], plain)
    # a homography among affine ones is still divided by its w
    h = m.clone()
    h[2, 2, :2] = torch.tensor([1e-4, -2e-4])
    mixed = apply_homography_to_grid(h, rows, cols)
    assert torch.equal(mixed[:2], got[:2]) and not torch.equal(mixed[2], got[2])
    w = (h[2, 2, 1] * rows + h[2, 2, 2])[:, None] + (h[2, 2, 0] * cols)[None, :]
    plain = ((h[2, 0, 1] * rows + h[2, 0, 2])[:, None] + (h[2, 0, 0] * cols)[None, :]) / w
    assert torch.equal(mixed[2, ..., 0], plain)


@pytest.mark.parametrize("kind", ["translation", "homography"])
def test_node_batch_in_pieces_has_the_bits_of_the_whole_batch(kind, monkeypatch):
    positions = _positions(kind, shape=(4, 40, 50), seed=2)
    frames = torch.rand(4, 40, 50, generator=torch.Generator().manual_seed(0))
    weights = torch.rand(4, 40, 50, generator=torch.Generator().manual_seed(1))
    offset = (0.25, 0.5)  # with the exact halves above: ties at halfway
    for part in ((slice(0, 4), slice(3, 29)), (slice(1, 3), slice(5, 6))):
        monkeypatch.setattr(L, "PIECE_SAMPLES", 1 << 30)
        whole = L.node_batch(frames, positions, part, 2, offset, weights)
        monkeypatch.setattr(L, "PIECE_SAMPLES", 100)  # two rows a piece
        pieces = L.node_batch(frames, positions, part, 2, offset, weights)
        for a, b in zip(whole, pieces):
            assert torch.equal(a, b) if isinstance(a, torch.Tensor) else a == b
        # the plain expression, for the batch at once
        where = positions[part]
        coord = (where[..., 0] + 0.5) * 2 - 0.5 - offset[0]
        assert torch.equal(whole.col, torch.round(coord).reshape(-1).to(torch.int32))
        gap = (torch.round(coord) - coord).to(torch.float32).reshape(-1)
        assert torch.equal(whole.dx, gap)
        assert whole.reach == max(float(whole.dx.abs().max()), float(whole.dy.abs().max()))


@pytest.mark.parametrize("motion", [np.array([[1, 0.002, 1.3], [-0.002, 1, -0.7], [0, 0, 1.0]]),
                                    np.array([[1, 0.002, 1.3], [-0.002, 1, -0.7], [2e-4, -1e-4, 1.0]])])
def test_warp_in_pieces_has_the_bits_of_the_whole_warp(motion, monkeypatch):
    image = torch.rand(1, 2, 37, 45, generator=torch.Generator().manual_seed(3))
    monkeypatch.setattr(W, "PIECE_SAMPLES", 1 << 30)
    warped, valid = W.warp_onto_reference(image, motion, size=(40, 45))
    monkeypatch.setattr(W, "PIECE_SAMPLES", 100)
    monkeypatch.setattr(W, "PIECES_FROM", 0)
    pieces, valid2 = W.warp_onto_reference(image, motion, size=(40, 45))
    assert torch.equal(pieces, warped) and torch.equal(valid2, valid)
    out = (torch.full((1, 2, 40, 45), 7.0), torch.zeros((40, 45), dtype=torch.bool))
    got = W.warp_onto_reference(image, motion, size=(40, 45), out=out)
    assert got[0] is out[0] and torch.equal(out[0], warped) and torch.equal(out[1], valid)
    assert 0 < int(valid.sum()) < valid.numel()


def test_shifted_reference_into_kept_memory_has_the_same_bits(monkeypatch):
    image = torch.rand(1, 3, 64, 96, generator=torch.Generator().manual_seed(4))
    offsets = torch.rand(1, 2, 3, 2, generator=torch.Generator().manual_seed(5)) - 0.5
    axes = tuple((torch.arange(n, dtype=torch.float64) * (2 / (size - 1)) - 1).float()
                 for n, size in ((64, 60), (96, 90)))
    spread = (local_motion._spread(64, 2, 32), local_motion._spread(96, 3, 32).T.contiguous())
    monkeypatch.setattr(local_motion, "PIECE_SAMPLES", 1 << 30)
    plain = local_motion._shift(image, offsets, 32, spread, axes)
    monkeypatch.setattr(local_motion, "PIECE_SAMPLES", 300)
    monkeypatch.setattr(local_motion, "PIECES_FROM", 0)
    kept = (torch.empty_like(plain), torch.empty((1, 2, 64, 96)))
    got = local_motion._shift(image, offsets, 32, spread, axes, out=kept)
    assert got is kept[0] and torch.equal(got, plain)
    assert torch.equal(kept[1].permute(0, 2, 3, 1), local_motion._field(
        offsets * torch.tensor([2 / 95, 2 / 63]), (64, 96), 32, spread))


def test_luminance_in_torch_memory_is_the_float32_division():
    from hbis_torch.capture.burst import luminance

    frames = np.random.default_rng(6).integers(0, 65536, (3, 20, 30), dtype=np.uint16)
    got = luminance(frames)
    assert isinstance(got, torch.Tensor) and got.dtype == torch.float32
    assert np.array_equal(got.numpy(), np.divide(frames, np.float32(65535), dtype=np.float32))


def test_the_tally_in_pieces_of_rows_has_the_sums_of_the_whole_frame(monkeypatch):
    from hbis_torch.reconstruct import burst_fill

    rng = np.random.default_rng(5)
    H, Wd = 37, 53
    where = apply_homography_to_grid(torch.from_numpy(_motions("homography", 4, rng)),
                                     torch.arange(H, dtype=torch.float64), torch.arange(Wd, dtype=torch.float64))
    weights = torch.from_numpy(rng.uniform(0, 1, (4, H, Wd)))
    weights[2, 5:9] = 0.0
    where[3, 0, 0] = float("nan")  # a sample that lands nowhere

    def tally(piece):
        monkeypatch.setattr(burst_fill, "TALLY_PIECE_SAMPLES", piece)
        t = burst_fill.Tally((H, Wd), 0, (3, 2))
        for k in range(4):
            t.add(k, where[k], weights[k])
        return t

    whole, pieces = tally(1 << 20), tally(3 * Wd + 1)  # one piece, and pieces of 3 rows
    assert np.array_equal(whole.coverage(), pieces.coverage())
    assert all(torch.equal(whole.hits[s], pieces.hits[s]) for s in (2, 3))
    assert whole.coverage().sum() > 0 and bool(whole.hits[3].any())


@pytest.mark.parametrize("channels", [None, 3])
def test_the_blend_in_pieces_is_the_whole_arrays_blend(channels, monkeypatch):
    """The output's blend of the method's image with the single frame, a few rows at a time, has
    the bits of the whole arrays' float32 blend; a colour image takes one alpha for its three
    channels; a non-finite value is refused, in any piece."""
    from hbis_torch.reconstruct import burst as B

    rng = np.random.default_rng(5)
    shape = (37, 29) if channels is None else (37, 29, channels)
    alpha = rng.uniform(-0.1, 1.1, (37, 29, 1) if channels else (37, 29)).clip(0, 1).astype(np.float32)
    image, fallback = (rng.uniform(-0.2, 1.2, shape).astype(np.float32) for _ in range(2))
    whole = np.clip(alpha * image + (1 - alpha) * fallback, 0, 1).astype(np.float32)
    monkeypatch.setattr(B, "BLEND_PIECE_SAMPLES", 100)  # three rows a piece (one for colour)
    got = B._blend(alpha, image, fallback)
    assert got.dtype == np.float32 and np.array_equal(got, whole)
    image[30, 3] = np.nan
    with pytest.raises(RuntimeError, match="non-finite"):
        B._blend(alpha, image, fallback)
