"""Still black bands at a burst's edges (a letterbox, a pillarbox): found, cut away before the
registration, and said; photographed dark or white rows are not taken for bands."""

import numpy as np
import pytest
import tifffile
from skimage import data, transform

from hbis_torch.capture.borders import picture_inside_bands
from hbis_torch.capture.burst import assemble_burst
from hbis_torch.cli import main
from hbis_torch.metrics import psnr
from hbis_torch.reconstruct.registry import reconstruct
from hbis_torch.reconstruct.single_frame import single_frame
from hbis_torch.simulate.burst import random_motions, simulate_burst

pytestmark = pytest.mark.usefixtures("one_thread")
W, H, BAND = 96, 72, 10


def _letterboxed(seed=2):
    """A burst of 8 frames (H, W) uint8 at S = 2 that turn and shift, with black bands of BAND px
    at the top and bottom; and the burst without them."""
    truth = transform.resize(data.camera() / 255.0, (2 * H, 2 * W), anti_aliasing=True)
    motions = random_motions(8, (H, W), np.random.default_rng(seed), 2.0, 0.5)
    burst = simulate_burst(truth, 2, motions, noise=0.005, seed=seed)
    frames = burst.frames.copy()
    frames[:, :BAND] = frames[:, -BAND:] = 0
    return frames, burst


def test_a_letterboxed_burst_is_cut_to_its_picture_and_gains_as_an_unbanded_one():
    frames, burst = _letterboxed()
    stack, messages = assemble_burst(frames, 2)
    assert stack.roi == (0, BAND, W, H - 2 * BAND) and stack.frames.shape[1:] == (H - 2 * BAND, W)
    assert sum("black bands (10 px at the top, 10 px at the bottom)" in m for m in messages) == 1, messages
    picture = (slice(2 * BAND, -2 * BAND), slice(None))
    truth = burst.truth[picture]
    image = reconstruct(stack, "classical")
    assert image.shape == truth.shape
    bicubic = single_frame(frames[0].astype(np.float32) / 255, 2)[picture]
    # the whole frames registered, their bands' still edges holding the motion back (the old way)
    whole, _ = assemble_burst(frames, 2, roi=(0, 0, W, H))
    banded = reconstruct(whole, "classical")[picture]
    gain, whole_gain = psnr(image, truth) - psnr(bicubic, truth), psnr(banded, truth) - psnr(bicubic, truth)
    assert gain > whole_gain + 3.0, (gain, whole_gain)  # +6.58 against -7.37 dB
    # as the burst without bands gains on the same picture
    plain = reconstruct(assemble_burst(burst.frames, 2)[0], "classical")[picture]
    assert gain > psnr(plain, truth) - psnr(bicubic, truth) - 0.3


def test_the_command_line_says_so_and_roi_keeps_the_whole_frames(tmp_path, capsys):
    frames, _ = _letterboxed()
    tifffile.imwrite(tmp_path / "frames.tif", frames, photometric="minisblack")
    out = tmp_path / "b.tif"
    assert main(["assemble", "--burst", "--scale", "2", "--out", str(out), str(tmp_path / "frames.tif")]) == 0
    said = capsys.readouterr()
    assert "black bands" in said.err and f"--roi 0,0,{W},{H}" in said.err
    assert f"frames of {W} x {H - 2 * BAND} px" in said.out
    assert main(["assemble", "--burst", "--scale", "2", "--roi", f"0,0,{W},{H}", "--out", str(out), "--overwrite",
                 str(tmp_path / "frames.tif")]) == 0
    said = capsys.readouterr()
    assert "black bands" not in said.err and f"frames of {W} x {H} px" in said.out


def test_bands_on_every_side_and_codec_rounding():
    frames = np.random.default_rng(0).integers(40, 220, (3, 50, 80), dtype=np.uint8)
    frames[:, :, :6] = 16  # limited-range black, a pillarbox
    frames[:, :, -7:] = 17
    frames[:, :3] = 16
    assert picture_inside_bands(frames, 255) == (6, 3, 80 - 13, 47)
    frames[1, 1, 40] = 19  # more than a codec's rounding: the top band ends there
    assert picture_inside_bands(frames, 255) == (6, 1, 80 - 13, 49)


def test_photographed_dark_or_white_rows_are_not_bands():
    rng = np.random.default_rng(1)
    frames = rng.integers(40, 220, (4, 50, 80)).astype(np.float32) / 255
    frames[:, :8] = np.clip(0.01 + rng.normal(0, 0.01, (4, 8, 80)), 0, 1)  # a night sky: the sensor's noise
    frames[:, -8:] = 1.0  # a sky clipped to white
    assert picture_inside_bands(frames, 1.0) is None
    # a burst of black frames leaves no picture: not a band either (the registration refuses it)
    assert picture_inside_bands(np.zeros((3, 30, 30), np.uint8), 255) is None


def test_ten_bits_in_a_sixteen_bit_file_keep_their_dark_rows():
    # 10-bit values written to 16 bits: a dark row of the photograph varies by a few 10-bit steps,
    # under 2/255 of 65535 but not of the values' own white (1023)
    _, burst = _letterboxed()
    tenbit = burst.frames.astype(np.uint16) * 4
    tenbit[:, :BAND] = np.random.default_rng(3).integers(20, 60, (len(tenbit), BAND, W))  # dark, photographed
    stack, messages = assemble_burst(tenbit, 2)
    assert stack.roi == (0, 0, W, H) and not any("black bands" in m for m in messages)
