"""A burst's samples are read a band at a time: every sample's position is never held whole
(issue [handheld], item 3: 16 frames of 12 MP would take 3 GB in float64), and the image is
the one the whole arrays give."""

import numpy as np
import pytest
import torch
from skimage import data, transform

from hbis_torch.capture.burst import assemble_burst
from hbis_torch.reconstruct.registry import reconstruct
from hbis_torch.registration import apply_homography, apply_homography_to_grid
from hbis_torch.simulate.burst import random_motions, simulate_burst

pytestmark = pytest.mark.usefixtures("one_thread")
SIZE = 128  # large enough for the pyramid and the local field's tiles


@pytest.fixture(scope="module")
def stack():
    truth = transform.resize(data.camera().astype(float) / 255, (2 * SIZE, 2 * SIZE), anti_aliasing=True)
    motions = random_motions(6, (SIZE, SIZE), np.random.default_rng(4), 2.0, 1.0)
    burst = simulate_burst(truth, 2, motions, noise=0.005, seed=4)
    found, _ = assemble_burst(burst.frames, 2)
    assert found.meta.get("local_motion") is not None  # the positions carry the local field too
    return found


def test_the_grid_form_of_a_homography_matches_the_point_form():
    rng = np.random.default_rng(0)
    m = np.eye(3) + rng.normal(0, 1e-3, (3, 3, 3)) * np.array([[1, 1, 1000], [1, 1, 1000], [1e-3, 1e-3, 0]])
    rows = torch.tensor([0.0, 1.0, 2047.0, 5000.0, 8191.0])
    cols = torch.tensor([0.0, 3.0, 4095.0, 8191.0])
    grid = apply_homography_to_grid(torch.from_numpy(m), rows, cols)
    v, u = torch.meshgrid(rows.double(), cols.double(), indexing="ij")
    points = torch.stack((u, v), -1).reshape(1, -1, 2).expand(3, -1, -1)
    exact = apply_homography(torch.from_numpy(m), points).reshape(grid.shape)
    assert float((grid - exact).abs().max()) <= 4 * np.spacing(8192.0)  # a few roundings: 7e-12 px


def test_the_grid_written_into_a_callers_memory_and_the_local_shifts_added_in_place():
    from hbis_torch.registration.local import add_offsets, sample_offsets

    rng = np.random.default_rng(1)
    scale = np.array([[1, 1, 10], [1, 1, 10], [1e-3, 1e-3, 0]])
    m = torch.from_numpy(np.eye(3) + rng.normal(0, 1e-3, (2, 3, 3)) * scale)
    rows, cols = torch.arange(40.0), torch.arange(72.0)
    kept = torch.full((2, 40, 72, 2), np.nan, dtype=torch.float64)
    assert apply_homography_to_grid(m, rows, cols, out=kept) is kept
    assert torch.equal(kept, apply_homography_to_grid(m, rows, cols))
    offsets = torch.from_numpy(rng.normal(0, 0.3, (2, 2, 3, 2)))  # 2 x 3 tiles of 32 px
    shifted = kept + sample_offsets(offsets, kept, 32)
    assert add_offsets(offsets, kept, 32) is kept and torch.equal(kept, shifted)


def test_burst_positions_index_as_the_whole_array(stack):
    from hbis_torch.reconstruct.positions import burst_positions

    lazy, trusted = burst_positions(stack, lazy=True)
    whole, same = burst_positions(stack)
    assert torch.equal(trusted, same) and lazy.shape == tuple(whole.shape)
    assert torch.equal(lazy.whole(), whole)
    for index in (3, -1, (2, 5), (1, slice(7, 90, 4)), (slice(1, 4), slice(None, None, 3)),
                  (2, slice(10, 20), slice(30, 41)), (0, 5, 7), (slice(None), 100, slice(2, 9))):
        assert torch.equal(lazy[index], whole[index]), index
    with pytest.raises(TypeError):
        lazy[[0, 1]]
    with pytest.raises(IndexError):
        lazy[len(lazy)]


def test_the_burst_path_never_holds_every_samples_position(stack, monkeypatch):
    """The classical method reads the positions a band at a time, the robustness, coverage and
    fill a frame at a time; the image is the one the whole arrays give, bit for bit."""
    import hbis_torch.reconstruct.classical.burst as classical_burst
    import hbis_torch.reconstruct.classical.sr as sr
    import hbis_torch.reconstruct.positions as positions
    from hbis_torch.reconstruct.positions import BurstPositions

    F, H, W = stack.frames.shape
    monkeypatch.setattr(positions, "CACHE_BYTES", 0)  # a large burst's: none kept
    monkeypatch.setattr(sr, "BATCH_SAMPLES", 2 * W * F)  # bands of two rows of every frame
    largest, band = [0], BurstPositions._band

    def counted(self, frames, rows, cols=slice(None)):
        out = band(self, frames, rows, cols)
        largest[0] = max(largest[0], out[..., 0].numel())
        return out

    def refused(self):
        raise AssertionError("every sample's position was asked for at once")

    monkeypatch.setattr(BurstPositions, "_band", counted)
    monkeypatch.setattr(BurstPositions, "whole", refused)
    streamed = reconstruct(stack, "classical")
    assert 0 < largest[0] <= H * W  # one frame at most, never the burst's F H W
    monkeypatch.setattr(BurstPositions, "whole", lambda self: band(self, slice(None), slice(None)))
    monkeypatch.setattr(classical_burst.classical_burst, "streams", False)  # the whole arrays instead
    assert np.array_equal(reconstruct(stack, "classical"), streamed)


def test_a_colour_burst_never_holds_its_float_rgb_frames(stack, monkeypatch):
    """An RGB burst reconstructed channel by channel converts its luma a frame at a time and
    one channel at a time, never the float RGB frames whole (a 12 MP burst's: 2.3 GB); the image
    is the one the whole float frames give, bit for bit."""
    import hbis_torch.reconstruct.burst as burst

    gains = np.array([1.0, 0.8, 0.6])
    rgb = type(stack)(np.round(stack.frames[..., None] * gains).astype(stack.frames.dtype), dict(stack.meta))
    whole = burst.corrected_frames

    def one_channel_at_most(stack, channel=None):
        assert channel is not None, "the whole float RGB frames were made"
        return whole(stack, channel)

    monkeypatch.setattr(burst, "corrected_frames", one_channel_at_most)
    by_channel = reconstruct(rgb, "classical")
    assert by_channel.shape == (2 * stack.frames.shape[1], 2 * stack.frames.shape[2], 3)
    monkeypatch.setattr(burst, "corrected_frames", lambda stack, channel=None: whole(stack)[..., channel].contiguous())
    monkeypatch.setattr(burst, "corrected_frame", lambda stack, k: whole(stack)[k])
    monkeypatch.setattr(burst, "corrected_luma", lambda stack: burst._luma(whole(stack)))
    assert np.array_equal(reconstruct(rgb, "classical"), by_channel)


def test_a_colour_bursts_channels_share_what_depends_on_their_samples_places(stack, monkeypatch):
    """The three channels of an RGB burst are the same samples with other values: the lattice's
    offset, the samples' nodes and the hole fit's matrix are computed for the first channel
    alone, and the image is the one three independent channels give, bit for bit."""
    import hbis_torch.reconstruct.classical.burst as classical_burst
    import hbis_torch.reconstruct.classical.lattice_fit as lattice_fit
    import hbis_torch.reconstruct.classical.sr as sr

    rgb = type(stack)(np.round(stack.frames[..., None] * np.array([1.0, 0.8, 0.6])).astype(stack.frames.dtype),
                      dict(stack.meta))
    calls = {"common_offset_of": 0, "normal_equations": 0, "node_batch": 0}
    for module, name in ((sr, "common_offset_of"), (lattice_fit, "normal_equations"), (sr, "node_batch")):
        def counted(*args, _name=name, _real=getattr(module, name), **kw):
            calls[_name] += 1
            return _real(*args, **kw)

        monkeypatch.setattr(module, name, counted)
    shared = reconstruct(rgb, "classical")
    batches = len(sr.batch_slices(*stack.frames.shape, sr.BATCH_SAMPLES))
    assert calls == {"common_offset_of": 1, "normal_equations": 1, "node_batch": batches}
    monkeypatch.setattr(classical_burst.classical_burst, "shares_samples", False)
    assert np.array_equal(reconstruct(rgb, "classical"), shared)
    assert calls["normal_equations"] == 4  # (the check: three more without sharing)


def test_the_learned_methods_classical_image_shares_the_channels_samples_too(stack, monkeypatch):
    """The learned method refines each channel's classical image, made as the classical method's
    (its channels sharing their samples' places): the same image as without sharing."""
    import hbis_torch.reconstruct.learned.burst as learned_burst

    rgb = type(stack)(np.round(stack.frames[..., None] * np.array([1.0, 0.8, 0.6])).astype(stack.frames.dtype),
                      dict(stack.meta))
    shared = reconstruct(rgb, "learned", adapt=False)
    monkeypatch.setattr(learned_burst.learned_burst, "shares_samples", False)
    assert np.array_equal(reconstruct(rgb, "learned", adapt=False), shared)


def test_a_small_bursts_positions_are_computed_once_with_the_same_bits(stack, monkeypatch):
    import hbis_torch.reconstruct.positions as positions
    from hbis_torch.reconstruct.positions import BurstPositions, burst_positions

    computed, band = [], BurstPositions._band

    def counted(self, frames, rows, cols=slice(None), **kw):  # kw: out, where a frame is kept
        computed.append(range(self.shape[0])[frames])
        return band(self, frames, rows, cols, **kw)

    monkeypatch.setattr(BurstPositions, "_band", counted)
    kept, _ = burst_positions(stack, lazy=True)
    monkeypatch.setattr(positions, "CACHE_BYTES", 0)
    streamed, _ = burst_positions(stack, lazy=True)
    F, H, W = stack.frames.shape
    for index in (3, (2, 5), (1, slice(7, 90, 4)), (slice(1, 4), slice(None, None, 3)), (0, 5, 7),
                  (slice(None), 100, slice(2, 9)), (slice(None, None, 2), slice(10, 20), slice(30, 41))):
        assert torch.equal(kept[index], streamed[index]), index
    assert torch.equal(kept.whole(), streamed.whole())
    computed.clear()
    for _ in range(3):  # every frame is kept now: read again without computing
        kept[:, :, 5], kept[2]
    assert not computed
    whole = kept.whole()
    whole += 1.0  # the whole array is the caller's own
    assert torch.equal(kept[1], streamed[1])


def test_the_lazy_samples_keep_the_weights_values_in_float32(stack):
    from hbis_torch.reconstruct.burst import burst_samples
    from hbis_torch.reconstruct.positions import BurstPositions

    _, lazy, _, light = burst_samples(stack, lazy=True)
    _, whole, _, heavy = burst_samples(stack)
    assert isinstance(lazy, BurstPositions) and light.dtype == torch.float32
    assert whole.dtype == torch.float64 and heavy.dtype == torch.float64
    assert torch.equal(light.double(), heavy) and float(heavy[1:].min()) < 1.0  # weights, not all ones


def test_the_tally_drops_samples_beyond_the_grid_or_without_weight():
    from hbis_torch.reconstruct.burst_fill import Tally

    tally = Tally((4, 5), 0, (2,))
    where = torch.zeros(4, 5, 2, dtype=torch.float64)
    where[1, 2], where[2, 3], where[3, 4] = float("nan"), float("inf"), 7.0  # nowhere, nowhere, beyond
    where[0, 1] = torch.tensor([4.0, 3.0])  # the last pixel
    weight = torch.ones(4, 5)
    weight[0, 0] = 0.05  # counted in the coverage, too light for the fill
    tally.add(1, where, weight)
    cover = tally.coverage()
    assert cover[0, 0] == pytest.approx(15.05) and cover[3, 4] == 1.0 and cover.sum() == pytest.approx(16.05)
    tally.add(0, where, weight)  # the reference: only the fill
    assert np.array_equal(tally.coverage(), cover) and tally.added == 2
    hit = tally.hits[2].reshape(10, 12)[1:-1, 1:-1]
    assert bool(hit[0, 0]) and bool(hit[6, 8]) and int(hit.sum()) == 2  # the nodes nearest (0, 0) and (4, 3)


def test_the_rejections_grow_by_the_3x3_minimum():
    from hbis_torch.reconstruct.burst import _minimum_3x3

    rng = torch.Generator().manual_seed(1)
    for shape in ((37, 53), (1, 9), (8, 1), (2, 2)):
        image = torch.rand(shape, generator=rng)
        pooled = -torch.nn.functional.max_pool2d(-image[None, None], 3, 1, 1)[0, 0]
        assert torch.equal(_minimum_3x3(image), pooled), shape
    spot = torch.ones(5, 6)
    spot[0, 0] = 0.25
    grown = _minimum_3x3(spot)
    assert torch.equal(grown[:2, :2], torch.full((2, 2), 0.25)) and float(grown[2:].min()) == 1.0


def test_the_blend_weight_is_the_coverage_enlarged_bilinear():
    from scipy.ndimage import zoom

    from hbis_torch.reconstruct.burst import FULL_COVERAGE, _blend_weight

    rng = np.random.default_rng(3)
    for shape, scale in (((23, 31), 2), ((7, 5), 3), ((4, 9), 4), ((6, 6), 1)):
        cover = rng.random(shape) * 3 * FULL_COVERAGE * (rng.random(shape) > 0.3)
        alpha = np.clip(cover / FULL_COVERAGE, 0, 1)
        expected = np.clip(zoom(alpha, scale, order=1, mode="nearest", grid_mode=True), 0, 1).astype(np.float32)
        got = _blend_weight(cover, scale)
        assert got.dtype == np.float32 and got.shape == expected.shape
        assert np.array_equal(got, expected), (shape, scale)


def test_positions_asked_not_to_keep_compute_only_the_bands_read():
    # the raw path's still test reads three bands of each frame: a small burst's positions are not
    # made whole for it (keep=False), and the bands are the kept ones' to the bit
    from hbis_torch.reconstruct.positions import BurstPositions

    motions = np.repeat(np.eye(3)[None], 3, 0)
    motions[1:, :2, 2] = [[0.3, -0.2], [1.7, 0.4]]
    kept, fresh = BurstPositions(motions, 40, 30), BurstPositions(motions, 40, 30, keep=False)
    assert torch.equal(kept[1, 18:22], fresh[1, 18:22]) and torch.equal(kept[2], fresh[2])
    assert kept._kept is not None and fresh._kept is None
