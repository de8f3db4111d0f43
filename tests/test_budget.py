"""Up-front memory and time estimates: printed with -v, a job over the available memory refused in
one line before any work unless --force."""

import pytest

from hbis_torch import budget
from hbis_torch.cli import main
from hbis_torch.errors import HbisInputError


def test_estimates_grow_with_the_work_and_refuse_past_the_available_memory():
    small, big = budget.estimate_simulate(16, 64, 64), budget.estimate_simulate(256, 1280, 960)
    assert small.memory_bytes < 2**30 < 20 * 2**30 < big.memory_bytes and small.seconds < big.seconds
    assert budget.estimate_reconstruct(16, 64, 64, 3).memory_bytes > budget.estimate_reconstruct(16, 64, 64).memory_bytes
    budget.check_budget(small, available=2**40)
    with pytest.raises(HbisInputError, match=r"would need about 38\.\d GiB .* give --force") as info:
        budget.check_budget(big, available=8 * 2**30)
    assert "\n" not in str(info.value)
    budget.check_budget(big, force=True, available=8 * 2**30)  # --force: a warning, no refusal


def test_available_memory_is_read():
    assert budget.available_memory_bytes() is None or budget.available_memory_bytes() > 2**20


@pytest.mark.parametrize("command", [
    ["simulate", "--scene", "flat", "--h", "2", "--roi", "600,400,16,12", "--out", "{tmp}/s.tif"],
    ["reconstruct", "{stack}", "--registration", "optics", "--out", "{tmp}/r.tif"],
])
def test_a_job_over_the_budget_is_refused_unless_forced(command, tmp_path, capsys, monkeypatch, caplog):
    import logging

    stack = tmp_path / "stack.tif"
    assert main(["simulate", "--scene", "flat", "--h", "2", "--roi", "600,400,16,12", "--out", str(stack), "-q"]) == 0
    argv = [a.format(tmp=tmp_path, stack=stack) for a in command]
    out = tmp_path / ("s.tif" if command[0] == "simulate" else "r.tif")
    monkeypatch.setattr(budget, "available_memory_bytes", lambda: 2**20)  # a machine with 1 MiB free
    capsys.readouterr()
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "give --force to run it anyway" in err and not out.exists(), err
    with caplog.at_level(logging.INFO, logger="hbis_torch"):
        assert main([*argv, "--force", "-v"]) == 0
    assert "estimated peak memory" in caplog.text and "running anyway (--force)" in caplog.text and out.exists()


def test_assemble_is_estimated_from_the_frame_headers(tmp_path, capsys, monkeypatch):
    import numpy as np
    import tifffile
    from test_capture_assemble import write_phases

    write_phases(tmp_path / "phases.json")
    paths = []
    for k, frame in enumerate(np.zeros((4, 20, 24), np.uint16)):
        paths.append(str(tmp_path / f"f{k}.tif"))
        tifffile.imwrite(paths[-1], frame)
    argv = ["assemble", "--phases", str(tmp_path / "phases.json"), "--roi", "600,450,24,20",
            "--out", str(tmp_path / "s.tif"), *paths]
    monkeypatch.setattr(budget, "available_memory_bytes", lambda: 2**20)
    assert main(argv) == 2
    assert "assembling 0 MiB of frames would need about" in capsys.readouterr().err
    assert not (tmp_path / "s.tif").exists()
    assert main([*argv, "--force"]) == 0 and (tmp_path / "s.tif").exists()


def test_a_burst_is_estimated_by_its_own_path():
    """A 16-frame 12 MP burst peaks at about 4 GiB through the hbis program (5.5 in colour:
    benchmarks/results/bench_burst_budget.json); the scan stack's terms put it at 45 GiB, past a
    24 GB machine. The burst's estimate stays near what was measured and grows with what grows the
    work."""
    GiB = 2**30
    grey = budget.estimate_reconstruct_burst(16, 4000, 3000, 1, 2)
    rgb = budget.estimate_reconstruct_burst(16, 4000, 3000, 3, 2)
    assert 3 * GiB < grey.memory_bytes < 6 * GiB < rgb.memory_bytes < 9 * GiB
    assert budget.estimate_reconstruct(16, 4000, 3000).memory_bytes > 40 * GiB  # what it was estimated by
    # the output's share: at S = 4 it peaks 2.4 times as high as at S = 2 (no lattice fit at either)
    assert budget.estimate_reconstruct_burst(16, 4000, 3000, 1, 4).memory_bytes > 2.2 * grey.memory_bytes
    vga = budget.estimate_reconstruct_burst(16, 640, 480)
    assert 0.5 * GiB < vga.memory_bytes < budget.estimate_reconstruct_burst(16, 640, 480, scale=4).memory_bytes
    learned = budget.estimate_reconstruct_burst(16, 640, 480, method="learned")
    assert learned.memory_bytes > vga.memory_bytes and learned.seconds > vga.seconds
    assemble = budget.estimate_assemble_burst(16 * 4000 * 3000 * 2, 16 * 4000 * 3000)
    assert 2 * GiB < assemble.memory_bytes < 4 * GiB
    # a raw burst of 12 MP mosaics: an RGB output of 8000 x 6000, joint (5.0 GiB measured:
    # benchmarks/results/bench_burst_budget_raw.json), above the grey burst's own terms
    raw = budget.estimate_reconstruct_burst(16, 4000, 3000, 1, 2, raw=True)
    assert grey.memory_bytes < raw.memory_bytes and 4.5 * GiB < raw.memory_bytes < 7 * GiB


def test_burst_commands_are_refused_before_any_work_and_run_with_force(tmp_path, capsys, monkeypatch, caplog):
    import logging

    import tifffile
    from test_burst import _burst

    tifffile.imwrite(tmp_path / "frames.tif", _burst(count=4).frames, photometric="minisblack")
    stack, out = tmp_path / "burst.tif", tmp_path / "sr.tif"
    assemble = ["assemble", "--burst", "--scale", "2", "--out", str(stack), str(tmp_path / "frames.tif")]
    reconstruct = ["reconstruct", str(stack), "--method", "classical", "--out", str(out)]
    monkeypatch.setattr(budget, "available_memory_bytes", lambda: 2**20)
    assert main(["-q", *assemble]) == 2 and not stack.exists()
    assert "assembling a burst of 0 MiB of frames would need about" in capsys.readouterr().err
    assert main(["-q", *assemble, "--force"]) == 0 and stack.exists()
    assert main(["-q", *reconstruct]) == 2 and not out.exists()
    assert "reconstructing a burst of 4 frames of 40 x 40 px at S = 2 would need" in capsys.readouterr().err
    with caplog.at_level(logging.INFO, logger="hbis_torch"):
        assert main([*reconstruct, "--force", "-v"]) == 0 and out.exists()
    assert "running anyway (--force)" in caplog.text


def test_a_raw_burst_is_refused_from_its_headers_before_any_frame_is_read(tmp_path, capsys, monkeypatch):
    pytest.importorskip("rawpy")
    pytest.importorskip("pidng")
    pytest.importorskip("cv2")
    from dng_bursts import write_dng_burst

    from hbis_torch.capture import raw as raw_module

    frames = write_dng_burst(tmp_path, size=64)
    stack, out = tmp_path / "burst.tif", tmp_path / "sr.tif"
    assemble = ["-q", "assemble", "--burst", "--scale", "2", "--out", str(stack), *frames]
    monkeypatch.setattr(budget, "available_memory_bytes", lambda: 2**20)
    read = raw_module.read_raw
    monkeypatch.setattr(raw_module, "read_raw", lambda path: pytest.fail("a frame was read"))
    assert main(assemble) == 2 and not stack.exists()
    assert "assembling a burst of 0 MiB of frames would need about" in capsys.readouterr().err
    monkeypatch.setattr(raw_module, "read_raw", read)
    assert main([*assemble, "--force"]) == 0 and stack.exists()
    assert main(["-q", "reconstruct", str(stack), "--out", str(out)]) == 2 and not out.exists()
    assert "reconstructing a raw burst of 4 frames of 64 x 64 px at S = 2 would need" in capsys.readouterr().err
