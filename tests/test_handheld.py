"""hbis_torch.training.handheld_render (hand-held bursts at real sizes) and training/eval_handheld.py:
the frames move as the true motion says, the truth lies on frame 0's grid, and the eval resumes."""

import json

import numpy as np
import pytest
from scipy.ndimage import map_coordinates

from hbis_torch.training.handheld_render import MOTIONS, render_burst

W, H = 96, 72
INNER = (slice(12, -12), slice(12, -12))


def reference_at_flow(burst, k, flow=None):
    """The noise-free reference frame read (cubic spline) where frame k's pixels lie in it."""
    flow = burst.flow(k) if flow is None else flow
    return map_coordinates(burst.clean[0].astype(np.float64), [flow[..., 1], flow[..., 0]], order=3)


@pytest.mark.parametrize("motion", ["similarity", "homography", "rolling_shutter", "brightness"])
def test_a_frame_is_the_reference_seen_through_its_true_motion(motion):
    burst = render_burst(motion, 2, 4, W, H, noise=False, keep_clean=True, seed=3)
    assert burst.frames.shape == (4, H, W) and burst.frames.dtype == np.uint16
    assert burst.truth.shape == (2 * H, 2 * W) and burst.truth.dtype == np.float32
    np.testing.assert_array_equal(burst.motions[0], np.eye(3))
    for k in range(1, 4):
        g, o = burst.gain_offset[k]
        frame = burst.clean[k].astype(np.float64)
        through = g * reference_at_flow(burst, k) + o
        # the other way round (reference px -> frame px) puts the samples elsewhere
        wrong = burst.flow(k) - 2 * (burst.flow(k) - np.stack(np.mgrid[0:H, 0:W][::-1], -1))
        error = np.abs(through - frame)[INNER].mean()
        assert error < 3e-3  # well under the noise (1 % at mid grey): what resampling an aliased frame leaves
        assert error < 0.5 * np.abs(g * reference_at_flow(burst, k, wrong) + o - frame)[INNER].mean()
        assert error < 0.5 * np.abs(burst.clean[0] - frame)[INNER].mean()
    if motion == "rolling_shutter":  # one homography cannot hold it, the oracle's comes nearest
        assert np.abs(burst.row_shift[1:]).max() > 0.2
        fit = burst.oracle_motions()
        assert not np.allclose(fit[1:], burst.motions[1:])
        v, u = np.mgrid[0:H, 0:W]
        points = np.stack((u.ravel(), v.ravel(), np.ones(u.size)))
        for k in range(1, 4):  # nearer the true flow at every pixel than the frame's own homography
            errors = []
            for homography in (fit[k], burst.motions[k]):
                mapped = homography @ points
                errors.append(np.abs(mapped[:2] / mapped[2] - burst.flow(k).reshape(-1, 2).T).mean())
            assert errors[0] < 0.75 * errors[1], errors
    if motion == "brightness":
        g, o = burst.stack_gain_offset()[1]
        assert g * (burst.gain_offset[1, 0] * 0.5 + burst.gain_offset[1, 1]) + o == pytest.approx(0.5)


def test_the_truth_lies_on_frame_0s_grid():
    """Frame 0 before noise (no lens blur) is the truth averaged over S x S blocks; the truth moved
    by one output pixel is not."""
    S = 3
    burst = render_burst("translation", S, 2, W, H, blur_sigma_px=0.0, noise=False, keep_clean=True, seed=5)
    blocks = burst.truth.reshape(H, S, W, S).mean((1, 3))
    moved = np.roll(burst.truth, 1, axis=1).reshape(H, S, W, S).mean((1, 3))
    error = np.abs(blocks - burst.clean[0])[INNER].mean()
    assert error < 2e-3
    assert error < 0.2 * np.abs(moved - burst.clean[0])[INNER].mean()
    # and the noisy 16-bit frame is that signal with about 1 % noise at mid grey
    noisy = render_burst("translation", S, 2, W, H, blur_sigma_px=0.0, seed=5).frames[0] / 65535.0
    assert 0.003 < np.std(noisy - burst.clean[0]) < 0.02


def test_the_lens_blur_and_the_moving_object_show():
    sharp = render_burst("moving_object", 2, 3, W, H, blur_sigma_px=0.0, noise=False, keep_clean=True, seed=1)
    soft = render_burst("moving_object", 2, 3, W, H, blur_sigma_px=0.8, noise=False, keep_clean=True, seed=1)
    assert soft.blur_sigma_px == 0.8
    assert np.abs(np.diff(soft.clean[0], axis=1)).mean() < 0.8 * np.abs(np.diff(sharp.clean[0], axis=1)).mean()
    assert sharp.object_box is not None and np.abs(sharp.object_offset[1:]).max() >= 2
    # the object moves on its own: the frame is not the reference through the camera's motion there
    x0, y0, side = (v // 2 for v in sharp.object_box)
    where = (slice(y0, y0 + side), slice(x0, x0 + side))
    outside = np.abs(sharp.clean[1] - reference_at_flow(sharp, 1))
    assert outside[where].mean() > 5 * np.median(outside[INNER])


def test_shaken_frames_are_the_reference_seen_through_their_motion_and_a_smear():
    burst = render_burst("shaken", 2, 9, W, H, noise=False, keep_clean=True, seed=3)
    assert len(burst.shaken) == 2 and 0 not in burst.shaken
    for k in range(1, 9):
        frame, through = burst.clean[k].astype(np.float64), reference_at_flow(burst, k)
        error = np.abs(through - frame)[INNER].mean()
        if k in burst.shaken:  # smeared: softer than the reference seen through the motion
            assert error > 3e-3
            assert np.abs(np.diff(frame, axis=1))[INNER].mean() < 0.9 * np.abs(np.diff(through, axis=1))[INNER].mean()
        else:
            assert error < 3e-3


def test_every_motion_renders():
    for motion in MOTIONS:
        burst = render_burst(motion, 2, 2, 48, 40, seed=0)
        assert burst.frames.shape == (2, 40, 48) and burst.motion == motion


@pytest.fixture(scope="module")
def eh(load_script):
    return load_script("training/eval_handheld.py")


def test_the_eval_resumes_where_it_stopped(eh, tmp_path, capsys):
    out = tmp_path / "cells.json"
    args = ["--out", str(out), "--motions", "translation", "--scales", "2", "--frames", "3", "--size", "64x48",
            "--no-vidsr", "--no-learned"]
    assert eh.main(args) == 0
    done = json.loads(out.read_text())
    cell = done["cells"]["translation|S=2|F=3"]
    assert set(cell["rows"]) == {"bicubic", "classical", "classical_lens", "oracle"}
    assert cell["rows"]["classical"]["psnr_db"] > cell["rows"]["bicubic"]["psnr_db"] - 3
    # a run stopped before its oracle row: the rerun keeps what was there and adds only that row
    cell["rows"]["bicubic"]["psnr_db"] = 99.0
    del cell["rows"]["oracle"]
    out.write_text(json.dumps(done))
    assert eh.main(args) == 0
    again = json.loads(out.read_text())["cells"]["translation|S=2|F=3"]["rows"]
    assert again["bicubic"]["psnr_db"] == 99.0 and again["oracle"]["run"] == 1
    assert "translation" in out.with_suffix(".md").read_text()
    # other settings are refused in one line, the file untouched
    before = out.read_text()
    assert eh.main(args[:-2] + ["--no-learned", "--blur", "0.5"]) == 2
    assert "other settings" in capsys.readouterr().err and out.read_text() == before
    assert eh.main(["--out", str(out), "--motions", "spin"]) == 2
    # the table alone, from what the file holds
    out.with_suffix(".md").unlink()
    assert eh.main(["--out", str(out), "--table-only"]) == 0
    assert "| translation | " in out.with_suffix(".md").read_text()


def test_a_dimmer_light_is_a_setting_of_its_own(eh, tmp_path, capsys):
    out = tmp_path / "dim.json"
    args = ["--out", str(out), "--motions", "translation", "--scales", "2", "--frames", "3", "--size", "64x48",
            "--no-vidsr", "--no-learned", "--rows", "bicubic"]
    assert eh.main([*args, "--full-well", "200"]) == 0
    dim = json.loads(out.read_text())
    assert dim["settings"]["full_well_e"] == 200 and "(200 e- full well" in out.with_suffix(".md").read_text()
    # a dimmer light's burst is noisier: bicubic of its reference scores lower than in the default light
    bright = tmp_path / "bright.json"
    assert eh.main([*args[:1], str(bright), *args[2:]]) == 0
    default = json.loads(bright.read_text())
    assert "full_well_e" not in default["settings"]  # files made before the setting existed resume
    key = "translation|S=2|F=3"
    assert dim["cells"][key]["rows"]["bicubic"]["psnr_db"] < default["cells"][key]["rows"]["bicubic"]["psnr_db"] - 3
    # resuming the dim file in the default light is refused, the file untouched
    before = out.read_text()
    assert eh.main(args) == 2 and "other settings" in capsys.readouterr().err and out.read_text() == before
    assert eh.main([*args, "--full-well", "5"]) == 2 and "--full-well" in capsys.readouterr().err


def test_redo_runs_the_named_rows_again_once(eh, tmp_path, capsys):
    out = tmp_path / "cells.json"
    args = ["--out", str(out), "--motions", "translation", "--scales", "2", "--frames", "3", "--size", "64x48",
            "--no-vidsr", "--no-learned", "--rows", "bicubic", "classical"]
    assert eh.main(args) == 0
    done = json.loads(out.read_text())
    rows = done["cells"]["translation|S=2|F=3"]["rows"]
    rows["bicubic"]["psnr_db"] = rows["classical"]["psnr_db"] = 99.0  # what an older method gave
    out.write_text(json.dumps(done))
    assert eh.main([*args, "--redo", "classical"]) == 0
    again = json.loads(out.read_text())
    rows = again["cells"]["translation|S=2|F=3"]["rows"]
    assert rows["bicubic"]["psnr_db"] == 99.0 and rows["bicubic"]["run"] == 0
    assert rows["classical"]["psnr_db"] < 99.0 and rows["classical"]["run"] == 1
    assert eh.main([*args, "--redo", "classical"]) == 0  # done: the same run, nothing run again
    assert json.loads(out.read_text()) == {**again, "summary": json.loads(out.read_text())["summary"]}
    assert eh.main([*args, "--redo", "oracle"]) == 2
    assert "--redo oracle" in capsys.readouterr().err


def test_the_eval_runs_only_the_rows_asked_for_and_compares_learned_with_classical(eh, tmp_path, capsys):
    out = tmp_path / "learned.json"
    assert eh.main(["--out", str(out), "--motions", "translation", "--rows", "bogus", "--size", "64x48"]) == 2
    assert "unknown row(s) bogus" in capsys.readouterr().err and not out.exists()
    assert eh.main(["--out", str(out), "--motions", "translation", "--scales", "2", "--frames", "4", "--size",
                    "64x48", "--rows", "classical", "learned"]) == 0
    results = json.loads(out.read_text())
    rows = results["cells"]["translation|S=2|F=4"]["rows"]
    assert set(rows) == {"classical", "learned"}
    learned = results["summary"]["S=2|F=4"]["learned_minus_classical"]
    assert learned["mean_db"] == pytest.approx(rows["learned"]["psnr_db"] - rows["classical"]["psnr_db"])
    assert learned["time_ratio_worst"] == pytest.approx(rows["learned"]["seconds"] / rows["classical"]["seconds"])
    assert "Learned - classical over the 1 cells with both" in out.with_suffix(".md").read_text()


def test_the_vidsr_peer_gives_an_image_on_the_truths_grid(eh):
    pytest.importorskip("vidsr")
    vidsr_sr = eh._peer().vidsr_sr  # benchmarks/peers/vidsr_peer.py, as the eval loads it

    burst = render_burst("translation", 2, 6, W, H, seed=2)
    image = vidsr_sr(burst.frames, 2)
    assert image.shape == burst.truth.shape and image.dtype == np.float32
    # on the truth's grid: better than the reference enlarged, and worse moved by one output pixel
    score = eh.psnr(image, burst.truth, 4, 2)
    assert score > eh.psnr(eh.bicubic(burst.frames[0], 2), burst.truth, 4, 2)
    assert score > eh.psnr(np.roll(image, 1, axis=1), burst.truth, 4, 2) + 1


def test_the_vidsr_peer_takes_colour_frames_and_gives_each_channel(eh):
    """Colour frames (F, H, W, 3): registered once on their grey, each channel fused on the truth's
    grid: a burst whose channels are the grey one times 1, 0.8 and 0.6 comes back in those
    proportions (vidsr's fusion and back-projection are linear), each channel ahead of its bicubic
    enlargement."""
    pytest.importorskip("vidsr")
    vidsr_sr = eh._peer().vidsr_sr
    burst = render_burst("translation", 2, 6, W, H, seed=2)
    gains = np.array([1.0, 0.8, 0.6], np.float32)
    grey = burst.frames.astype(np.float32) / 65535
    image = vidsr_sr(grey[..., None] * gains, 2)
    assert image.shape == (*burst.truth.shape, 3) and image.dtype == np.float32
    assert np.allclose(np.median(image / image[..., :1], axis=(0, 1)), gains, rtol=1e-3)
    bicubic = eh.bicubic(burst.frames[0][..., None].repeat(3, -1), 2) * gains
    for c in range(3):
        truth = burst.truth * gains[c]
        assert eh.psnr(image[..., c], truth, 4, 2) > eh.psnr(bicubic[..., c], truth, 4, 2)


def test_swap_shifts_renders_a_cell_with_another_cells_motion(load_script, tmp_path, capsys):
    swap = load_script("training/swap_shifts.py")
    out = tmp_path / "swap.json"
    args = ["--out", str(out), "--pairs", "moving_object:translation", "--frames", "3", "--size", "64x48"]
    assert swap.main(args) == 0
    pair = json.loads(out.read_text())["pairs"]["moving_object:translation"]
    donor = render_burst("translation", 2, 3, 64, 48, seed=0)
    assert pair["swapped"]["phases_px"] == swap.centre_phases(donor.motions, 2, 64, 48)
    assert pair["drawn"]["phases_px"] != pair["swapped"]["phases_px"]
    assert all(np.isfinite(pair[k]["classical_db"]) for k in ("drawn", "swapped"))
    # the file is never overwritten, and a bad pair is refused before any work, in one line
    before = out.read_text()
    assert swap.main(args) == 2 and out.read_text() == before
    assert swap.main(["--out", str(tmp_path / "new.json"), "--pairs", "spin:translation"]) == 2
    assert "CELL:DONOR" in capsys.readouterr().err and not (tmp_path / "new.json").exists()
