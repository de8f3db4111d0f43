"""``hbis assemble`` and hbis_torch.capture: frames from files, patterns, multi-page TIFFs and
videos plus the phases file of ``hbis motors scan --out`` -> an hbis-stack/1 stack; every bad
input is one line, exit code 2, and nothing written."""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import tifffile

from hbis_torch.capture import read_frames
from hbis_torch.cli import main
from hbis_torch.config import FoveaSystem
from hbis_torch.scan import plan_scan
from hbis_torch.stack_io import read_stack

ROI = (600, 450, 24, 20)
REPO = Path(__file__).resolve().parents[1]


def write_phases(path, h=2, system=None, initial=(5.0, 70.0), **change):
    """A phases file as ``hbis motors scan --out`` writes it (read-back = targets rounded to steps)."""
    from hbis_torch.stack_io import system_meta

    system = system or FoveaSystem()
    plan = plan_scan(system, h, initial)
    targets = plan.phases_deg.numpy()
    data = {"format": "hbis-motor-phases/1", "h": h, "method": "exact", "steps_per_deg": [100.0, 100.0],
            "initial_phases_deg": list(initial), "reference_index": int(plan.reference_index),
            "targets_deg": targets.tolist(), "phases_deg": (np.round(targets * 100) / 100).tolist(),
            "predicted_ae": {}, "system": system_meta(system)}
    data.update(change)
    Path(path).write_text(json.dumps(data))
    return data


def frames(count=4, shape=(20, 24), dtype=np.uint16, top=4095, seed=0):
    return np.random.default_rng(seed).integers(0, top + 1, (count, *shape)).astype(dtype)


def assemble(tmp_path, *args):
    return main(["assemble", "--phases", str(tmp_path / "phases.json"), "--out", str(tmp_path / "stack.tif"), "--overwrite",
                 *args])


def one_line_error(capsys, code, fragment, tmp_path):
    assert code == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and err.startswith("hbis assemble: error:") and fragment in err, err
    assert not (tmp_path / "stack.tif").exists()


def test_assemble_files_keeps_read_back_phases_and_reference(tmp_path, capsys):
    data = write_phases(tmp_path / "phases.json")
    f = frames()
    paths = []
    for k, frame in enumerate(f):
        paths.append(str(tmp_path / f"cap_{k:03d}.tif"))
        tifffile.imwrite(paths[-1], frame)
    assert assemble(tmp_path, "--roi", ",".join(map(str, ROI)), "--bit-depth", "12", *paths) == 0
    stack = read_stack(tmp_path / "stack.tif")
    np.testing.assert_array_equal(stack.frames, f)
    np.testing.assert_allclose(stack.phases_deg, data["phases_deg"])
    assert stack.reference_index == data["reference_index"] and stack.h == 2 and stack.roi == ROI
    assert stack.bit_depth == 12 and stack.meta["capture"]["phases_file"] == "phases.json"
    # the same frames by pattern, and as one multi-page TIFF, give the same stack
    assert assemble(tmp_path, "--roi", ",".join(map(str, ROI)), "--bit-depth", "12",
                    str(tmp_path / "cap_{index:03d}.tif")) == 0
    np.testing.assert_array_equal(read_stack(tmp_path / "stack.tif").frames, f)
    assert "--bit-depth" not in capsys.readouterr().err  # given: no hint
    tifffile.imwrite(tmp_path / "all.tif", f, photometric="minisblack")
    assert assemble(tmp_path, "--roi", ",".join(map(str, ROI)), str(tmp_path / "all.tif")) == 0
    np.testing.assert_array_equal(read_stack(tmp_path / "stack.tif").frames, f)
    # 12-bit values in 16-bit frames without --bit-depth: one line names it (the stack keeps 16)
    assert "if the camera records 12 bits, pass --bit-depth 12" in capsys.readouterr().err


def test_full_sensor_frames_are_cut_to_the_roi(tmp_path):
    write_phases(tmp_path / "phases.json", system=FoveaSystem())
    full = frames(shape=(96, 128), dtype=np.uint8, top=255)
    tifffile.imwrite(tmp_path / "all.tif", full, photometric="minisblack")
    assert assemble(tmp_path, "--rows", "96", "--cols", "128", "--roi", "10,20,30,40", str(tmp_path / "all.tif")) == 2
    # the phases file was planned for the Table 1 sensor: refused above; plan it for this one
    from hbis_torch.config import Camera

    small = FoveaSystem(Camera(rows=96, cols=128))
    write_phases(tmp_path / "phases.json", system=small)
    assert assemble(tmp_path, "--rows", "96", "--cols", "128", "--roi", "10,20,30,40", str(tmp_path / "all.tif")) == 0
    np.testing.assert_array_equal(read_stack(tmp_path / "stack.tif").frames, full[:, 20:60, 10:40])


def write_video(path, frames, codec="ffv1", pix_fmt=None):
    """Frames (F, H, W) grey or (F, H, W, 3) RGB uint8 into a lossless video with PyAV."""
    import av

    grey = frames.ndim == 3
    with av.open(str(path), "w") as out:
        stream = out.add_stream(codec, rate=5)
        stream.width, stream.height = frames.shape[2], frames.shape[1]
        stream.pix_fmt = pix_fmt or ("gray" if grey else ("bgr0" if codec == "ffv1" else "rgb24"))
        for f in frames:
            frame = av.VideoFrame.from_ndarray(f, format="gray" if grey else "rgb24")
            out.mux(stream.encode(frame))
        out.mux(stream.encode())


def test_png_and_video_frames(tmp_path):
    from PIL import Image

    write_phases(tmp_path / "phases.json")
    f = frames(dtype=np.uint8, top=255)
    for k, frame in enumerate(f):
        Image.fromarray(frame).save(tmp_path / f"p{k}.png")
    stack, _ = read_frames([str(tmp_path / "p{index}.png")], count=4)
    np.testing.assert_array_equal(stack, f)
    # lossless grey videos (FFV1 in AVI and MKV, PNG in MOV, raw video in AVI) come back as the same frames
    for name, codec in (("scan.avi", "ffv1"), ("scan.mkv", "ffv1"), ("scan.mov", "png"), ("raw.avi", "rawvideo")):
        write_video(tmp_path / name, f, codec)
        video, _ = read_frames([str(tmp_path / name)])
        np.testing.assert_array_equal(video, f)
    rgb = np.random.default_rng(3).integers(0, 256, (3, 20, 24, 3)).astype(np.uint8)
    write_video(tmp_path / "rgb.mkv", rgb)
    np.testing.assert_array_equal(read_frames([str(tmp_path / "rgb.mkv")])[0], rgb)
    assert assemble(tmp_path, "--roi", ",".join(map(str, ROI)), str(tmp_path / "scan.avi")) == 0


REAL = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "real-bursts"


@pytest.mark.skipif(not REAL.is_dir(), reason="the shared real-bursts set is not beside this checkout")
@pytest.mark.parametrize("name", ["text", "disk"])
def test_real_uncompressed_avis_read_bit_identical_to_their_tiffs(name, tmp_path, capsys):
    """The MDSP sequences' 8-bit AVIs (odd widths, rows padded) once killed OpenCV's reader."""
    from hbis_torch.capture.frames import probe_frames

    info, _, _ = probe_frames([REAL / f"{name}.avi"])
    truth = tifffile.imread(REAL / f"{name}.tif")
    assert (info.count, info.shape[:2]) == (truth.shape[0], truth.shape[1:])
    video, names = read_frames([REAL / f"{name}.avi"])
    assert video.dtype == truth.dtype and np.array_equal(video, truth)
    # and through `hbis assemble` in a fresh process (a signal there would kill the test run): the
    # sequence is decoded, then refused in one line because it holds no h x h Risley scan
    write_phases(tmp_path / "phases.json", h=5)
    proc = subprocess.run([sys.executable, "-m", "hbis_torch", "assemble", "--phases", str(tmp_path / "phases.json"),
                           "--roi", f"600,450,{truth.shape[2]},{truth.shape[1]}", "--out", str(tmp_path / "s.tif"),
                           str(REAL / f"{name}.avi")],
                          capture_output=True, text=True, env={**os.environ, "PYTHONPATH": str(REPO)})
    assert proc.returncode == 2, proc.stderr
    assert "different scans" in proc.stderr and len(proc.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "s.tif").exists()


@pytest.mark.parametrize("case, fragment", [
    ("missing", "no such file"),
    ("size", "all frames must have one size and dtype"),
    ("dtype", "all frames must have one size and dtype"),
    ("count", "frames and phases file are from different scans"),
    ("bits", "more than 8 bits hold"),
    ("bits-container", "does not fit uint8"),
    ("roi-outside", "lies outside"),
    ("roi-size", "neither the ROI's"),
    ("nan", "NaN is not a JSON number"),  # refused by the hostile-safe JSON reader
    ("other-scan", "another scan or system"),
    ("other-system", "planned for another system"),
    ("dark-size", "a calibration of another camera or ROI"),
    ("not-json", "not valid JSON"),
])
def test_bad_input_is_one_line_and_nothing_written(tmp_path, capsys, case, fragment):
    write_phases(tmp_path / "phases.json")
    f = frames(dtype=np.uint16, top=255)
    paths = []
    for k, frame in enumerate(f):
        paths.append(str(tmp_path / f"c{k}.tif"))
        tifffile.imwrite(paths[-1], frame)
    args = ["--roi", ",".join(map(str, ROI))]
    if case == "missing":
        Path(paths[2]).unlink()
    elif case == "size":
        tifffile.imwrite(paths[1], f[1][:-1])
    elif case == "dtype":
        tifffile.imwrite(paths[3], f[3].astype(np.uint8))
    elif case == "count":
        paths = paths[:3]
    elif case == "bits":
        tifffile.imwrite(paths[0], f[0] + 300)
        args += ["--bit-depth", "8"]
    elif case == "bits-container":
        for p, frame in zip(paths, f):
            tifffile.imwrite(p, frame.astype(np.uint8))
        args += ["--bit-depth", "12"]
    elif case == "roi-outside":
        args = ["--roi", "1270,450,24,20"]
    elif case == "roi-size":
        args = ["--roi", "600,450,25,20"]
    elif case == "nan":
        text = (tmp_path / "phases.json").read_text().replace("70.", "NaN, 0.0, 70.", 0)
        data = json.loads((tmp_path / "phases.json").read_text())
        data["phases_deg"][1][0] = float("nan")
        (tmp_path / "phases.json").write_text(json.dumps(data))
        assert text
    elif case == "other-scan":
        write_phases(tmp_path / "phases.json", initial=(5.0, 70.0), initial_phases_deg=[6.0, 70.0])
    elif case == "other-system":
        args += ["--focal-length-mm", "16"]
    elif case == "dark-size":
        tifffile.imwrite(tmp_path / "dark.tif", np.zeros((21, 24), np.uint16))
        args += ["--dark", str(tmp_path / "dark.tif")]
    elif case == "not-json":
        (tmp_path / "phases.json").write_text("{h: 2")
    one_line_error(capsys, assemble(tmp_path, *args, *paths), fragment, tmp_path)


def test_an_existing_stack_survives_a_failed_assemble(tmp_path, capsys):
    write_phases(tmp_path / "phases.json")
    (tmp_path / "stack.tif").write_bytes(b"keep me")
    assert assemble(tmp_path, "--roi", ",".join(map(str, ROI)), str(tmp_path / "none_{index}.tif")) == 2
    assert (tmp_path / "stack.tif").read_bytes() == b"keep me"


def test_dark_flat_and_bad_pixels_undo_a_sensor_s_pixel_response(tmp_path):
    """Frames = dark + gain * signal with per-pixel dark and gain and two dead pixels: the
    calibrated stack is the signal again (to rounding), with 'hbis assemble' and 'hbis reconstruct'."""
    from hbis_torch.capture import calibrate_stack, load_calibration
    from hbis_torch.stack_io import write_stack

    write_phases(tmp_path / "phases.json")
    rng = np.random.default_rng(2)
    signal = rng.uniform(0.1, 0.8, (4, 20, 24))
    dark = rng.uniform(60, 90, (20, 24))
    gain = rng.uniform(0.8, 1.2, (20, 24))
    gain /= gain.mean()
    raw = np.round(dark + gain * signal * 3000).astype(np.uint16)
    flat = np.round(dark + gain * 3000).astype(np.uint16)
    bad = np.zeros((20, 24), np.uint8)
    bad[5, 7] = bad[12, 3] = 1
    raw[:, 5, 7] = 4095  # a hot pixel
    tifffile.imwrite(tmp_path / "raw.tif", raw, photometric="minisblack")
    tifffile.imwrite(tmp_path / "dark.tif", np.stack([dark, dark]).round().astype(np.uint16), photometric="minisblack")
    tifffile.imwrite(tmp_path / "flat.tif", flat)
    tifffile.imwrite(tmp_path / "bad.tif", bad)
    cal = ["--dark", str(tmp_path / "dark.tif"), "--flat", str(tmp_path / "flat.tif"),
           "--bad-pixels", str(tmp_path / "bad.tif")]
    assert assemble(tmp_path, "--roi", ",".join(map(str, ROI)), "--bit-depth", "12", *cal, str(tmp_path / "raw.tif")) == 0
    stack = read_stack(tmp_path / "stack.tif")
    assert stack.frames.dtype == np.float32 and stack.meta["calibration"]["bad_pixel_count"] == 2
    expected = signal * 3000 / 4095
    good = np.ones((20, 24), bool)
    good[5, 7] = good[12, 3] = False
    assert np.abs(stack.frames[:, good] - expected[:, good]).max() < 2e-3
    assert abs(stack.frames[0, 5, 7] - expected[0, 5, 7]) < 0.15  # filled from its neighbours, not hot
    # the same correction at reconstruction time, from the raw stack
    raw_stack = stack.__class__(raw, {**{k: v for k, v in stack.meta.items() if k != "calibration"},
                                      "bit_depth": 12})
    corrected = calibrate_stack(raw_stack, load_calibration(tmp_path / "dark.tif", tmp_path / "flat.tif", tmp_path / "bad.tif"))
    np.testing.assert_allclose(corrected.frames, stack.frames, atol=1e-6)
    write_stack(tmp_path / "raw_stack.tif", raw_stack)
    assert main(["reconstruct", str(tmp_path / "raw_stack.tif"), "--registration", "optics", *cal,
                 "--out", str(tmp_path / "sr.tif")]) == 0
    # a flat field of another size is refused by reconstruct too
    tifffile.imwrite(tmp_path / "small.tif", flat[:10])
    assert main(["reconstruct", str(tmp_path / "raw_stack.tif"), "--flat", str(tmp_path / "small.tif"),
                 "--out", str(tmp_path / "sr2.tif")]) == 2
    assert not (tmp_path / "sr2.tif").exists()


def test_without_pyav_a_video_is_one_clear_line(tmp_path, monkeypatch):
    import sys

    from hbis_torch.errors import HbisInputError

    (tmp_path / "scan.avi").write_bytes(b"\0" * 16)
    monkeypatch.setitem(sys.modules, "av", None)  # as if the 'video' extra were not installed
    with pytest.raises(HbisInputError, match=r"needs PyAV: pip install 'hbis-torch\[video\]'"):
        read_frames([str(tmp_path / "scan.avi")])




@pytest.mark.parametrize("orientation", range(1, 9))
def test_a_phone_jpeg_is_read_the_way_up_a_viewer_shows_it(tmp_path, orientation):
    """A phone stores a portrait photograph as the sensor read it and says how to turn it (the
    EXIF orientation): the frames are read upright, as Pillow's exif_transpose turns them, and the
    header's size is the upright one (so a burst's sizes are checked as they will be read)."""
    from PIL import Image, ImageOps

    from hbis_torch.capture.frames import probe_image, read_image

    rng = np.random.default_rng(orientation)
    stored = np.kron(rng.integers(0, 256, (12, 20, 3)), np.ones((8, 8, 1))).astype(np.uint8)  # 96 x 160, blocks
    exif = Image.Exif()
    exif[0x0112] = orientation
    path = tmp_path / "p.jpg"
    Image.fromarray(stored).save(path, quality=98, exif=exif)
    with Image.open(path) as im:
        shown = np.asarray(ImageOps.exif_transpose(im))
    frames = read_image(path)
    assert frames.shape[1:] == shown.shape and probe_image(path).shape == shown.shape
    assert np.abs(frames[0].astype(int) - shown).mean() < 2  # (two JPEG decoders)
    assert (orientation in (5, 6, 7, 8)) == (shown.shape[:2] == (160, 96))


def test_a_folder_or_a_wildcard_gives_its_frames_in_number_order(tmp_path, capsys):
    """A burst given as a folder, or as a wildcard no shell expanded (Windows' does not): its frame
    files in name order with numbers as numbers (f2 before f10), other files left out; an empty
    folder and a wildcard that matches nothing are one line each."""
    from hbis_torch.capture.frames import expand_sources

    folder = tmp_path / "burst"
    folder.mkdir()
    for k in (10, 2, 1):
        tifffile.imwrite(folder / f"f{k}.tif", np.full((30, 40), k, np.uint8))
    (folder / "notes.json").write_text("{}")
    (folder / ".f0.tif").write_bytes(b"")  # a hidden file (a sync tool's)
    names = [Path(p).name for p in expand_sources([folder])]
    assert names == ["f1.tif", "f2.tif", "f10.tif"]
    assert [Path(p).name for p in expand_sources([str(folder / "f*.tif")])] == names
    frames, _ = read_frames(expand_sources([folder]))
    assert frames[:, 0, 0].tolist() == [1, 2, 10]
    (tmp_path / "empty").mkdir()
    for source, fragment in ((tmp_path / "empty", "holds no frame file"), (str(folder / "g*.png"), "matches no file")):
        out = tmp_path / "b.tif"
        assert main(["assemble", "--burst", "--scale", "2", "--out", str(out), str(source)]) == 2
        err = capsys.readouterr().err
        assert fragment in err and len(err.splitlines()) == 1 and not out.exists()


@pytest.mark.parametrize("degrees", [90, -90, 180])
def test_a_phone_s_portrait_video_is_read_the_way_a_player_shows_it(tmp_path, degrees):
    """A phone stores a portrait video as the sensor reads it, with a display matrix that turns it:
    the frames are read turned as a player turns them (anticlockwise by the matrix's rotation),
    and the probe's size is the shown one."""
    av = pytest.importorskip("av")
    from hbis_torch.capture.frames import probe_video

    stored = np.kron(np.random.default_rng(1).integers(0, 256, (6, 10)), np.ones((8, 8))).astype(np.uint8)
    path = tmp_path / "portrait.mp4"
    with av.open(str(path), "w") as container:
        stream = container.add_stream("mpeg4", rate=10)
        stream.width, stream.height, stream.pix_fmt = 80, 48, "yuv420p"
        stream.options = {"qscale": "1"}
        stream.set_display_rotation(degrees)
        for _ in range(3):
            frame = av.VideoFrame.from_ndarray(np.repeat(stored[..., None], 3, -1), format="rgb24")
            for packet in stream.encode(frame):
                container.mux(packet)
        for packet in stream.encode():
            container.mux(packet)
    frames, _ = read_frames([path])
    shown = np.rot90(stored, degrees // 90)
    assert frames.shape[:3] == (3, *shown.shape) and probe_video(path).shape[:2] == shown.shape
    grey = (frames[0].mean(-1) if frames.ndim == 4 else frames[0]).astype(float)
    assert np.abs(grey - shown).mean() < 6  # (the codec's loss)
    assert np.abs(grey - np.rot90(shown, 2)).mean() > 30  # (turned the other way)
