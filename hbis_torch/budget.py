"""Up-front estimates of a job's peak memory and time, and the refusal of one the machine cannot
hold (``--force`` runs it anyway).

The estimates are linear in the work: frames x pixels per frame (N), on top of the libraries'
own footprint. Their coefficients were measured with ``/usr/bin/time`` on the project's 2-core
development machine, under load (so the times are on the slow side):

- ``hbis simulate --scene flat --h {4,8} --roi ...128,128`` and ``--h 4 --roi ...256,256``:
  about 130 bytes and 1.3e-5 s per frame pixel, plus about 250 MiB and 10 s;
- ``hbis reconstruct`` (classical and learned) of the h = 4, 256 x 256 stack: about 250 bytes and
  3e-5 s per frame pixel, plus about 300 MiB.

They are meant to tell 1 GB from 40 GB before starting, not to the nearest 10 %.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass

from hbis_torch.errors import HbisInputError

log = logging.getLogger(__name__)
MiB = 2**20

# (base bytes, bytes per frame pixel, base seconds, seconds per frame pixel)
_SIMULATE = (250 * MiB, 130, 10.0, 1.3e-5)
_RECONSTRUCT = (300 * MiB, 250, 5.0, 3.0e-5)
_ASSEMBLE = (200 * MiB, 0, 2.0, 5.0e-8)  # frames: bytes as decoded, counted by the caller


@dataclass(frozen=True)
class Estimate:
    """A job's estimated peak memory (bytes) and time (seconds)."""

    what: str
    memory_bytes: int
    seconds: float

    def describe(self) -> str:
        return (f"{self.what}: estimated peak memory {self.memory_bytes / 2**30:.2f} GiB, time about "
                f"{_duration(self.seconds)} (on 2 CPU cores)")


def _duration(seconds: float) -> str:
    if seconds < 120:
        return f"{seconds:.0f} s"
    if seconds < 7200:
        return f"{seconds / 60:.0f} min"
    return f"{seconds / 3600:.1f} h"


def _linear(what: str, coefficients, pixels: float, extra_bytes: float = 0.0) -> Estimate:
    base_b, per_b, base_s, per_s = coefficients
    return Estimate(what, int(base_b + per_b * pixels + extra_bytes), base_s + per_s * (pixels + extra_bytes))


def estimate_simulate(frames: int, width: int, height: int) -> Estimate:
    """``hbis simulate``: ``frames`` (h^2) frames of ``width`` x ``height`` pixels."""
    return _linear(f"simulating {frames} frames of {width} x {height} px", _SIMULATE, frames * width * height)


def estimate_reconstruct(frames: int, width: int, height: int, channels: int = 1) -> Estimate:
    """``hbis reconstruct`` of a stack of ``frames`` frames of ``width`` x ``height`` (x channels)."""
    return _linear(f"reconstructing {frames} frames of {width} x {height} px", _RECONSTRUCT,
                   frames * width * height * channels)


def estimate_assemble(decoded_bytes: int, frame_pixels: int, calibrated: bool) -> Estimate:
    """``hbis assemble``: the frames as decoded, and with a calibration their float64 copies (x3)."""
    extra = decoded_bytes + (3 * 8 * frame_pixels if calibrated else 0)
    return _linear(f"assembling {decoded_bytes / MiB:.0f} MiB of frames", _ASSEMBLE, 0, extra)


def available_memory_bytes() -> int | None:
    """Memory the system can still give (``MemAvailable`` of /proc/meminfo; physical memory
    where that is missing; None where neither is known)."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_AVPHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        return None


def check_budget(estimate: Estimate, force: bool = False, available: int | None = None) -> None:
    """Log the estimate (``-v``) and refuse, in one line, a job whose peak memory exceeds what is
    available, unless ``force``."""
    log.info(estimate.describe())
    available = available_memory_bytes() if available is None else available
    if available is None or estimate.memory_bytes <= available:
        return
    message = (f"{estimate.what} would need about {estimate.memory_bytes / 2**30:.1f} GiB of memory at its peak "
               f"(estimate), more than the {available / 2**30:.1f} GiB available")
    if force:
        log.warning("%s; running anyway (--force)", message)
        return
    raise HbisInputError(f"{message}: make the job smaller (a smaller --roi or h) or give --force to run it anyway")


def add_force_arg(parser) -> None:
    """``--force``: run a job whose memory estimate exceeds what the machine has available."""
    parser.add_argument("--force", action="store_true",
                        help="run even when the estimated peak memory (printed with -v) exceeds the "
                        "memory available")
