"""The digital twin: ``hbis motors scan --camera sim:SCENE --stack`` against the GRBL simulator
captures, assembles and reconstructs a stack on one machine; its reconstruction comes within
0.3 dB PSNR of the same stack made directly by ``hbis simulate``. And the OpenCV camera backend,
fed from a video file."""

import json

import numpy as np
import pytest

from hbis_torch.capture.cameras import OpenCVCamera, SimulatedCamera, camera_from_spec
from hbis_torch.cli import main
from hbis_torch.config import FoveaSystem
from hbis_torch.errors import HbisInputError
from hbis_torch.hardware import GrblSimulator
from hbis_torch.metrics import psnr
from hbis_torch.stack_io import read_image, read_stack

FAST = ["--timeout-s", "0.5", "--welcome-timeout-s", "1"]
ROI = "608,456,32,32"


def test_twin_scan_capture_assemble_reconstruct_matches_hbis_simulate(tmp_path, capsys):
    # 10000 steps/deg: the initial phases 5, 70 lie on the motor grid (the twin's reference frame is
    # the direct simulation's, one ground truth for both) and the motors stop within 5e-5 deg of
    # the plan, so the twin records the scan 'hbis simulate' renders (with its own noise)
    with GrblSimulator({100: 10000.0, 101: 10000.0}, speedup=50, max_lifetime_s=120) as sim:
        code = main(["motors", "--port", sim.port, *FAST, "scan", "--h", "2", "--phases-deg", "5,70",
                     "--settle-s", "0", "--journal", str(tmp_path / "journal.json"),
                     "--camera", "sim:siemens-star", "--roi", ROI,
                     "--frames", str(tmp_path / "frames" / "f{index:02d}.tif"),
                     "--out", str(tmp_path / "phases.json"), "--stack", str(tmp_path / "twin.tif")])
    out = capsys.readouterr()
    assert code == 0, out.err
    twin = read_stack(tmp_path / "twin.tif")
    phases = json.loads((tmp_path / "phases.json").read_text())
    np.testing.assert_allclose(twin.phases_deg, phases["phases_deg"])
    assert twin.reference_index == phases["reference_index"] and twin.bit_depth == 12
    assert len(list((tmp_path / "frames").glob("f*.tif"))) == 4

    assert main(["simulate", "--scene", "siemens-star", "--h", "2", "--roi", ROI, "--phases-deg", "5,70",
                 "--out", str(tmp_path / "direct.tif"), "--truth", str(tmp_path / "truth.tif")]) == 0
    truth, _ = read_image(tmp_path / "truth.tif")
    scores = {}
    for name in ("twin", "direct"):
        assert main(["reconstruct", str(tmp_path / f"{name}.tif"), "--registration", "optics",
                     "--out", str(tmp_path / f"{name}_sr.tif")]) == 0
        scores[name] = psnr(read_image(tmp_path / f"{name}_sr.tif")[0], truth)
    assert abs(scores["twin"] - scores["direct"]) < 0.3, scores
    assert scores["twin"] > 20


def test_simulated_camera_renders_at_the_phases_it_is_given():
    system = FoveaSystem()
    cam = SimulatedCamera("siemens-star", system, (608, 456, 16, 16), 2, (5.0, 70.0))
    a, b = cam.grab(0, (5.0, 70.0)), cam.grab(0, (5.0, 70.0))
    np.testing.assert_array_equal(a, b)  # frame k's noise depends on k alone
    moved = cam.grab(1, (5.3, 70.4))
    assert a.shape == (16, 16) and a.dtype == np.uint16 and np.abs(moved.astype(float) - a).mean() > 20


def test_a_video_file_camera_reads_with_pyav(tmp_path):
    import av

    frames = np.random.default_rng(1).integers(0, 256, (3, 16, 20, 3)).astype(np.uint8)
    with av.open(str(tmp_path / "v.mkv"), "w") as out:
        stream = out.add_stream("ffv1", rate=5)
        stream.width, stream.height, stream.pix_fmt = 20, 16, "bgr0"
        for f in frames:
            out.mux(stream.encode(av.VideoFrame.from_ndarray(f, format="rgb24")))
        out.mux(stream.encode())
    for spec in (f"video:{tmp_path / 'v.mkv'}", f"opencv:{tmp_path / 'v.mkv'}"):  # a file never goes to OpenCV
        with camera_from_spec(spec) as cam:
            got = [cam.grab(k, (0.0, 0.0)) for k in range(3)]
            with pytest.raises(RuntimeError, match="no frame"):
                cam.grab(3, (0.0, 0.0))
        np.testing.assert_array_equal(np.stack(got), frames)


def test_camera_spec_and_missing_source_are_input_errors(tmp_path):
    with pytest.raises(HbisInputError, match="opencv:SOURCE"):
        camera_from_spec("webcam")
    pytest.importorskip("cv2")
    with pytest.raises(HbisInputError, match="cannot open"), OpenCVCamera(str(tmp_path / "none.avi")):
        pass


def test_capture_cmd_writing_a_pattern_ends_in_a_stack(tmp_path, capsys):
    """--capture-cmd writes each frame by pattern; --stack assembles them when the scan is done."""
    import sys

    grab = (f"{sys.executable} -c \"import sys, numpy, tifffile; "
            "tifffile.imwrite(sys.argv[1], numpy.full((12, 16), int(sys.argv[2]), numpy.uint8))\" "
            f"{tmp_path}/cap_{{index}}.tif {{index}}")
    with GrblSimulator(speedup=50, max_lifetime_s=60) as sim:
        code = main(["motors", "--port", sim.port, *FAST, "scan", "--h", "2", "--settle-s", "0",
                     "--journal", str(tmp_path / "j.json"), "--capture-cmd", grab,
                     "--frames", str(tmp_path / "cap_{index}.tif"), "--roi", "600,450,16,12",
                     "--stack", str(tmp_path / "stack.tif")])
    out = capsys.readouterr()
    assert code == 0, out.err
    stack = read_stack(tmp_path / "stack.tif")
    assert stack.frames.shape == (4, 12, 16) and [int(f[0, 0]) for f in stack.frames] == [0, 1, 2, 3]
    assert stack.reference_index == 3 and stack.bit_depth == 8


@pytest.mark.parametrize("args, fragment", [
    (["--stack", "s.tif"], "need --frames"),
    (["--camera", "sim:flat", "--capture-cmd", "true", "--frames", "f{index}.tif"], "not both"),
    (["--frames", "f.tif", "--stack", "s.tif", "--capture-cmd", "true"], "must hold {index}"),
    (["--camera", "webcam", "--frames", "f{index}.tif"], "opencv:SOURCE"),
])
def test_capture_options_are_checked_before_anything_moves(tmp_path, capsys, args, fragment, monkeypatch):
    monkeypatch.chdir(tmp_path)
    with GrblSimulator(speedup=50, max_lifetime_s=30) as sim:
        assert main(["motors", "--port", sim.port, *FAST, "scan", "--h", "2", *args]) == 2
        assert sim.machine.position_deg()[:2] == (0.0, 0.0)
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and fragment in err, err
    assert not (tmp_path / "s.tif").exists()
