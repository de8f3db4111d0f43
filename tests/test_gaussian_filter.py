"""scipy.ndimage.gaussian_filter's sums without its import (hbis_torch/gaussian_filter.py)."""

import numpy as np
import pytest

from hbis_torch.gaussian_filter import MODES, gaussian_filter


@pytest.mark.parametrize("mode", sorted(MODES))
@pytest.mark.parametrize("shape, sigma", [((48, 64), 0.7), ((48, 64), 2.0), ((5, 13, 13), (0, 1.5, 1.5)),
                                          ((3, 4), 2.0), ((1, 7), (0.0, 3.0)), ((2,), 1.5)])
def test_the_same_bits_as_scipys(mode, shape, sigma):
    """Every mode, sigmas per axis and none along one, lines shorter than the kernel's reach."""
    from scipy.ndimage import gaussian_filter as scipys

    image = np.random.default_rng(0).random(shape) * 3 - 1
    expected = scipys(image, sigma, mode=mode)
    assert gaussian_filter(image, sigma, mode=mode).tobytes() == expected.tobytes()
    output = np.full(shape, np.nan)
    assert gaussian_filter(image, sigma, mode=mode, output=output) is output
    assert output.tobytes() == expected.tobytes()


def test_the_image_is_left_as_it_was():
    image = np.random.default_rng(1).random((9, 11))
    before = image.copy()
    smooth = gaussian_filter(image, 1.0)
    assert np.array_equal(image, before)
    assert not np.shares_memory(gaussian_filter(image, 0.0), image)
    assert smooth.std() < image.std()


def test_other_types_and_modes_are_refused():
    with pytest.raises(ValueError, match="float64"):
        gaussian_filter(np.zeros((4, 4), dtype=np.float32), 1.0)
    with pytest.raises(ValueError, match="mode"):
        gaussian_filter(np.zeros((4, 4)), 1.0, mode="constant")
