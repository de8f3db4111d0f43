"""Reconstruction of simulated stacks: the ROI's geometry, registration on top of the optics,
frames out of order, the one sample-position policy, the method registry, and the
``hbis reconstruct`` command."""

import copy
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import tifffile
import torch
from skimage.metrics import peak_signal_noise_ratio as psnr

from hbis_torch.cli import main
from hbis_torch.config import FoveaSystem
from hbis_torch.errors import HbisInputError
from hbis_torch.optics import landing_map, sensor_position
from hbis_torch.reconstruct import (
    classical_sr,
    optical_sample_positions,
    reconstruct,
    registry,
)
from hbis_torch.reconstruct import positions as position_policy
from hbis_torch.reconstruct.classical import (
    optics_cutoff,
    stack_fill_factor,
)
from hbis_torch.reconstruct.positions import stack_sample_positions
from hbis_torch.registration import (
    apply_homography,
    homographies_from_positions,
    register_stack,
)
from hbis_torch.scan import plan_scan
from hbis_torch.simulate import (
    SceneSpec,
    SensorModel,
    load_scene,
    sample_positions,
    simulate_stack,
)
from hbis_torch.stack_io import write_stack

SYSTEM = FoveaSystem()
H = 3
SENSOR_40DB = SensorModel(full_well_e=20000.0, read_noise_e=2.0)  # shot noise: SNR ~ 40 dB at mid grey
CENTRE = (608, 448, 64, 64)
CORNER = (0, 0, 64, 64)

pytestmark = pytest.mark.usefixtures("one_thread")


def _scene(width_px: int, seed: int = 2):
    px = SYSTEM.object_pixel_mm
    spec = SceneSpec(size_mm=(1.3 * width_px * px,) * 2, pixel_mm=px, detail_mm=px / (2 * H))
    return load_scene("camera", spec, seed=seed)


def _simulate(roi, **kw):
    return simulate_stack(_scene(roi[2]), SYSTEM, plan_scan(SYSTEM, H), roi=roi, seed=1,
                          sensor=kw.pop("sensor", SENSOR_40DB), **kw)


@pytest.fixture(scope="module")
def centre():
    return _simulate(CENTRE)


@pytest.fixture(scope="module")
def corner():
    return _simulate(CORNER)


def _score(truth, image):
    c = slice(2 * H, -2 * H)
    return psnr(truth[c, c], image[c, c], data_range=1.0)


def _bicubic(stack):
    ref = stack.to_float()[stack.reference_index]
    up = torch.nn.functional.interpolate(ref[None, None], scale_factor=stack.h, mode="bicubic", align_corners=False)
    return up[0, 0].clamp(0, 1).numpy()


def test_optical_positions_follow_the_contract_for_a_corner_roi():
    roi = (0, 0, 40, 24)  # not square, at the sensor's corner
    stack, _ = _simulate(roi)
    pos = optical_sample_positions(stack)
    assert pos.shape == (H * H, 24, 40, 2) and pos.dtype == torch.float64
    # The contract's formula, for one pixel of one frame.
    phases = stack.phases_deg
    k, ref, (v, u) = 2, stack.reference_index, (17, 31)
    point = landing_map(SYSTEM, phases[k, 0], phases[k, 1], roi)[v, u]
    expected = sensor_position(SYSTEM, point, phases[ref, 0], phases[ref, 1]) - torch.tensor([0.0, 0.0])
    assert torch.allclose(pos[k, v, u], expected, atol=1e-12)
    # The simulator's own implementation agrees everywhere; the reference frame is the grid.
    theirs = sample_positions(SYSTEM, phases, ref, roi, exact=True)
    assert (pos - theirs).abs().max() < 1e-9
    vv, uu = torch.meshgrid(torch.arange(24.0), torch.arange(40.0), indexing="ij")
    assert (pos[ref] - torch.stack((uu, vv), -1)).abs().max() < 1e-9
    # The same frames described as a centre ROI would be placed differently.
    moved = copy.deepcopy(stack)
    moved.meta["roi"] = [620, 460, 40, 24]
    assert (optical_sample_positions(moved) - pos).abs().max() > 0.03


def test_registration_confirms_the_corner_roi_geometry(corner):
    """The frames' measured motion matches the corner ROI's optics, not the centre's."""
    stack, _ = corner
    frames, ref = stack.to_float(), stack.reference_index
    own = homographies_from_positions(optical_sample_positions(stack))
    centred = copy.deepcopy(stack)
    centred.meta["roi"] = list(CENTRE)
    other = homographies_from_positions(optical_sample_positions(centred))
    measured = register_stack(frames, ref, prediction=own).homographies
    grid = torch.tensor([[0.0, 0.0], [63.0, 0.0], [0.0, 63.0], [63.0, 63.0]], dtype=torch.float64)
    off_own = (apply_homography(measured, grid) - apply_homography(own, grid)).norm(dim=-1).max()
    off_other = (apply_homography(measured, grid) - apply_homography(other, grid)).norm(dim=-1).max()
    assert off_own < 0.01 < 0.03 < off_other


def test_reconstruction_has_the_contract_shape_and_beats_single_frame_upsampling(centre, corner):
    for stack, truth in (centre, corner):
        image = reconstruct(stack)
        assert image.shape == (H * 64, H * 64) == truth.shape and image.dtype == np.float32
        assert 0.0 <= image.min() and image.max() <= 1.0
        plain = classical_sr(stack.to_float(), optical_sample_positions(stack), H, deblur=False).numpy()
        assert _score(truth, image) > _score(truth, plain) + 1.0
        assert _score(truth, image) > _score(truth, _bicubic(stack)) + 3.0


def test_registration_corrects_motor_errors_to_the_goal():
    """Motors off by 0.02 deg (about a tenth of the step): the data puts every sample back
    within 0.02 px RMS (issue goal, 40 dB), and the reconstruction gains from it."""
    stack, truth = _simulate(CENTRE, phase_error_deg=0.02)
    actual = copy.deepcopy(stack)
    actual.meta["phases_deg"] = stack.meta["simulation"]["true_phases_deg"]
    true_pos = optical_sample_positions(actual)
    planned_pos = optical_sample_positions(stack)
    reg = register_stack(stack.to_float(), stack.reference_index, prediction=homographies_from_positions(planned_pos))
    vv, uu = torch.meshgrid(torch.arange(64.0), torch.arange(64.0), indexing="ij")
    grid = torch.stack((uu, vv), -1).reshape(-1, 2).double()
    got = apply_homography(reg.homographies, grid).reshape(true_pos.shape)
    rms = float(((got - true_pos) ** 2).sum(-1).mean().sqrt())
    planned_rms = float(((planned_pos - true_pos) ** 2).sum(-1).mean().sqrt())
    assert rms < 0.02 < planned_rms
    assert _score(truth, reconstruct(stack, registration="auto")) > _score(truth, reconstruct(stack, registration="optics")) + 0.2


def test_frames_out_of_order_are_detected_and_survived(centre):
    stack, truth = centre
    swapped = copy.deepcopy(stack)
    swapped.frames = stack.frames.copy()
    swapped.frames[[1, 5]] = stack.frames[[5, 1]]
    messages = []
    auto = reconstruct(swapped, registration="auto", messages=messages)
    assert any("frame 1 sits where frame 5 was planned" in m for m in messages)
    assert _score(truth, auto) > _score(truth, reconstruct(stack)) - 0.3  # the data knows better
    assert _score(truth, reconstruct(swapped, registration="optics")) < _score(truth, auto) - 1.0


def test_reconstruct_rejects_bad_arguments(centre):
    stack, _ = centre
    with pytest.raises(HbisInputError, match="unknown reconstruction method 'magic'"):
        reconstruct(stack, method="magic")
    with pytest.raises(HbisInputError, match="registration must be one of"):
        reconstruct(stack, registration="magic")


def test_cli_reconstruct_writes_the_image(centre, tmp_path, capsys):
    stack, truth = centre
    path, out = tmp_path / "stack.tif", tmp_path / "sr.tif"
    write_stack(path, stack)
    assert main(["reconstruct", str(path), "--method", "classical", "--out", str(out)]) == 0
    image = tifffile.imread(out)
    assert image.shape == truth.shape and image.dtype == np.float32
    assert np.allclose(image, reconstruct(stack), atol=1e-6)


@pytest.mark.parametrize(
    "extra, message",
    [
        (["--method", "magic"], "invalid choice"),
        (["--model", "m.onnx"], "--model is only for --method learned"),
        (["--provider", "cpu"], "--provider is only for --method learned"),
        (["--method", "learned", "--provider", "gpu"], "invalid choice"),
        (["--registration", "magic"], "invalid choice"),
        # Options belong to their method and stack: none is accepted and then ignored.
        (["--method", "learned", "--no-deblur"], "--no-deblur is only for --method classical"),
        (["--colour", "luma"], "applies to colour stacks"),
        (["--method", "learned", "--colour", "channels"], "applies to colour stacks"),
    ],
)
def test_cli_reconstruct_bad_arguments_exit_2(centre, tmp_path, capsys, extra, message):
    path = tmp_path / "stack.tif"
    write_stack(path, centre[0])
    try:
        rc = main(["reconstruct", str(path), "--out", str(tmp_path / "o.tif"), *extra])
    except SystemExit as exc:  # argparse's own errors
        rc = exc.code
    assert rc == 2
    err = capsys.readouterr().err
    assert message in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "o.tif").exists()


def test_cli_reconstruct_corrupt_file_exit_2(tmp_path, capsys):
    bad = tmp_path / "bad.tif"
    bad.write_bytes(b"not a tiff")
    assert main(["reconstruct", str(bad), "--out", str(tmp_path / "o.tif")]) == 2
    err = capsys.readouterr().err
    assert "bad.tif" in err and len(err.strip().splitlines()) == 1


def test_cli_reconstruct_refuses_to_overwrite_its_input_and_a_black_reference(centre, tmp_path, capsys):
    stack, _ = centre
    path = tmp_path / "stack.tif"
    write_stack(path, stack)
    before = path.read_bytes()
    assert main(["reconstruct", str(path), "--out", str(path)]) == 2
    assert "is the input" in capsys.readouterr().err and path.read_bytes() == before
    black = copy.deepcopy(stack)
    black.frames[black.reference_index] = 0
    write_stack(path, black)
    assert main(["reconstruct", str(path), "--registration", "data", "--out", str(tmp_path / "o.tif")]) == 2
    err = capsys.readouterr().err
    assert "is uniform" in err and len(err.strip().splitlines()) == 1 and not (tmp_path / "o.tif").exists()


def test_the_registry_names_every_method_and_imports_no_onnx():
    import hbis_torch.reconstruct as layer

    assert layer.METHODS is registry.METHODS and sorted(registry.METHODS) == ["classical", "learned"]
    code = ("import sys; from hbis_torch.reconstruct.registry import METHODS; "
            "print(sorted(METHODS), 'onnxruntime' in sys.modules, 'onnx' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "['classical', 'learned'] False False"


def test_exact_positions_are_the_per_frame_trace_bit_for_bit_in_any_chunks(corner, monkeypatch):
    """The optics part of the policy: one call, or a few frames per call (large stacks), gives
    the same bits as tracing one frame at a time (the classical method's former tracer)."""
    stack, _ = corner
    phases, ref = stack.phases_deg, stack.reference_index
    origin = torch.tensor(CORNER[:2], dtype=torch.float64)
    per_frame = torch.stack([sensor_position(SYSTEM, landing_map(SYSTEM, p1, p2, CORNER), phases[ref, 0],
                                             phases[ref, 1]) - origin for p1, p2 in phases])
    whole = optical_sample_positions(stack)
    monkeypatch.setattr(position_policy, "EXACT_SAMPLES_PER_CALL", 2 * 64 * 64)  # two frames per call
    assert torch.equal(whole, per_frame) and torch.equal(optical_sample_positions(stack), whole)
    optics, trusted = stack_sample_positions(stack, "optics", exact=True)
    assert torch.equal(optics, whole) and bool(trusted.all())


def test_untrusted_frames_keep_the_optics_and_classical_data_mode_leaves_them_out(centre, distrust_frame):
    stack, _ = centre
    distrust_frame(2)
    optical = position_policy.optical_positions(stack)  # the methods' positions: node splines
    corrected, trusted = stack_sample_positions(stack, "data")
    assert trusted.tolist() == [k != 2 for k in range(H * H)]
    assert torch.equal(corrected[2], optical[2]) and not torch.equal(corrected[4], optical[4])
    frames, kw = stack.to_float(), {"cutoff": optics_cutoff(SYSTEM), "fill_factor": stack_fill_factor(stack)}
    messages = []
    data = reconstruct(stack, registration="data", messages=messages)
    assert messages[-1] == "left out 1 frame(s) the registration could not trust"
    # the positions from the nodes (the methods') and every pixel's (float64) agree to float32
    # rounding, some 1e-6 HR px: the images to 1e-6, far below what one frame changes
    assert np.abs(data - classical_sr(frames, corrected, H, weights=trusted.double(), **kw).numpy()).max() < 1e-5
    messages = []
    auto = reconstruct(stack, registration="auto", messages=messages)
    assert not any("frame(s)" in m for m in messages)
    assert np.abs(auto - classical_sr(frames, corrected, H, **kw).numpy()).max() < 1e-5
    assert np.abs(auto - data).max() > 1e-3


