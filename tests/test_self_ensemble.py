"""The learned method's geometric self-ensemble: the network averaged over the square's symmetries."""

import numpy as np
import pytest

from hbis_torch.cli import main
from hbis_torch.errors import HbisInputError
from hbis_torch.metrics import psnr
from hbis_torch.reconstruct.learned import (LearnedSR, default_ensemble, default_model_path, learned_sr,
                                           network_inputs, run_tiled, self_ensemble, tile_ensemble)
from hbis_torch.stack_io import read_stack
from hbis_torch.reconstruct.learned.inputs import (ENSEMBLE_ORDER, _transform_image, _transform_phases,
                                                   _untransform_image, check_ensemble, space_to_depth)
from test_learned_cli import simulated_stack_file


def depth_to_space(base, h):
    """(h^2, H, W) -> (hH, hW), the inverse of space_to_depth."""
    _, rows, cols = base.shape
    return base.reshape(h, h, rows, cols).transpose(2, 0, 3, 1).reshape(h * rows, h * cols)


@pytest.mark.parametrize("h", [2, 3, 4])
@pytest.mark.parametrize("k", range(8))
def test_each_symmetry_acts_on_the_phases_as_on_the_image(h, k):
    image = np.random.default_rng(k).random((h * 5, h * 7)).astype(np.float32)
    phases = space_to_depth(image, h).reshape(h, h, 5, 7)
    moved = np.ascontiguousarray(_transform_phases(phases, k))
    expected = space_to_depth(np.ascontiguousarray(_transform_image(image, k)), h)
    np.testing.assert_array_equal(moved.reshape(h * h, *moved.shape[2:]), expected)
    np.testing.assert_array_equal(_untransform_image(_transform_image(image, k), k), image)


def test_the_symmetries_are_the_eight_of_the_square():
    image = np.arange(12.0).reshape(3, 4)
    seen = {_transform_image(image, k).tobytes() + bytes(_transform_image(image, k).shape) for k in ENSEMBLE_ORDER}
    assert len(seen) == 8


@pytest.mark.parametrize("count", [1, 2, 4, 8])
def test_an_equivariant_network_is_unchanged(count):
    h = 4
    base = np.random.default_rng(0).random((h * h, 6, 9)).astype(np.float32)
    noise = np.random.default_rng(1).random((1, 6, 9)).astype(np.float32)

    def run(b, n):  # depth-to-space plus the noise map's value, pixel for pixel: equivariant
        return depth_to_space(b, h) + np.kron(n[0], np.ones((h, h), np.float32))

    np.testing.assert_allclose(self_ensemble(run, h, count)(base, noise), run(base, noise), atol=1e-6)


def test_a_network_that_sees_direction_is_averaged_over_the_symmetries():
    h = 2
    base = np.zeros((h * h, 4, 6), np.float32)
    noise = np.zeros((1, 4, 6), np.float32)

    def run(b, n):  # adds its column index: not equivariant
        image = depth_to_space(b, h)
        return image + np.arange(image.shape[1], dtype=np.float32)[None, :]

    rows, cols = np.mgrid[0:8, 0:12].astype(np.float32)
    # identity and transpose: the column index, and the row index seen through the transpose
    np.testing.assert_allclose(self_ensemble(run, h, 2)(base, noise), (cols + rows) / 2, atol=1e-6)
    # all eight: columns and rows, each counted forwards and backwards
    expected = (cols + (11 - cols) + rows + (7 - rows)) / 4
    np.testing.assert_allclose(self_ensemble(run, h, 8)(base, noise), expected, atol=1e-5)


@pytest.mark.parametrize("count", [2, 8])
def test_the_mean_a_tile_at_a_time_is_the_mean_of_the_tiled_network(count):
    # LearnedSR averages each tile over the symmetries (tile_ensemble); the halo spans the
    # receptive field, so that equals averaging the whole tiled image, bit for bit
    h = 3
    runner = LearnedSR(default_model_path(h), provider="cpu", tile=16)
    image = np.random.default_rng(count).random((h * 40, h * 53)).astype(np.float32)
    base, noise = network_inputs(image, h, (1e-4, 1e-6))
    whole = self_ensemble(lambda b, n: run_tiled(runner.infer, b, n, h, runner.tile, runner.halo), h, count)
    tiled = runner.run_network(base, noise, count)
    np.testing.assert_array_equal(tiled, whole(base, noise))
    assert np.abs(tiled - runner.run_network(base, noise)).max() > 1e-4  # and it is not one pass
    assert tile_ensemble(runner.infer, h, 1) == runner.infer  # one symmetry: the network itself


@pytest.mark.parametrize("bad", [0, 3, 16, True, 2.0, "8"])
def test_other_sizes_are_refused(bad):
    with pytest.raises(HbisInputError, match="ensemble must be one of 1, 2, 4, 8"):
        check_ensemble(bad)


def test_the_average_is_closer_to_the_truth(tmp_path):
    # a simulated stack the training never saw (the words scene at h = 4): on it each doubling
    # of the ensemble gains (29.31, 29.43, 29.47, 29.51 dB for 1, 2, 4, 8)
    stack_path, truth = simulated_stack_file(tmp_path, 4)
    stack = read_stack(stack_path)
    scores = [psnr(learned_sr(stack, ensemble=count), truth) for count in (1, 2, 8)]
    assert scores[0] + 0.05 < scores[1] < scores[2]


def test_the_default_is_two_at_h3_and_h7_and_one_elsewhere(tmp_path):
    assert [default_ensemble(h) for h in (2, 3, 4, 7)] == [1, 2, 1, 2]
    assert check_ensemble(None, 7) == 2 and check_ensemble(None, 4) == 1 and check_ensemble(None) == 1
    for h in (4, 7):
        stack = read_stack(simulated_stack_file(tmp_path, h, size=12)[0])
        chosen = learned_sr(stack, registration="optics")
        np.testing.assert_array_equal(chosen, learned_sr(stack, registration="optics", ensemble=default_ensemble(h)))
        if h == 7:  # and it is not the single pass
            assert np.abs(chosen - learned_sr(stack, registration="optics", ensemble=1)).max() > 1e-4


def test_the_best_tier_defaults_to_more_symmetries(tmp_path):
    # the best models are for users who chose time for quality: 2 symmetries at h = 2 and 4, all 8 at h = 7
    assert [default_ensemble(h, "best") for h in (2, 4, 7)] == [2, 2, 8]
    assert default_ensemble(4, None) == default_ensemble(4, "fast") == 1  # a file of no tier: as fast
    assert check_ensemble(None, 4, "best") == 2 and check_ensemble(8, 4, "best") == 8
    stack = read_stack(simulated_stack_file(tmp_path, 4, size=12)[0])
    chosen = learned_sr(stack, registration="optics", model="best")
    np.testing.assert_array_equal(chosen, learned_sr(stack, registration="optics", model="best", ensemble=2))
    assert np.abs(chosen - learned_sr(stack, registration="optics", model="best", ensemble=1)).max() > 1e-4


def test_cli_ensemble_is_learned_only_and_checked_first(tmp_path, capsys):
    stack_path, truth = simulated_stack_file(tmp_path, 4)
    out = tmp_path / "sr.tif"
    code = main(["reconstruct", str(stack_path), "--ensemble", "4", "--out", str(out)])
    assert code == 2 and "--ensemble is only for --method learned" in capsys.readouterr().err
    assert not out.exists()
    with pytest.raises(SystemExit) as exit_:
        main(["reconstruct", str(stack_path), "--method", "learned", "--ensemble", "3", "--out", str(out)])
    assert exit_.value.code == 2 and not out.exists()
    code = main(["reconstruct", str(stack_path), "--method", "learned", "--registration", "optics",
                 "--ensemble", "2", "--out", str(out)])
    assert code == 0, capsys.readouterr().err
    assert out.exists()
