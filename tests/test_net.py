"""The SR network: space-to-depth written as reshape/permute, shapes, and its starting point."""

import pytest
import torch
import torch.nn.functional as F
from hypothesis import given, settings
from hypothesis import strategies as st

from hbis_torch.errors import HbisInputError
from hbis_torch.reconstruct.learned.net import HbisSRNet, bilinear_kernel, count_parameters, depth_to_space, space_to_depth


@settings(max_examples=25, deadline=None)
@given(block=st.integers(1, 7), batch=st.integers(1, 2), channels=st.integers(1, 3),
       rows=st.integers(1, 5), cols=st.integers(1, 5))
def test_space_to_depth_matches_pixel_unshuffle_and_inverts(block, batch, channels, rows, cols):
    x = torch.randn(batch, channels, rows * block, cols * block)
    packed = space_to_depth(x, block)
    assert torch.equal(packed, F.pixel_unshuffle(x, block))
    assert torch.equal(depth_to_space(packed, block), x)
    assert torch.equal(depth_to_space(packed, block), F.pixel_shuffle(packed, block))


def test_space_to_depth_channel_layout():
    # Channel dy * b + dx holds the pixel at offset (dx, dy) inside each tile.
    x = torch.arange(36.0).reshape(1, 1, 6, 6)
    packed = space_to_depth(x, 3)
    assert packed[0, 1 * 3 + 2, 1, 0] == x[0, 0, 3 + 1, 0 + 2]


@pytest.mark.parametrize("h", [2, 3, 4, 7])
def test_output_is_h_times_larger(h):
    model = HbisSRNet(h, width=8, blocks=1)
    frames = torch.rand(2, h * h, 5, 7)
    offsets = torch.zeros(2, 2 * h * h, 5, 7)
    assert model(frames, offsets).shape == (2, 1, 5 * h, 7 * h)


def test_untrained_network_is_bilinear_upsampling_of_the_reference_frame():
    h = 4
    model = HbisSRNet(h)
    frames = torch.rand(1, h * h, 9, 11)
    out = model(frames, torch.randn(1, 2 * h * h, 9, 11))
    expected = F.interpolate(frames[:, :1], scale_factor=h, mode="bilinear", align_corners=False)
    torch.testing.assert_close(out, expected)


@pytest.mark.parametrize("h,skip", [(2, 3), (4, 7), (7, 5)])
def test_untrained_linear_base_is_bilinear_upsampling_edges_included(h, skip):
    model = HbisSRNet(h, width=8, blocks=1, skip=skip).eval()
    frames = torch.rand(2, h * h, 6, 9)
    out = model(frames, torch.randn(2, 2 * h * h, 6, 9))
    expected = F.interpolate(frames[:, :1], scale_factor=h, mode="bilinear", align_corners=False)
    torch.testing.assert_close(out, expected, atol=3e-6, rtol=0)
    # ... and only the reference frame (channel 0) enters it at first
    assert model.linear.weight[:, 1:].abs().max() == 0


def test_bilinear_kernel_reproduces_interpolate_on_an_impulse():
    h, size = 4, 5
    kernel = bilinear_kernel(h, size)  # (h^2, size, size)
    assert kernel.shape == (h * h, size, size)
    # every output pixel is a convex combination of LR pixels: each channel sums to one
    torch.testing.assert_close(kernel.sum(dim=(1, 2)), torch.ones(h * h))
    # bilinear upsampling by h reaches only the 3 x 3 neighbours
    assert kernel[:, 0].abs().max() == 0 and kernel[:, :, -1].abs().max() == 0


def test_linear_base_sees_every_frame_after_a_step():
    # the point of the linear base: gradient reaches the weights of all h^2 frames
    h = 3
    model = HbisSRNet(h, width=4, blocks=1, skip=3)
    frames = torch.rand(1, h * h, 8, 8)
    model(frames, torch.zeros(1, 2 * h * h, 8, 8)).square().mean().backward()
    assert (model.linear.weight.grad.abs().sum(dim=(0, 2, 3)) > 0).all()


def test_default_size_is_small_enough_for_two_cpu_cores():
    assert 150_000 < count_parameters(HbisSRNet(4)) < 300_000
    assert 150_000 < count_parameters(HbisSRNet(4, skip=7)) < 300_000
    assert count_parameters(HbisSRNet(7, blocks=4, skip=5)) < 320_000


@pytest.mark.parametrize("skip", [2, -1, 1.5])
def test_bad_skip_is_rejected(skip):
    with pytest.raises(HbisInputError, match="skip"):
        HbisSRNet(4, skip=skip)


@pytest.mark.parametrize("h", [1, 0, 2.5])
def test_bad_h_is_rejected(h):
    with pytest.raises(HbisInputError):
        HbisSRNet(h)
