"""The classical method's faster steps against the plain forms they replace: the lattice's
nodes from the float32 node splines against float64 positions, the Wiener filter's mirrored
rows, the boundary spectrum of the periodic + smooth split, the 3 x 3 mean of the power, the
holes found in NumPy."""

import math

import numpy as np
import pytest
import torch

from hbis_torch.optics import NodePositions, interpolate_positions
from hbis_torch.reconstruct.classical.lattice import batch_slices, node_batch
from hbis_torch.reconstruct.classical.periodic import (
    add_shifted_smooth,
    mirror_borders,
    periodic_smooth,
    shift_image,
    smooth_spectrum,
)
from hbis_torch.reconstruct.classical import wiener
from hbis_torch.reconstruct.classical.holes import _holes
from hbis_torch.reconstruct.classical.wiener import _add_at, _mean_3x3, _Model, _ring_of, _ring_sums


def _nodes(gen, count=3, height=40, width=56, amplitude=0.0):
    """NodePositions of a small stack: every pixel on the grid (plus a smooth displacement of
    ``amplitude`` LR px and a per-frame shift)."""
    nu, nv = np.linspace(0, width - 1, 5), np.linspace(0, height - 1, 4)
    base = torch.stack(torch.broadcast_tensors(torch.from_numpy(nu)[None, :], torch.from_numpy(nv)[:, None]), -1)
    wobble = amplitude * torch.rand((count, len(nv), len(nu), 2), generator=gen, dtype=torch.float64)
    shift = torch.rand((count, 1, 1, 2), generator=gen, dtype=torch.float64) * 3
    shift[0] = 0  # the first frame on the pixel grid: every sample halfway between two nodes at even h
    return NodePositions(base + wobble + shift, nu, nv, width, height)


def test_nodes_from_splines_match_float64_positions():
    """Each sample's node from the float32 parts of the node splines is the float64 position's
    nearest node (ties included: frame 0 sits exactly halfway at h = 4), and node minus
    sample agrees to float32 rounding."""
    gen = torch.Generator().manual_seed(5)
    cases = ((4, 0.0, (0.0, 0.0)), (4, 2.0, (0.3, -0.45)), (7, 5.0, (0.0, 0.1)), (2, 1.0, (-0.5, 0.5)))
    for h, amplitude, offset in cases:
        nodes = _nodes(gen, amplitude=amplitude)
        frames = torch.rand((3, nodes.height, nodes.width), generator=gen)
        dense = interpolate_positions(nodes)
        for part in batch_slices(3, nodes.height, nodes.width, 2 * nodes.height * nodes.width):
            fast, plain = node_batch(frames, nodes, part, h, offset), node_batch(frames, dense, part, h, offset)
            assert torch.equal(fast.col, plain.col) and torch.equal(fast.row, plain.row)
            assert float((fast.dx - plain.dx).abs().max()) < 1e-5 and float((fast.dy - plain.dy).abs().max()) < 1e-5
            assert torch.equal(fast.values, plain.values)
            x = (dense[part][..., 0].reshape(-1) + 0.5) * h - 0.5 - offset[0]
            assert float((fast.col - fast.dx.double() - x).abs().max()) < 1e-5


def _filter_by_definition(model, shifts, s2, beta, noise2, strength):
    """The MMSE filter of wiener_deblur's docstring at every frequency of the half spectrum,
    every alias on every frequency (the image's measured power below the prior's)."""
    rows, cols = torch.arange(len(model.fy)), torch.arange(len(model.fx))
    num = torch.zeros((len(rows), len(cols)), dtype=torch.complex128)
    den = torch.zeros((len(rows), len(cols)), dtype=torch.float64)
    for kx, ky in shifts:
        prior, k_mag, w, k2 = (t.double() for t in model.terms(kx, ky, rows, cols, s2, beta))
        gx, gy = model.fx.double()[None, :] + kx, model.fy.double()[:, None] + ky
        phase = torch.exp(-2j * math.pi * (gx * model.offset[0] + gy * model.offset[1]))
        num += prior * k_mag * w * phase
        den += prior * k2  # abs(K)^2, the lens's square averaged over its spread
    return num / (den + strength * noise2)


@pytest.mark.parametrize("rows, cols, h, tolerance, lens", [
    (24, 32, 3, 1e-5, 0.0),  # every frequency evaluated; an even row count: fy = -1/2 too
    (25, 32, 3, 1e-5, 0.0),  # odd
    (24, 32, 3, 1e-5, 0.4),  # a lens, its transfer and its square averaged over LENS_SPREAD
    (1024, 768, 2, 3e-4, 0.0),  # the aliases on every 3rd frequency (768 / 2 / ALIAS_SAMPLES = 128): 8.7e-5
])
def test_the_filter_by_blocks_and_coarse_aliases_matches_its_definition(rows, cols, h, tolerance, lens):
    """_apply_filter (blocks of rows filtered with their mirrors, the aliases' sums interpolated
    from a coarse grid) against the filter computed at every frequency from its definition; an
    offset that is not half a pixel, so that the aliases' phases differ between fy and -fy."""
    fy = torch.fft.fftfreq(rows, dtype=torch.float64).to(torch.float32)
    fx = torch.fft.rfftfreq(cols, dtype=torch.float64).to(torch.float32)
    model = _Model(fx, fy, h, 0.9, 1.5, (0.2, -0.35), 1e-4, lens)
    shifts = [(kx, ky) for ky in (-1, 0, 1) for kx in (-1, 0, 1)]
    terms = (shifts, 1e-4, 2.0, 1e-5, 2.0)
    spectrum = torch.ones((rows, len(fx)), dtype=torch.complex64)
    wiener._apply_filter(spectrum, torch.full((rows, len(fx)), 1e-12), model, terms)
    expected = _filter_by_definition(model, *terms)
    assert float((spectrum - expected).abs().max()) <= tolerance * float(expected.abs().max())


def test_alias_terms_added_as_a_slice_or_by_index_add_alike():
    """An alias's terms go to contiguous rows as a slice's add_, to others by index_add_: the
    same sums."""
    gen = torch.Generator().manual_seed(9)
    sums = torch.rand((6, 8), generator=gen)
    values = torch.rand((3, 4), generator=gen)
    for rows in (torch.tensor([1, 2, 3]), torch.tensor([0, 2, 5])):
        got, expected = sums.clone(), sums.clone()
        _add_at(got, rows, torch.arange(2, 6), values, 0.5)
        expected[:, 2:6].index_add_(0, rows, values, alpha=0.5)
        assert torch.equal(got, expected)


def test_holes_found_in_numpy_match_torch_nonzero():
    """fill_holes' holes: the same nodes, in the same (row-major) order, as torch's nonzero of
    the comparison; none, a few, whole rows and columns, one row, one column."""
    gen = torch.Generator().manual_seed(3)
    den = 0.5 + torch.rand((60, 45), generator=gen)
    assert _holes(den, 0.25)[0].numel() == 0
    den[7, 3] = den[7, 40] = den[59, 0] = 0.0
    den[20] = 0.1
    den[:, 44] = 0.2
    for cases in (den, torch.rand((1, 9), generator=gen), torch.rand((9, 1), generator=gen)):
        rows, cols = _holes(cases, 0.25)
        assert torch.equal(torch.stack((rows, cols), 1), torch.nonzero(cases < 0.25))


def test_ring_sums_from_half_the_rows_match_every_row():
    """The rings' counts and power sums found on rows 0 .. rows // 2 (their mirrors' power
    added) against bincount over every row (odd and even sizes, more rows than a block, float32
    and float64 power, which is left as it was)."""
    gen = torch.Generator().manual_seed(10)
    for rows, cols in ((300, 40), (301, 33), (2, 8), (1, 6), (7, 7)):
        fy = torch.fft.fftfreq(rows, dtype=torch.float64)[:, None]
        fx = torch.fft.rfftfreq(cols, dtype=torch.float64)[None, :]
        edges = torch.logspace(math.log10(1.5 / max(rows, cols)), math.log10(0.71), 25, dtype=torch.float64)
        bins = _ring_of(fx, fy, edges).reshape(-1) + 1
        for dtype in (torch.float32, torch.float64):
            power = torch.rand((rows, cols // 2 + 1), generator=gen, dtype=dtype)
            before = power.clone()
            count, total = _ring_sums(power, fx, fy, edges)
            assert torch.equal(count, torch.bincount(bins, minlength=26)[1:25])
            expected = torch.bincount(bins, power.reshape(-1).double(), minlength=26)[1:25]
            assert torch.allclose(total, expected, rtol=1e-12, atol=0)
            assert torch.equal(power, before)


def test_periodic_smooth_and_mean_3x3_match_their_plain_forms():
    """The boundary image's spectrum from 1-D FFTs against Moisan's rfft2 of the boundary image;
    separable 3 x 3 means against avg_pool2d (float32 and float64, odd and even sizes)."""
    gen = torch.Generator().manual_seed(4)
    for shape in ((33, 48), (50, 31), (2, 5), (300, 17)):  # 300 rows: more than one block
        for dtype, tol in ((torch.float64, 1e-12), (torch.float32, 1e-5)):
            image = torch.rand(shape, generator=gen, dtype=dtype)
            v = torch.zeros_like(image)
            v[0, :] += image[-1, :] - image[0, :]
            v[-1, :] += image[0, :] - image[-1, :]
            v[:, 0] += image[:, -1] - image[:, 0]
            v[:, -1] += image[:, 0] - image[:, -1]
            M, N = shape
            q = torch.arange(M, dtype=dtype)[:, None]
            r = torch.arange(N // 2 + 1, dtype=dtype)[None, :]
            den = 2 * torch.cos(2 * math.pi * q / M) + 2 * torch.cos(2 * math.pi * r / N) - 4
            den[0, 0] = 1
            spectrum = torch.fft.rfft2(v) / den
            spectrum[0, 0] = 0
            p, s = periodic_smooth(image)
            assert float((s - torch.fft.irfft2(spectrum, s=shape)).abs().max()) < tol
            assert float((p + s - image).abs().max()) < tol
            pooled = torch.nn.functional.avg_pool2d(image[None, None], 3, 1, 1, count_include_pad=False)[0, 0]
            assert float((_mean_3x3(image.clone()) - pooled).abs().max()) < tol


def test_smooth_part_shifted_in_the_fourier_domain_matches_shift_image():
    """The smooth part's bicubic shift as a DFT multiplier plus the mirrored borders mended
    equals shift_image of the smooth part itself (every offset sign, odd and even sizes)."""
    gen = torch.Generator().manual_seed(6)
    cases = (((40, 52), (0.5, 0.5)), ((33, 27), (-0.5, 0.2)), ((8, 9), (0.31, -0.44)), ((64, 50), (0.0, 0.25)))
    for shape, offset in cases:
        image = torch.rand(shape, generator=gen, dtype=torch.float64)
        smooth = smooth_spectrum(image)
        expected = shift_image(torch.fft.irfft2(smooth, s=shape), offset)
        got = torch.fft.irfft2(add_shifted_smooth(torch.zeros_like(smooth), smooth, shape, offset), s=shape)
        assert float((mirror_borders(got, smooth, offset) - expected).abs().max()) < 1e-12


def test_all_finite_by_the_sum_agrees_with_isfinite():
    """A NaN or an infinity anywhere is found; finite values whose sum overflows are finite."""
    from hbis_torch.reconstruct.classical.sr import _all_finite

    values = torch.rand(1000)
    assert _all_finite(values)
    for bad in (float("nan"), float("inf"), -float("inf")):
        broken = values.clone()
        broken[517] = bad
        assert not _all_finite(broken)
    large = torch.full((8,), 3e38)
    assert _all_finite(large) and not _all_finite(torch.cat((large, torch.tensor([float("nan")]))))
    assert _all_finite(torch.tensor([float(torch.finfo(torch.float32).max), -float(torch.finfo(torch.float32).max)]))


def test_fill_holes_in_place_gives_the_same_image():
    """Holes of every kind (empty nodes, a wide empty band, weak nodes): the same bits in place."""
    from hbis_torch.reconstruct.classical.holes import fill_holes

    gen = torch.Generator().manual_seed(8)
    den = torch.rand((60, 70), generator=gen) + 0.5
    den[10:14, 20:23] = 0  # a small hole
    den[:, 40:62] = 0  # a band wider than the first blurs
    den[30, 5] = 0.1  # a weak node
    num = den * torch.rand((60, 70), generator=gen)
    expected = fill_holes(num, den)
    got = fill_holes(num.clone(), den, in_place=True)
    assert torch.isfinite(got).all() and torch.equal(got, expected)
