"""The SR network: space-to-depth written as reshape/permute, shapes, its starting point, and its
architecture record (what builds it, what sizes the tiles' halo)."""

import pytest
import torch
import torch.nn.functional as F
from hypothesis import given, settings
from hypothesis import strategies as st

from hbis_torch.errors import HbisInputError
from hbis_torch.reconstruct.learned.architecture import Architecture
from hbis_torch.training.net import HbisSRNet, build_net, count_parameters, depth_to_space, space_to_depth


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
    base = torch.rand(2, h * h, 5, 7)
    noise = torch.zeros(2, 1, 5, 7)
    assert model(base, noise).shape == (2, 1, 5 * h, 7 * h)


def test_untrained_network_returns_its_classical_input():
    h = 4
    model = HbisSRNet(h)
    base = torch.rand(1, h * h, 9, 11)
    torch.testing.assert_close(model(base, torch.rand(1, 1, 9, 11)), depth_to_space(base, h))


def test_every_layer_learns_from_the_first_step():
    # the zero tail gets a gradient at once, and the head and body right after it moves
    h = 3
    model = HbisSRNet(h, width=4, blocks=1)
    optimizer = torch.optim.SGD(model.parameters(), lr=0.1)
    base, noise = torch.rand(1, h * h, 8, 8), torch.rand(1, 1, 8, 8)
    for _ in range(2):
        optimizer.zero_grad()
        (model(base, noise) - 0.3).square().mean().backward()
        optimizer.step()
    assert model.tail.weight.grad.abs().sum() > 0 and model.head.weight.grad.abs().sum() > 0


def test_the_noise_map_changes_the_output_once_trained():
    h = 2
    torch.manual_seed(0)
    model = HbisSRNet(h, width=8, blocks=1)
    torch.nn.init.normal_(model.tail.weight, std=0.1)
    base = torch.rand(1, h * h, 6, 6)
    assert not torch.allclose(model(base, torch.zeros(1, 1, 6, 6)), model(base, torch.ones(1, 1, 6, 6)))


def test_default_size_is_small_enough_for_two_cpu_cores():
    assert 50_000 < count_parameters(HbisSRNet(4)) < 150_000
    assert count_parameters(HbisSRNet(7)) < 150_000


@pytest.mark.parametrize("h", [1, 0, 2.5])
def test_bad_h_is_rejected(h):
    with pytest.raises(HbisInputError):
        HbisSRNet(h)


@pytest.mark.parametrize("kind, blocks", [("plain", 1), ("plain", 3), ("ir", 2)])
def test_the_halo_covers_the_receptive_field_exactly_plus_one(kind, blocks):
    """One LR pixel changed moves outputs up to halo - 1 LR pixels away, and no further."""
    arch = Architecture(2, width=4, blocks=blocks, kind=kind)
    torch.manual_seed(0)
    model = build_net(arch).eval()
    for p in model.parameters():  # the tail starts at zero: give every layer something to pass on
        torch.nn.init.normal_(p, std=0.3)
    base, noise = torch.rand(1, 4, 31, 31), torch.rand(1, 1, 31, 31)
    moved = base.clone()
    moved[0, :, 15, 15] += 0.5
    with torch.no_grad():
        change = (model(moved, noise) - model(base, noise)).abs()[0, 0] > 0
    rows, cols = torch.nonzero(change, as_tuple=True)
    reach = int(max((rows // 2 - 15).abs().max(), (cols // 2 - 15).abs().max()))
    assert reach == arch.halo - 1


def test_the_architecture_travels_in_metadata_and_defaults_to_the_shipped_design():
    ir = Architecture(4, width=16, blocks=6, kind="ir")
    assert Architecture.from_metadata({"h": "4", **ir.to_metadata()}) == ir
    assert Architecture.from_dict(ir.as_dict()) == ir
    # the shipped models' model_config has no kind: the plain design, halo 2 * blocks + 3
    shipped = Architecture.from_metadata({"h": "4", "model_config": '{"h": 4, "width": 32, "blocks": 4}'})
    assert shipped == Architecture(4) and shipped.kind == "plain" and shipped.halo == 11
    assert build_net(shipped.as_dict()).config() == shipped.as_dict()
    with pytest.raises(ValueError, match="kind"):
        Architecture(4, kind="dense")

