"""grid_sample_threaded: grid_sample's values to the bit, the points split over threads."""

import pytest
import torch

from hbis_torch.registration.threaded_sample import MIN_POINTS, grid_sample_threaded


@pytest.fixture
def two_threads():
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    yield
    torch.set_num_threads(before)


@pytest.mark.parametrize("channels", [1, 3])
@pytest.mark.parametrize("shape", [(512, 640), (1, 4 * MIN_POINTS), (257, 511)])
@pytest.mark.parametrize("mode", ["bilinear", "bicubic"])
def test_same_bits_as_grid_sample(two_threads, channels, shape, mode):
    generator = torch.Generator().manual_seed(0)
    image = torch.rand((1, channels, 300, 400), generator=generator)
    grid = torch.rand((1, *shape, 2), generator=generator) * 2.2 - 1.1  # some points beyond the edge
    options = dict(mode=mode, padding_mode="border", align_corners=True)
    expected = torch.nn.functional.grid_sample(image, grid, **options)
    got = grid_sample_threaded(image, grid, **options)
    assert got.shape == expected.shape
    assert torch.equal(got, expected)


def test_a_batch_of_several_and_few_points_go_straight_through(two_threads):
    image = torch.rand((2, 1, 30, 40))
    grid = torch.rand((2, 300, 400, 2)) * 2 - 1
    assert torch.equal(grid_sample_threaded(image, grid, align_corners=True),
                       torch.nn.functional.grid_sample(image, grid, align_corners=True))
    small = torch.rand((1, 10, 10, 2)) * 2 - 1
    assert torch.equal(grid_sample_threaded(image[:1], small, align_corners=True),
                       torch.nn.functional.grid_sample(image[:1], small, align_corners=True))


@pytest.mark.parametrize("shape", [(512, 640), (1, 4 * MIN_POINTS), (257, 511)])
def test_written_into_a_slice_of_the_callers_memory(two_threads, shape):
    generator = torch.Generator().manual_seed(1)
    image = torch.rand((1, 3, 60, 80), generator=generator)
    grid = torch.rand((1, *shape, 2), generator=generator) * 2 - 1
    memory = torch.full((1, 3, shape[0] + 6, shape[1]), -1.0)
    got = grid_sample_threaded(image, grid, out=memory[:, :, 2:2 + shape[0]], align_corners=True)
    expected = torch.nn.functional.grid_sample(image, grid, align_corners=True)
    assert torch.equal(got, expected) and torch.equal(memory[:, :, 2:2 + shape[0]], expected)
    assert bool((memory[:, :, :2] == -1).all()) and bool((memory[:, :, 2 + shape[0]:] == -1).all())
