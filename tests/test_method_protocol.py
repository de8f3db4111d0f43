"""The method protocol: a method is one module plus one registry entry.

The toy method below (the nearest sample, with one option) is defined in this test module and
registered; nothing else in the project is edited for it, and it runs through the Python API,
``hbis reconstruct`` (with its option, built from the entry) and an RGB stack.
"""

from __future__ import annotations

import numpy as np
import pytest
import skimage.data
import tifffile
from scipy.spatial import cKDTree

from hbis_torch.cli import main
from hbis_torch.config import FoveaSystem
from hbis_torch.metrics import psnr
from hbis_torch.reconstruct import Method, Option, reconstruct, register
from hbis_torch.reconstruct.positions import check_registration, stack_sample_positions
from hbis_torch.reconstruct.registry import METHODS
from hbis_torch.simulate import SensorModel, simulate_stack
from hbis_torch.simulate.stacks import scene_for_roi
from hbis_torch.simulate.colour import simulate_colour_stack
from hbis_torch.stack_io import write_stack

ROI = (608, 456, 24, 24)


def nearest_sample(stack, registration: str = "auto", *, messages=None, reference_only: bool = False) -> np.ndarray:
    """Each output pixel takes the value of the nearest sample (of the reference frame alone with
    ``reference_only``): (h H, h W) float32."""
    check_registration(registration)
    positions, _ = stack_sample_positions(stack, registration, messages=messages)
    frames = stack.to_float().numpy()
    positions = positions.numpy()
    if reference_only:
        frames = frames[stack.reference_index:stack.reference_index + 1]
        positions = positions[stack.reference_index:stack.reference_index + 1]
    h, (rows, cols) = stack.h, frames.shape[1:]
    centres = (np.arange(h * max(rows, cols)) + 0.5) / h - 0.5
    grid = np.stack(np.meshgrid(centres[:h * cols], centres[:h * rows]), axis=-1)
    _, nearest = cKDTree(positions.reshape(-1, 2)).query(grid.reshape(-1, 2))
    return frames.reshape(-1)[nearest].reshape(h * rows, h * cols).astype(np.float32)


TOY = Method(
    name="nearest",
    run=nearest_sample,
    summary="the nearest sample (a test's toy)",
    options=(Option("--reference-only", "reference_only", "use the reference frame's samples alone",
                    {"action": "store_true"}),),
)


@pytest.fixture
def toy():
    register(TOY)
    yield TOY
    METHODS.pop(TOY.name)


@pytest.fixture(scope="module")
def grey_case():
    system = FoveaSystem()
    scene = scene_for_roi("camera", system, ROI, 2)
    return simulate_stack(scene, system, 2, ROI, SensorModel(), seed=1)


def test_a_registered_method_runs_through_the_python_api(toy, grey_case):
    stack, truth = grey_case
    every = reconstruct(stack, "nearest", registration="optics")
    alone = reconstruct(stack, "nearest", registration="optics", reference_only=True)
    reference = stack.to_float().numpy()[stack.reference_index]
    assert every.shape == alone.shape == truth.shape and every.dtype == np.float32
    # The reference frame alone: every output pixel lies in the LR pixel it came from.
    np.testing.assert_array_equal(alone, np.repeat(np.repeat(reference, 2, axis=0), 2, axis=1))
    # With every frame, each of the four frames is the nearest sample for a quarter of the output.
    frames = stack.to_float().numpy()
    source = [np.isin(every, frames[k]) for k in range(len(frames))]
    assert np.logical_or.reduce(source).all()
    assert all(0.15 < s.mean() for s in source)
    assert psnr(every, truth) > 20 and not np.array_equal(every, alone)


def test_a_registered_method_runs_through_the_cli_with_its_option(toy, grey_case, tmp_path, capsys):
    stack, _ = grey_case
    path = tmp_path / "stack.tif"
    write_stack(path, stack)
    with pytest.raises(SystemExit):
        main(["reconstruct", "--help"])
    help_text = capsys.readouterr().out
    assert "nearest" in help_text and "--reference-only" in help_text
    out = tmp_path / "sr.tif"
    assert main(["reconstruct", str(path), "--method", "nearest", "--reference-only",
                 "--registration", "optics", "--out", str(out)]) == 0
    expected = reconstruct(stack, "nearest", registration="optics", reference_only=True)
    np.testing.assert_array_equal(tifffile.imread(out), expected)
    # The option belongs to its method: the classical method refuses it, in one line, writing nothing.
    refused = tmp_path / "refused.tif"
    assert main(["reconstruct", str(path), "--reference-only", "--out", str(refused)]) == 2
    err = capsys.readouterr().err.strip()
    assert "--reference-only is only for --method nearest" in err and len(err.splitlines()) == 1
    assert not refused.exists()


def test_a_registered_method_runs_on_an_rgb_stack(toy):
    rgb = skimage.data.astronaut()[40:240, 140:340]
    stack, truth = simulate_colour_stack(rgb, FoveaSystem(), 2, ROI, SensorModel(), seed=3)
    image = reconstruct(stack, "nearest", registration="optics", colour="channels")
    assert image.shape == truth.shape == (48, 48, 3) and image.dtype == np.float32
    for c in range(3):  # each channel as the method gives it on that channel's grey stack
        channel = stack.to_float().numpy()[..., c]
        assert np.corrcoef(image[..., c].ravel(), truth[..., c].ravel())[0, 1] > 0.9
        assert image[..., c].min() >= channel.min() and image[..., c].max() <= channel.max()


def test_a_name_is_registered_once_and_a_shared_flag_means_one_thing(toy):
    from hbis_torch.errors import HbisInputError

    with pytest.raises(HbisInputError, match="registered already"):
        register(TOY)
    clash = Method(name="other", run=nearest_sample, summary="x",
                   options=(Option("--reference-only", "reference_only", "x", {"action": "store_false"}),))
    with pytest.raises(HbisInputError, match="differs"):
        register(clash)
    assert "other" not in METHODS
