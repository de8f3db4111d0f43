"""The SR network: space-to-depth written as reshape/permute, shapes, and its starting point."""

import pytest
import torch
import torch.nn.functional as F
from hypothesis import given, settings
from hypothesis import strategies as st

from hbis_torch.errors import HbisInputError
from hbis_torch.sr.net import HbisSRNet, count_parameters, depth_to_space, space_to_depth


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


def test_default_size_is_small_enough_for_two_cpu_cores():
    n = count_parameters(HbisSRNet(4))
    assert 150_000 < n < 400_000


@pytest.mark.parametrize("h", [1, 0, 2.5])
def test_bad_h_is_rejected(h):
    with pytest.raises(HbisInputError):
        HbisSRNet(h)
