"""The raw joint path in bounded memory (hbis_torch/reconstruct/classical/raw_burst.py and
raw_splat.py): its splat, its positions computed a band at a time and its cell weights give what
the whole arrays give (docs/raw-bursts.md, time and memory)."""

import numpy as np
import pytest
import torch

pytest.importorskip("skimage")

from hbis_torch.capture.raw import normalised, raw_burst_stack  # noqa: E402
from hbis_torch.reconstruct.classical import raw_burst as rb  # noqa: E402
from hbis_torch.reconstruct.classical.raw_splat import PlanePositions, Splat  # noqa: E402
from hbis_torch.reconstruct.classical.holes import fill_holes  # noqa: E402
from hbis_torch.reconstruct.classical.splat import splat  # noqa: E402
from hbis_torch.reconstruct.positions import BurstPositions  # noqa: E402
from hbis_torch.training.heldout_burst import BurstCondition  # noqa: E402
from hbis_torch.training.heldout_raw import make_raw_burst  # noqa: E402


@pytest.fixture(scope="module")
def stack():
    burst = make_raw_burst("rocket", "GBRG", "indoor", 2, 48, 2, BurstCondition("raw", frames=6))
    return raw_burst_stack(burst.mosaics, "GBRG", burst.raw, 2)[0]


def test_splat_sums_are_the_classical_splat_s_in_and_beyond_the_grid():
    g = torch.Generator().manual_seed(1)
    n, rows, cols = 4000, 20, 30
    x = torch.rand(n, generator=g, dtype=torch.float64) * 40 - 5  # some two and more nodes beyond
    y = torch.rand(n, generator=g, dtype=torch.float64) * 30 - 5
    values, weights = torch.rand(n, generator=g), torch.rand(n, generator=g)
    x[3], weights[3] = float("nan"), 0.0  # a degenerate motion's sample, left out
    acc = Splat((rows, cols), 0.45)
    for part in (slice(0, 1500), slice(1500, None)):  # in two batches
        acc.add(values[part], x[part], y[part], weights[part])
    keep = weights > 0
    num, den = splat(values[keep].double(), x[keep], y[keep], (rows, cols), 0.45, weights[keep].double())
    assert float(den.max()) > 1 and bool((acc.result(1) > 0).all())  # samples reach every node
    assert torch.allclose(acc.result(0), num, rtol=0, atol=1e-6)
    assert torch.allclose(acc.result(1), den, rtol=0, atol=1e-6)


def test_plane_positions_are_the_whole_array_s_pattern_positions(stack):
    local = {"tile_px": 16, "offsets": np.random.default_rng(0).normal(0, 0.3, (6, 3, 3, 2)).tolist()}
    lazy = rb._lazy_positions(stack.motions, 48, 48, local)
    whole = lazy.whole()
    where = [(0, 0), (1, 1)]  # GBRG's greens
    for half in (True, False):
        planes = PlanePositions(lazy, where, half=half)
        expected = torch.cat([whole[:, dv::2, du::2] for dv, du in where])
        if half:
            expected = (expected + 0.5) / 2 - 0.5
        assert planes.shape == tuple(expected.shape)
        assert torch.allclose(planes[4:9, 3:11], expected[4:9, 3:11], rtol=0, atol=1e-9)  # across the two
        assert torch.allclose(planes[7], expected[7], rtol=0, atol=1e-9)
        assert torch.allclose(planes[:, 5], expected[:, 5], rtol=0, atol=1e-9)
        # over a whole positions tensor (a caller's), read without writing over it
        kept = whole.clone()
        assert torch.allclose(PlanePositions(whole, where, half=half)[4:9, 3:11], expected[4:9, 3:11], rtol=0,
                              atol=1e-9)
        assert torch.equal(whole, kept)


def test_joint_planes_are_the_splat_of_each_colour_s_samples(stack):
    """Without differences and deblurring each plane is the classical splat and hole filling of
    its colour's samples of every frame at their whole positions, as the path was written before
    it streamed; cell weights give what their four samples' weights give."""
    raw = stack.meta["raw"]
    values, clipped = normalised(np.asarray(stack.frames), raw)
    noise = np.tile([1e-4, 1e-6], (3, 1))
    trusted = np.ones(len(values), bool)
    cells = rb.sample_weights(values, "GBRG", stack.motions, trusted, 0, [1, 1, 1], noise, cells=True)
    samples = rb.sample_weights(values, "GBRG", stack.motions, trusted, 0, [1, 1, 1], noise)
    assert tuple(cells.shape) == (6, 24, 24) and float(cells.min()) < 0.9  # some samples down-weighted
    assert torch.equal(samples.float(), cells.repeat_interleave(2, 1).repeat_interleave(2, 2))
    out = rb.joint_demosaick_sr(values, clipped, "GBRG", stack.motions, 2, cells, 0.4, differences=False,
                                deblur=False)
    same = rb.joint_demosaick_sr(values, clipped, "GBRG", stack.motions, 2, samples, 0.4, differences=False,
                                 deblur=False)
    assert np.array_equal(out, same)
    positions = rb._positions(stack.motions, 48, 48)
    weights = samples * torch.from_numpy(~clipped)
    for i, colour in enumerate("RGB"):
        where = [(k // 2, k % 2) for k, c in enumerate("GBRG") if c == colour]
        pick = [(dv, du) for dv, du in where]
        v = torch.cat([torch.from_numpy(values)[:, dv::2, du::2].reshape(-1) for dv, du in pick]).double()
        p = torch.cat([positions[:, dv::2, du::2].reshape(-1, 2) for dv, du in pick])
        w = torch.cat([weights[:, dv::2, du::2].reshape(-1) for dv, du in pick])
        keep = w > 0
        num, den = splat(v[keep], (p[keep, 0] + 0.5) * 2 - 0.5, (p[keep, 1] + 0.5) * 2 - 0.5, (96, 96), 0.4, w[keep])
        expected = np.clip(fill_holes(num, den).numpy(), 0, 1)
        assert np.abs(out[..., i] - expected).max() < 1e-5, colour


def test_reconstruction_never_holds_every_sample_s_position(stack, monkeypatch):
    def whole(self):
        raise AssertionError("every sample's position held at once")

    monkeypatch.setattr(BurstPositions, "whole", whole)
    out = rb.reconstruct_raw_burst(stack)
    assert out.shape == (96, 96, 3) and np.isfinite(out).all()
