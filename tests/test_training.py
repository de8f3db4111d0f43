"""The training script: two processes under torchrun (DDP, gloo), and resume after a kill."""

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

REPO = Path(__file__).resolve().parents[1]
SCRIPT = REPO / "training" / "train_sr.py"
TINY = ["h=2", "width=8", "blocks=1", "patch=12", "batch_size=2", "pool_size=3", "pool_roi=16",
        "val_size=2", "val_roi=16", "progress_bar=False", "max_minutes=1000.0"]


def run(args, out_dir, procs=1, **kw):
    if procs == 1:
        cmd = [sys.executable, str(SCRIPT)]
    else:
        torchrun = shutil.which("torchrun")
        if torchrun is None:
            pytest.skip("torchrun is not on PATH")
        cmd = [torchrun, "--standalone", f"--nproc_per_node={procs}", str(SCRIPT)]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    cache = Path(out_dir).parent / "cache"
    return subprocess.run(cmd + TINY + args + [f"out_dir={out_dir}", f"cache_dir={cache}"], cwd=REPO, env=env,
                          capture_output=True, text=True, timeout=120, **kw)


def history(out_dir):
    return json.loads((Path(out_dir) / "history.json").read_text())["history"]


def test_two_processes_under_torchrun(tmp_path):
    result = run(["max_steps=4", "eval_interval=2"], tmp_path, procs=2)
    # The workers' own lines come first, torchrun's summary of the failure last.
    assert result.returncode == 0, result.stderr[:1500] + "\n...\n" + result.stderr[-500:]
    assert "2 process(es)" in result.stdout
    steps = [r["step"] for r in history(tmp_path)]
    assert steps == [0, 2, 4]
    ckpt = torch.load(tmp_path / "ckpt.pt", weights_only=True)
    assert ckpt["step"] == 4 and (tmp_path / "val_psnr.png").stat().st_size > 1000
    assert all(torch.isfinite(v).all() for v in ckpt["model"].values())


def test_resume_after_a_kill_reproduces_the_uninterrupted_run(tmp_path):
    steps = ["max_steps=8", "eval_interval=2"]
    straight = tmp_path / "straight"
    assert run(steps, straight).returncode == 0
    killed = tmp_path / "killed"
    cmd = [sys.executable, str(SCRIPT)] + TINY + steps + [f"out_dir={killed}", f"cache_dir={tmp_path / 'cache'}"]
    proc = subprocess.Popen(cmd, cwd=REPO, env={**os.environ, "OMP_NUM_THREADS": "1"},
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 90
    while time.monotonic() < deadline and proc.poll() is None:
        if (killed / "history.json").exists() and history(killed)[-1]["step"] >= 2:
            break
        time.sleep(0.05)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    stopped_at = torch.load(killed / "ckpt.pt", weights_only=True)["step"]
    resumed = run(steps, killed)
    assert resumed.returncode == 0, resumed.stderr[-2000:]
    if stopped_at < 8:
        assert f"resumed from {killed / 'ckpt.pt'} at step {stopped_at}" in resumed.stdout
    a = torch.load(straight / "ckpt.pt", weights_only=True)["model"]
    b = torch.load(killed / "ckpt.pt", weights_only=True)["model"]
    for name in a:
        torch.testing.assert_close(a[name], b[name], rtol=0, atol=1e-6)
    assert [r["step"] for r in history(killed)] == [0, 2, 4, 6, 8]


def test_unknown_override_is_refused(tmp_path):
    result = run(["learning_rat=1"], tmp_path)
    assert result.returncode != 0 and "unknown or malformed override" in result.stderr


def test_device_flag_and_growth_from_a_smaller_network(tmp_path):
    """``--device cpu`` (the flag form), a network grown from a shipped one (it starts at that
    network's validation PSNR, above the classical image's), pools over 2 processes, prefetch."""
    result = run(["--device", "cpu", "width=40", "blocks=5", "max_steps=2", "eval_interval=2",
                  "pool_workers=2", "prefetch=2", f"init_from={REPO / 'hbis_torch/models/hbis_sr_h2.pt'}"],
                 tmp_path / "grown")
    assert result.returncode == 0, result.stderr[-2000:]
    assert "on cpu" in result.stdout and "grown from" in result.stdout
    first = history(tmp_path / "grown")[0]
    assert first["step"] == 0 and first["val_psnr"] > first["base_psnr"] + 0.1


def test_cuda_without_a_gpu_is_refused(tmp_path):
    if torch.cuda.is_available():
        pytest.skip("a GPU is visible")
    result = run(["--device", "cuda", "max_steps=1"], tmp_path / "x")
    assert result.returncode != 0 and "torch sees no GPU" in result.stderr
