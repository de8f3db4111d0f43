"""OpenCV calibration files as users bring them: written by cv2.FileStorage (YAML, XML, JSON), a
stereo result, one without an image size, and broken ones. Every problem is one line naming the
file and the key, found before anything large is allocated."""

import logging
import time
import tracemalloc

import numpy as np
import pytest

from hbis_torch.capture.lens import read_opencv_calibration
from hbis_torch.capture.system_file import principal_point_offset, with_lens
from hbis_torch.cli import main
from hbis_torch.config import FoveaSystem
from hbis_torch.errors import HbisInputError

cv2 = pytest.importorskip("cv2")

K = np.array([[3205.1, 0.0, 641.3], [0.0, 3204.7, 478.9], [0.0, 0.0, 1.0]])
D = np.array([[-0.12, 0.05, 0.0003, -0.0002, 0.0]])


def write_fs(path, **nodes):
    """What cv2.FileStorage writes: matrices as opencv-matrix, numbers as they are."""
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    for name, value in nodes.items():
        fs.write(name, value)
    fs.release()
    return path


@pytest.mark.parametrize("suffix", [".yml", ".xml", ".json"])
def test_a_calibration_opencv_wrote_reads_back(tmp_path, suffix):
    path = write_fs(tmp_path / f"cal{suffix}", image_width=1280, image_height=960, camera_matrix=K,
                    distortion_coefficients=D)
    cal = read_opencv_calibration(path)
    assert (cal.fx, cal.fy, cal.cx, cal.cy, cal.image_size) == (3205.1, 3204.7, 641.3, 478.9, (1280, 960))
    assert cal.distortion[:5] == pytest.approx(tuple(D[0]))


def test_a_stereo_file_needs_a_camera_chosen(tmp_path):
    k2 = K.copy()
    k2[0, 2] = 650.0
    path = write_fs(tmp_path / "intrinsics.yml", M1=K, D1=D, M2=k2, D2=D * 2)
    with pytest.raises(HbisInputError, match=r"stereo calibration with cameras M1, M2: choose one with FILE:M1"):
        read_opencv_calibration(path)
    assert read_opencv_calibration(f"{path}:M2").cx == 650.0
    assert read_opencv_calibration(f"{path}:M1").distortion[0] == pytest.approx(-0.12)
    with pytest.raises(HbisInputError, match=r"intrinsics.yml:M3: no camera 'M3'"):
        read_opencv_calibration(f"{path}:M3")


def test_no_image_size_and_an_off_centre_principal_point_is_warned_about(tmp_path, caplog):
    k = K.copy()
    k[0, 2], k[1, 2] = 320.0, 240.0  # made on a 640 x 480 image
    path = write_fs(tmp_path / "params.yml", camera_matrix=k, distortion_coefficients=D)
    system = FoveaSystem()
    off = principal_point_offset(read_opencv_calibration(path), 1280, 960)
    assert off == pytest.approx(np.hypot(639.5 - 320, 479.5 - 240))
    with caplog.at_level(logging.WARNING, logger="hbis_torch"):
        with_lens(system, read_opencv_calibration(path), str(path))
    assert f"lies {off:.0f} px from the centre of the 1280 x 960 sensor" in caplog.text
    caplog.clear()
    centred = write_fs(tmp_path / "centred.yml", camera_matrix=K, distortion_coefficients=D)
    with caplog.at_level(logging.WARNING, logger="hbis_torch"):
        with_lens(system, read_opencv_calibration(centred), str(centred))
    assert caplog.text == ""


YAML_MATRIX = "%YAML:1.0\n---\n{extra}camera_matrix: !!opencv-matrix\n   rows: {rows}\n   cols: {cols}\n   dt: d\n   data: [ {data} ]\n"
NINE = "3205.1, 0., 641.3, 0., 3204.7, 478.9, 0., 0., 1."
BROKEN = {
    "two numbers for 3 x 3": (YAML_MATRIX.format(extra="", rows=3, cols=3, data="3200., 0."),
                              "camera_matrix declares 3 x 3 = 9 numbers but its data holds 2"),
    "3e8 x 3e8 declared (XML)": ('<?xml version="1.0"?>\n<opencv_storage>\n<camera_matrix type_id="opencv-matrix">'
                                 "<rows>300000000</rows><cols>300000000</cols><dt>d</dt><data>1 0 0 0 1 0 0 0 1</data>"
                                 "</camera_matrix>\n</opencv_storage>\n", "declares a 300000000 x 300000000 matrix"),
    "rows not whole": (YAML_MATRIX.format(extra="", rows=2.5, cols=3, data=NINE), "camera_matrix.rows must be a whole number"),
    "NaN in K": (YAML_MATRIX.format(extra="", rows=3, cols=3, data=NINE.replace("641.3", ".nan")), "not finite"),
    "infinite focal length": (YAML_MATRIX.format(extra="", rows=3, cols=3, data=NINE.replace("3205.1", ".Inf")), "not finite"),
    "negative focal length": (YAML_MATRIX.format(extra="", rows=3, cols=3, data=NINE.replace("3205.1", "-3205.1")),
                              "focal lengths"),
    "absurd focal length": (YAML_MATRIX.format(extra="", rows=3, cols=3, data=NINE.replace("3205.1", "1e300")),
                            "focal lengths"),
    "text in the data": (YAML_MATRIX.format(extra="", rows=3, cols=3, data=NINE.replace("641.3", "abc")),
                         "not a number"),
    "1 x 9 for 3 x 3": (YAML_MATRIX.format(extra="", rows=1, cols=9, data=NINE), "must be a 3 x 3 matrix"),
    "image size 1e12": (YAML_MATRIX.format(extra="image_width: 1000000000000\nimage_height: 960\n", rows=3, cols=3,
                                           data=NINE), "image_size must be (cols, rows)"),
    "image size text": (YAML_MATRIX.format(extra="image_width: wide\nimage_height: 960\n", rows=3, cols=3, data=NINE),
                        "image_width must be a whole number"),
    "camera matrix is a string": ("%YAML:1.0\n---\ncamera_matrix: hello\n", "camera_matrix holds something that is not a number"),
    "a map without data": ("%YAML:1.0\n---\ncamera_matrix:\n   rows: 3\n   cols: 3\n", "camera_matrix is not a matrix"),
    "no camera matrix": ("%YAML:1.0\n---\nfoo: 1\n", "no camera matrix"),
    "not YAML at all": ("\x00\x01garbage{{{", "OpenCV cannot"),
    "huge distortion": (YAML_MATRIX.format(extra="", rows=3, cols=3, data=NINE)
                        + "distortion_coefficients: !!opencv-matrix\n   rows: 1\n   cols: 5\n   dt: d\n   data: [ 1e30, 0., 0., 0., 0. ]\n",
                        "distortion coefficients must be finite"),
    "14 distortion coefficients": (YAML_MATRIX.format(extra="", rows=3, cols=3, data=NINE)
                                   + "distortion_coefficients: [ " + ", ".join(["0.1"] * 14) + " ]\n",
                                   "distortion must be 4, 5 or 8"),
}


@pytest.mark.parametrize("name", list(BROKEN))
def test_a_broken_calibration_is_one_line_naming_file_and_key(tmp_path, name):
    text, fragment = BROKEN[name]
    path = tmp_path / ("cal.xml" if text.startswith("<?xml") else "cal.yml")
    path.write_text(text)
    tracemalloc.start()
    start = time.perf_counter()
    try:
        with pytest.raises(HbisInputError) as info:
            read_opencv_calibration(path)
    finally:
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
    message = str(info.value)
    assert fragment in message and str(path) in message and "\n" not in message, message
    assert time.perf_counter() - start < 2.0 and peak < 300 * 2**20


def test_a_huge_calibration_file_is_refused_unread(tmp_path):
    path = tmp_path / "cal.yml"
    path.write_text("%YAML:1.0\n---\n" + "# padding\n" * 200_000)
    with pytest.raises(HbisInputError, match="more than a calibration file holds"):
        read_opencv_calibration(path)


def test_the_cli_refuses_a_broken_calibration_in_one_line(tmp_path, capsys):
    path = tmp_path / "cal.yml"
    path.write_text(BROKEN["two numbers for 3 x 3"][0])
    (tmp_path / "phases.json").write_text("{}")
    code = main(["assemble", "--phases", str(tmp_path / "phases.json"), "--calibration", str(path),
                 "--out", str(tmp_path / "s.tif"), str(tmp_path / "f.tif")])
    err = capsys.readouterr().err.strip()
    assert code == 2 and "\n" not in err and "camera_matrix declares 3 x 3 = 9 numbers" in err, err
    assert not (tmp_path / "s.tif").exists()
