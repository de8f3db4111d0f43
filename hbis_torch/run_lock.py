"""One run per output folder: a lock, the clean-up of what a killed run left, and workers that
end with their launcher.

* :func:`lock_dir` takes an exclusive ``flock`` on ``DIR/.lock`` (holding the pid of the holder,
  for the message). The kernel releases it when the process ends in any way, SIGKILL included, so
  a lock left by a killed run is never in the way; a second live run on the same folder is
  refused in one line.
* :func:`remove_temp_files` deletes the ``.NAME.*.tmp`` files that :func:`~hbis_torch.io_utils.atomic_path`
  leaves when a run is killed between creating and renaming one (call it with the lock held).
* :func:`exit_with_parent` makes a worker end when the process that launched it dies (torchrun's
  launcher killed with SIGKILL cannot stop its workers itself): on Linux the kernel sends the
  worker SIGTERM (``PR_SET_PDEATHSIG``); elsewhere a thread watches the parent's pid.
"""

from __future__ import annotations

import os
import signal
import sys
import threading
import time
from pathlib import Path

from hbis_torch.errors import HbisInputError

LOCK_NAME = ".lock"


def _holder(path: Path) -> str:
    try:
        text = path.read_text().strip()
    except OSError:
        text = ""
    return f"pid {text}" if text.isdigit() else "another process"


def lock_dir(directory):
    """Lock ``directory`` (created if missing) for this process; return the open lock file.

    Keep the returned file object alive (and open) for as long as the run writes into the
    folder; closing it, or the process ending, releases the lock.

    Raises
    ------
    HbisInputError
        If another live process holds the lock (the message names its pid).
    """
    import fcntl

    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    path = directory / LOCK_NAME
    handle = open(path, "a+")  # noqa: SIM115 - held open for the run's lifetime
    try:
        fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        handle.close()
        raise HbisInputError(f"{directory} is in use by a run that is still going ({_holder(path)}); "
                             "wait for it, stop it, or choose another output folder") from None
    handle.seek(0)
    handle.truncate()
    handle.write(f"{os.getpid()}\n")
    handle.flush()
    return handle


def remove_temp_files(directory) -> list[Path]:
    """Delete the temporary files of atomic writes (``.*.tmp``) in ``directory``; return them.

    Only call this while holding :func:`lock_dir`'s lock: a live run's temporary file would go too.
    """
    removed = []
    for tmp in Path(directory).glob(".*.tmp"):
        if tmp.is_file():
            tmp.unlink(missing_ok=True)
            removed.append(tmp)
    return removed


def _pdeathsig(sig: int) -> bool:
    """Ask Linux to send ``sig`` to this process when its parent dies; False where unsupported."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        PR_SET_PDEATHSIG = 1
        return libc.prctl(PR_SET_PDEATHSIG, int(sig), 0, 0, 0) == 0
    except (OSError, AttributeError):
        return False


def exit_with_parent(poll_s: float = 1.0) -> None:
    """End this process (SIGTERM to itself) when its parent process dies.

    Meant for workers started by a launcher (torchrun): if the launcher is killed outright, the
    workers would otherwise run on, orphaned. Uses ``PR_SET_PDEATHSIG`` on Linux and, in any case,
    a daemon thread that checks every ``poll_s`` seconds whether the parent has changed.
    """
    parent = os.getppid()
    _pdeathsig(signal.SIGTERM)
    if os.getppid() != parent:  # the parent died before the request took effect
        os.kill(os.getpid(), signal.SIGTERM)

    def watch() -> None:
        while True:
            time.sleep(poll_s)
            if os.getppid() != parent:
                os.kill(os.getpid(), signal.SIGTERM)
                return

    threading.Thread(target=watch, name="exit-with-parent", daemon=True).start()
