"""The fast full-frame paths give what the exact ones gave: sample positions from nodes (with the
registration's correction applied on the nodes) against the per-pixel trace, the float32 Wiener
step against float64, and the holes filled from local blurs against whole-image ones. Behaviour,
not speed (that is benchmarks/bench_fullframe.py)."""

import math

import numpy as np
import pytest
import torch

from hbis_torch.config import FoveaSystem
from hbis_torch.metrics import psnr
from hbis_torch.optics import interpolate_positions, landing_at, node_positions, sensor_position
from hbis_torch.reconstruct.classical import classical_sr, optics_cutoff, wiener_deblur
from hbis_torch.reconstruct.classical import shift_image
from hbis_torch.reconstruct.classical import sr as classical_sr_module
from hbis_torch.reconstruct.classical.holes import _blur_at, _gaussian_blur, fill_holes
from hbis_torch.reconstruct.classical.splat import gradient_into
from hbis_torch.reconstruct.positions import stack_sample_nodes, stack_sample_positions
from hbis_torch.scan import plan_scan
from hbis_torch.simulate.cases import make_stack

SYSTEM = FoveaSystem()

pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture(scope="module")
def stack_and_truth():
    return make_stack(SYSTEM, 4, (900, 600, 96, 80), "camera", 7)


def test_node_positions_match_the_exact_trace_over_the_whole_sensor():
    """On the full 960 x 1280 frame, at a spread of pixels up to the corners: < 1e-6 px."""
    plan = plan_scan(SYSTEM, 4)
    phases, ref = plan.phases_deg, plan.reference_index
    nodes = node_positions(SYSTEM, phases, ref)
    rows = np.unique(np.r_[np.linspace(0, SYSTEM.camera.rows - 1, 23).round().astype(int), 1, 958])
    cols = np.unique(np.r_[np.linspace(0, SYSTEM.camera.cols - 1, 29).round().astype(int), 1, 1278])
    fast = interpolate_positions(nodes, rows, cols)
    u = torch.from_numpy(cols.astype(np.float64))[None, :]
    v = torch.from_numpy(rows.astype(np.float64))[:, None]
    landing = landing_at(SYSTEM, u, v, phases[:, 0, None, None], phases[:, 1, None, None])
    exact = sensor_position(SYSTEM, landing, phases[ref, 0], phases[ref, 1])
    assert fast.dtype == torch.float64 and fast.shape == (len(phases), len(rows), len(cols), 2)
    assert float((fast - exact).abs().max()) < 1e-6
    # the splines evaluated along u first (many rows) and along v first (a band of a few rows,
    # as the classical splat's batches ask): the same positions to float32 rounding
    band = interpolate_positions(nodes, [1, 2, 3], cols)
    assert float((band - interpolate_positions(nodes, np.arange(SYSTEM.camera.rows), cols)[:, 1:4]).abs().max()) < 1e-6


@pytest.mark.parametrize("registration", ["optics", "auto"])
def test_stack_positions_from_nodes_match_the_exact_path(stack_and_truth, registration):
    """The registration's correction applied on the nodes, then interpolated, against applied to
    every exactly traced pixel: the same positions within 1e-3 output px, the same frames trusted."""
    stack, _ = stack_and_truth
    fast, ok_fast = stack_sample_positions(stack, registration)
    exact, ok_exact = stack_sample_positions(stack, registration, exact=True)
    assert torch.equal(ok_fast, ok_exact)
    assert float((fast - exact).abs().max()) * stack.h < 1e-3


def test_classical_output_with_node_positions_matches_the_exact_positions(stack_and_truth):
    stack, truth = stack_and_truth
    frames = stack.to_float()
    cutoff = optics_cutoff(SYSTEM)
    images = [classical_sr(frames, stack_sample_positions(stack, "auto", exact=exact)[0], stack.h,
                           cutoff=cutoff).numpy() for exact in (False, True)]
    assert abs(psnr(images[0], truth) - psnr(images[1], truth)) < 0.05
    assert np.abs(images[0] - images[1]).max() < 1e-3


def test_classical_from_nodes_matches_classical_from_every_position(stack_and_truth, monkeypatch):
    """Positions interpolated from the nodes a batch at a time (never the whole stack's) give
    the image the whole stack's positions give, to float32 rounding; and so do batches of any
    size (bands of rows of every frame, or one row of a few frames at a time): the samples'
    common offset comes from the same rows whatever the batches, only the order in which a
    node's samples are summed changes."""
    stack, _ = stack_and_truth
    frames = stack.to_float()
    nodes, ok_nodes = stack_sample_nodes(stack, "auto")
    positions, ok = stack_sample_positions(stack, "auto")
    assert torch.equal(ok_nodes, ok)
    cutoff = optics_cutoff(SYSTEM)
    whole = classical_sr(frames, nodes, stack.h, cutoff=cutoff)
    # every position in float64 against the nodes' float32 parts (lattice.py): 1e-6 HR px apart
    assert float((whole - classical_sr(frames, positions, stack.h, cutoff=cutoff)).abs().max()) < 1e-5
    for samples in (3 * 96 * 80, 30 * 96, 8 * 80):  # bands of 18 and 2 rows; one row of half the frames
        monkeypatch.setattr(classical_sr_module, "BATCH_SAMPLES", samples)
        assert float((whole - classical_sr(frames, nodes, stack.h, cutoff=cutoff)).abs().max()) < 1e-6
        assert float((whole - classical_sr(frames, positions, stack.h, cutoff=cutoff)).abs().max()) < 1e-5


def test_wiener_in_float32_matches_float64():
    """The deblurring's FFTs and filter in float32 against float64 (odd and even sizes, a
    sub-pixel offset and the optics): differences far below the noise floor."""
    gen = torch.Generator().manual_seed(3)
    for shape, offset in (((96, 130), (0.5, 0.5)), ((101, 77), (0.2, -0.35))):
        image = torch.rand(shape, generator=gen, dtype=torch.float64)
        image = torch.nn.functional.avg_pool2d(image[None, None], 3, 1, 1)[0, 0]  # some smoothness
        kw = {"h": 4, "offset": offset, "kernel_sigma": 0.45, "noise": 0.01, "cutoff": optics_cutoff(SYSTEM),
              "strength": 2.0}
        single = wiener_deblur(image, dtype=torch.float32, **kw)
        double = wiener_deblur(image, dtype=torch.float64, **kw)
        assert single.dtype == torch.float64 and single.shape == shape
        assert float((single - double).abs().max()) < 1e-4
        rms = float((single - double).square().mean().sqrt())
        # as PSNR against the float64 result: far above any reconstruction's (< 60 dB)
        assert -20 * math.log10(rms) > 90


def test_holes_filled_from_local_blurs_match_whole_image_blurs():
    gen = torch.Generator().manual_seed(5)
    img = torch.rand(60, 70, generator=gen, dtype=torch.float64)
    rows = torch.tensor([0, 0, 59, 30, 1, 58, 12])
    cols = torch.tensor([0, 69, 0, 35, 68, 1, 2])
    for sigma in (1.0, 2.0, 4.0):
        local = _blur_at(img, sigma, rows, cols)
        whole = _gaussian_blur(img, sigma)[rows, cols]
        assert float((local - whole).abs().max()) < 2e-3 * float(whole.abs().max())
    # a frame's border missing (the full frame's holes): filled near the neighbours' values
    den = torch.ones(60, 70, dtype=torch.float64)
    den[0, :] = 0
    den[:, -1] = 0
    num = img * den
    filled = fill_holes(num, den)
    assert torch.equal(filled[1:, :-1], img[1:, :-1])
    assert float((filled[0, 1:-1] - img[1, 1:-1]).abs().max()) < 1.0
    assert bool(torch.isfinite(filled).all())


def test_shift_image_is_grid_samples_bicubic():
    """The two 4-tap filters give grid_sample's bicubic (reflected borders) at every node,
    small images included, without its (rows, cols, 2) grid."""
    gen = torch.Generator().manual_seed(11)
    for shape in ((50, 61), (7, 9), (3, 3), (2, 5), (1, 4)):
        image = torch.rand(shape, generator=gen, dtype=torch.float64)
        rows, cols = shape
        for offset in ((0.5, 0.5), (0.2, -0.35), (-0.5, 0.0), (0.0, 0.25)):
            v = (torch.arange(rows, dtype=torch.float64) - offset[1]) * (2 / max(rows - 1, 1)) - 1
            u = (torch.arange(cols, dtype=torch.float64) - offset[0]) * (2 / max(cols - 1, 1)) - 1
            grid = torch.stack(torch.meshgrid(v, u, indexing="ij")[::-1], -1)[None]
            expected = torch.nn.functional.grid_sample(image[None, None], grid, mode="bicubic",
                                                       padding_mode="reflection", align_corners=True)[0, 0]
            assert float((shift_image(image, offset) - expected).abs().max()) < 1e-12
    assert shift_image(image, (0.0, 0.0)) is image
    base = torch.rand(shape, generator=gen, dtype=torch.float64)
    total = shift_image(image, (0.2, -0.35), add_to=base.clone())
    assert float((total - base - shift_image(image, (0.2, -0.35))).abs().max()) < 1e-12


def test_gradient_into_is_torch_gradient():
    gen = torch.Generator().manual_seed(2)
    for shape in ((2, 7), (3, 2), (40, 33)):
        for dtype in (torch.float32, torch.float64):
            image = torch.rand(shape, generator=gen, dtype=dtype)
            for dim in (0, 1):
                out = torch.full(shape, float("nan"), dtype=dtype)
                assert torch.equal(gradient_into(image, dim, out), torch.gradient(image, dim=dim)[0])
                assert torch.equal(gradient_into(image, dim, out, twice=True), 2 * torch.gradient(image, dim=dim)[0])


def test_wiener_overwrite_gives_the_same_image_and_leaves_the_input_alone_by_default():
    gen = torch.Generator().manual_seed(4)
    image = torch.nn.functional.avg_pool2d(torch.rand(1, 1, 64, 72, generator=gen), 3, 1, 1)[0, 0]
    kw = {"h": 4, "offset": (0.5, 0.5), "kernel_sigma": 0.45, "noise": 0.01, "cutoff": optics_cutoff(SYSTEM)}
    before = image.clone()
    kept = wiener_deblur(image, **kw)
    assert torch.equal(image, before)
    reused = wiener_deblur(image, overwrite=True, **kw)
    assert torch.equal(kept, reused) and reused.data_ptr() == image.data_ptr()


def test_wiener_inverse_in_place_gives_the_same_image(monkeypatch):
    """Spectra of IN_PLACE_FFT_SIZE or more (a full frame at h = 4 or 7) are inverted a block at a
    time without irfft2's spectrum-sized temporary: the same image, odd and even sizes."""
    from hbis_torch.reconstruct.classical import wiener

    gen = torch.Generator().manual_seed(6)
    for shape in ((300, 260), (301, 517)):
        image = torch.nn.functional.avg_pool2d(torch.rand(1, 1, *shape, generator=gen), 3, 1, 1)[0, 0]
        kw = {"h": 4, "offset": (0.5, 0.5), "kernel_sigma": 0.45, "noise": 0.01, "cutoff": optics_cutoff(SYSTEM)}
        whole = wiener_deblur(image, **kw)
        monkeypatch.setattr(wiener, "IN_PLACE_FFT_SIZE", 1)
        in_place = wiener_deblur(image, **kw)
        monkeypatch.undo()
        assert float((whole - in_place).abs().max()) < 1e-6


def test_a_large_images_separable_blur_in_bands_is_the_whole_images_to_the_bit(monkeypatch):
    import importlib

    holes = importlib.import_module("hbis_torch.reconstruct.classical.holes")
    gen = torch.Generator().manual_seed(3)
    for shape, dtype, band in (((2, 700, 300), torch.float32, 300), ((1500, 300), torch.float64, 450)):
        img = torch.rand(shape, generator=gen, dtype=dtype)
        for sigma in (1.0, 4.0):
            monkeypatch.setattr(holes, "BLUR_BAND_ROWS", 10**6)
            whole = holes._separable_blur(img, sigma)
            monkeypatch.setattr(holes, "BLUR_BAND_ROWS", band)  # two and three bands, with halos
            assert torch.equal(holes._separable_blur(img, sigma), whole), (shape, sigma)


def test_the_separable_blur_is_the_blur_at_the_holes_at_every_node():
    from hbis_torch.reconstruct.classical.holes import _separable_blur

    gen = torch.Generator().manual_seed(7)
    for shape in ((60, 70), (9, 40), (5, 5)):
        img = torch.rand(shape, generator=gen, dtype=torch.float64)
        rows, cols = (g.reshape(-1) for g in torch.meshgrid(torch.arange(shape[0]), torch.arange(shape[1]), indexing="ij"))
        for sigma in (1.0, 2.0):
            whole = _separable_blur(img, sigma)
            assert whole.shape == img.shape
            assert float((whole.reshape(-1) - _blur_at(img, sigma, rows, cols)).abs().max()) < 1e-12, (shape, sigma)
