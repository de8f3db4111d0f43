"""Each frame's sharpness, the sharpest frame as the reference, and a blurred reference named."""

import numpy as np
import pytest
import tifffile
import torch
from scipy.ndimage import gaussian_filter, uniform_filter1d

from hbis_torch.capture.burst import assemble_burst, luminance
from hbis_torch.capture.sharpness import BLURRED_SHARE, choose_reference, frame_sharpness
from hbis_torch.cli import main
from hbis_torch.notices import asks_to_act
from hbis_torch.stack_io import read_stack
from hbis_torch.training.handheld_render import render_burst

pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture(scope="module")
def burst():
    """A hand-held burst of 8 equally sharp frames of 160 x 120 px (every motion)."""
    return render_burst("all", 2, 8, 160, 120, seed=4).frames


def _blurred(frames: np.ndarray, k: int, sigma: float = 1.0) -> np.ndarray:
    out = frames.copy()
    out[k] = np.round(gaussian_filter(frames[k].astype(np.float64), sigma)).astype(frames.dtype)
    return out


def test_a_frames_gain_and_offset_leave_its_sharpness_alone(burst):
    grey = luminance(burst)
    changed = grey.clone()
    changed[2] = changed[2] * 0.8 + 0.05
    assert np.allclose(frame_sharpness(changed), frame_sharpness(grey), rtol=1e-4)


def test_a_blurred_or_smeared_frame_is_the_least_sharp(burst):
    smeared = burst.copy()
    smeared[5] = np.round(uniform_filter1d(burst[5].astype(np.float64), 3, axis=1)).astype(burst.dtype)  # 3 px of shake
    for frames, k in ((_blurred(burst, 3), 3), (smeared, 5)):
        sharpness = frame_sharpness(luminance(frames))
        assert int(np.argmin(sharpness)) == k
        assert sharpness[k] < BLURRED_SHARE * sharpness.max()


def test_equally_sharp_frames_name_no_blurred_reference_and_keep_the_first(burst):
    grey = luminance(burst)
    sharpness = frame_sharpness(grey)
    assert sharpness.min() > 0.8 * sharpness.max()
    assert choose_reference(grey, 0) == (0, [])
    assert choose_reference(grey, "sharpest")[0] == 0


def test_a_blurred_reference_is_named_and_sharpest_takes_another(burst):
    grey = luminance(_blurred(burst, 0))
    index, messages = choose_reference(grey, 0)
    assert index == 0 and len(messages) == 1 and asks_to_act(messages[0])
    assert "frame 0, is blurred" in messages[0] and "--reference sharpest" in messages[0]
    index, messages = choose_reference(grey, "sharpest")
    assert index != 0 and messages == [f"reference: frame {index}, the sharpest of the burst (--reference sharpest)"]


def test_assemble_with_the_sharpest_reference(burst, tmp_path, capsys):
    frames = _blurred(burst, 0)
    stack, messages = assemble_burst(frames, 2, reference="sharpest")
    assert stack.reference_index != 0 and stack.confidence[stack.reference_index] == 1.0
    assert any("the sharpest of the burst" in m for m in messages)
    _, messages = assemble_burst(frames, 2)
    assert any("is blurred" in m for m in messages)
    tifffile.imwrite(tmp_path / "frames.tif", frames)
    out = tmp_path / "burst.tif"
    assert main(["assemble", "--burst", "--scale", "2", "--reference", "sharpest", "--out", str(out),
                 str(tmp_path / "frames.tif")]) == 0
    assert read_stack(out).reference_index == stack.reference_index
    capsys.readouterr()
    with pytest.raises(SystemExit) as exit_:  # argparse's own refusal
        main(["assemble", "--burst", "--scale", "2", "--reference", "sharp", "--out", str(tmp_path / "b.tif"),
              str(tmp_path / "frames.tif")])
    assert exit_.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "'sharpest'" in err[0] and not (tmp_path / "b.tif").exists()


def test_raw_frames_refuse_the_sharpest_reference_before_reading(tmp_path):
    from hbis_torch.capture.raw import assemble_raw_burst
    from hbis_torch.errors import HbisInputError

    with pytest.raises(HbisInputError, match="grey and RGB frames"):
        assemble_raw_burst([tmp_path / "a.dng", tmp_path / "b.dng"], 2, reference="sharpest")


def test_sharpness_is_zero_for_flat_frames():
    assert np.array_equal(frame_sharpness(torch.full((3, 40, 40), 0.5)), np.zeros(3))
