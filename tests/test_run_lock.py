"""One run per output folder: the lock, a killed run's leftovers, workers that end with their launcher."""

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from hbis_torch.errors import HbisInputError
from hbis_torch.io_utils import atomic_path
from hbis_torch.run_lock import lock_dir, remove_temp_files

REPO = Path(__file__).resolve().parents[1]
ENV = {**os.environ, "PYTHONPATH": str(REPO)}


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    # a zombie still answers kill(0): look at its state
    try:
        return Path(f"/proc/{pid}/stat").read_text().split()[2] != "Z"
    except OSError:
        return False


def test_a_second_run_is_refused_and_a_killed_runs_lock_is_not_in_the_way(tmp_path):
    holder = subprocess.Popen(
        [sys.executable, "-c", "import sys, time; from hbis_torch.run_lock import lock_dir; "
         "h = lock_dir(sys.argv[1]); print('locked', flush=True); time.sleep(60)", str(tmp_path)],
        stdout=subprocess.PIPE, text=True, env=ENV)
    try:
        assert holder.stdout.readline().strip() == "locked"
        with pytest.raises(HbisInputError, match=f"in use by a run that is still going .pid {holder.pid}"):
            lock_dir(tmp_path)
    finally:
        holder.kill()  # SIGKILL: no clean-up of its own
        holder.wait()
    handle = lock_dir(tmp_path)  # the kernel released the dead run's lock
    assert (tmp_path / ".lock").read_text().strip() == str(os.getpid())
    handle.close()


def test_temporary_files_of_a_killed_write_are_removed(tmp_path):
    with pytest.raises(KeyboardInterrupt), atomic_path(tmp_path / "val_psnr.png") as tmp:
        tmp.write_bytes(b"half")
        os.link(tmp, tmp_path / ".val_psnr.png.abc123.tmp")  # what a SIGKILL would leave
        raise KeyboardInterrupt
    (tmp_path / "keep.png").write_bytes(b"x")
    removed = remove_temp_files(tmp_path)
    assert [p.name for p in removed] == [".val_psnr.png.abc123.tmp"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["keep.png"]


def test_a_worker_ends_when_its_launcher_is_killed(tmp_path):
    launcher = subprocess.Popen(
        [sys.executable, "-c",
         "import subprocess, sys, time\n"
         "child = subprocess.Popen([sys.executable, '-c', 'import time; from hbis_torch.run_lock import "
         "exit_with_parent; exit_with_parent(0.2); print(1, flush=True); time.sleep(60)'], stdout=subprocess.PIPE, text=True)\n"
         "child.stdout.readline()\n"
         "print(child.pid, flush=True)\n"
         "time.sleep(60)\n"],
        stdout=subprocess.PIPE, text=True, env=ENV)
    worker = int(launcher.stdout.readline())
    assert _alive(worker)
    launcher.send_signal(signal.SIGKILL)
    launcher.wait()
    deadline = time.monotonic() + 5
    while _alive(worker) and time.monotonic() < deadline:
        time.sleep(0.05)
    alive = _alive(worker)
    if alive:
        os.kill(worker, signal.SIGKILL)
    assert not alive, "the worker outlived its launcher"
