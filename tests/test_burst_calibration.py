"""A burst from a sensor with its own dark current, pixel response and bad pixels, assembled with
the sensor's calibration (--dark, --flat, --bad-pixels): corrected before the motion is measured,
the bad pixels given no weight."""

import numpy as np
import pytest
import tifffile
from skimage import data, transform

from hbis_torch.cli import main
from hbis_torch.metrics import psnr
from hbis_torch.simulate.burst import random_motions, simulate_burst
from hbis_torch.stack_io import read_image, read_stack

pytestmark = pytest.mark.usefixtures("one_thread")
W, H, LEVEL, WHITE = 96, 72, 3000, 4095  # 12-bit numbers: the signal's white at LEVEL


@pytest.fixture
def sensor_burst(tmp_path):
    """A burst through a sensor of per-pixel dark (60 to 90) and gain (0.7 to 1.3), a dead pixel
    and a hot one, written as 12-bit numbers with its calibration files; and its truth in the
    corrected frames' units."""
    truth = transform.resize(data.camera() / 255.0, (2 * H, 2 * W), anti_aliasing=True)
    burst = simulate_burst(truth, 2, random_motions(8, (H, W), np.random.default_rng(3), 2.0, 0.3), noise=0.003,
                           seed=3)
    rng = np.random.default_rng(4)
    dark = rng.uniform(60, 90, (H, W))
    gain = rng.uniform(0.7, 1.3, (H, W))
    gain /= gain.mean()
    frames = np.round(dark + gain * burst.frames / 255.0 * LEVEL).astype(np.uint16)
    frames[:, 30, 40], frames[:, 50, 20] = WHITE, 0  # hot, dead
    bad = np.zeros((H, W), np.uint8)
    bad[30, 40] = bad[50, 20] = 1
    paths = {"frames": tmp_path / "frames.tif", "dark": tmp_path / "dark.tif", "flat": tmp_path / "flat.tif",
             "bad": tmp_path / "bad.tif"}
    tifffile.imwrite(paths["frames"], frames, photometric="minisblack")
    tifffile.imwrite(paths["dark"], np.round(dark).astype(np.uint16))
    tifffile.imwrite(paths["flat"], np.round(dark + gain * LEVEL).astype(np.uint16))
    tifffile.imwrite(paths["bad"], bad)
    return paths, burst.truth * LEVEL / WHITE


def _assemble(paths, out, *more):
    return main(["-q", "assemble", "--burst", "--scale", "2", "--bit-depth", "12", "--out", str(out), *more,
                 str(paths["frames"])])


def test_a_calibrated_burst_is_corrected_before_its_motion_and_gains(sensor_burst, tmp_path):
    paths, truth = sensor_burst
    cal = ["--dark", str(paths["dark"]), "--flat", str(paths["flat"]), "--bad-pixels", str(paths["bad"])]
    assert _assemble(paths, tmp_path / "cal.tif", *cal) == 0
    stack = read_stack(tmp_path / "cal.tif")
    assert stack.frames.dtype == np.float32 and "bit_depth" not in stack.meta
    assert stack.meta["calibration"] == {"dark": "dark.tif", "flat": "flat.tif", "bad_pixels": "bad.tif",
                                         "bad_pixel_count": 2}
    assert {(30, 40), (50, 20)} <= set(map(tuple, stack.meta["stuck_pixels"]))
    assert _assemble(paths, tmp_path / "raw.tif") == 0  # the same numbers, uncorrected
    scores = {}
    for name in ("cal", "raw"):
        out = tmp_path / f"{name}_sr.tif"
        assert main(["-q", "reconstruct", str(tmp_path / f"{name}.tif"), "--out", str(out)]) == 0
        image, _ = read_image(out)
        scores[name] = psnr(np.clip(image, 0, 1), truth)
    # uncorrected, the pixel response's pattern and the black level stay in the image
    assert scores["cal"] > scores["raw"] + 5.0, scores


def test_a_calibration_of_another_size_is_refused_before_the_frames_are_read(sensor_burst, tmp_path, capsys):
    paths, _ = sensor_burst
    tifffile.imwrite(tmp_path / "small.tif", np.zeros((H // 2, W), np.uint16))
    out = tmp_path / "b.tif"
    assert _assemble(paths, out, "--dark", str(tmp_path / "small.tif")) == 2
    err = capsys.readouterr().err
    assert "dark frame small.tif is 96 x 36 pixels but the frames are 96 x 72" in err and len(err.splitlines()) == 1
    assert not out.exists()
    # a calibration of the captured frames' size is cut with them by --roi
    assert _assemble(paths, out, "--roi", "8,8,64,48", "--dark", str(paths["dark"])) == 0
    assert read_stack(out).frames.shape == (8, 48, 64)


def test_reconstruct_asks_for_a_burst_s_calibration_at_assembly(sensor_burst, tmp_path, capsys):
    paths, _ = sensor_burst
    assert _assemble(paths, tmp_path / "b.tif") == 0
    capsys.readouterr()
    assert main(["reconstruct", str(tmp_path / "b.tif"), "--dark", str(paths["dark"]),
                 "--out", str(tmp_path / "sr.tif")]) == 2
    assert "give --dark, --flat and --bad-pixels to 'hbis assemble --burst'" in capsys.readouterr().err
    assert not (tmp_path / "sr.tif").exists()
