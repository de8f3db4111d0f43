"""Up-front estimates of a job's peak memory and time, and the refusal of one the machine cannot
hold (``--force`` runs it anyway).

The estimates are linear in the work: frames x pixels per frame (N), on top of the libraries'
own footprint. Their coefficients were measured with ``/usr/bin/time`` on the project's 2-core
development machine, under load (so the times are on the slow side):

- ``hbis simulate --scene flat --h {4,8} --roi ...128,128`` and ``--h 4 --roi ...256,256``:
  about 130 bytes and 1.3e-5 s per frame pixel, plus about 250 MiB and 10 s;
- ``hbis reconstruct`` (classical and learned) of the h = 4, 256 x 256 stack: about 250 bytes and
  3e-5 s per frame pixel, plus about 300 MiB.

A burst stack (``hbis assemble --burst``) goes through a path of its own, which streams its frames
and, at large sizes, never holds every sample's position: its estimates
(:func:`estimate_assemble_burst`, :func:`estimate_reconstruct_burst`) have terms of their own,
measured with ``benchmarks/bench_burst_budget.py`` (the hbis program on 16-frame bursts of
640 x 480 and 4000 x 3000 px, grey and RGB, at S = 2 and 4), which prints each estimate beside
the peak and the seconds it measured. (The scan stack's 250 bytes per frame pixel had put a 16-frame
12 MP burst at 45 GiB, 134 GiB in colour, where the program peaks at about 4 and 5.5 GiB: refused
on a machine of 24 GB.)

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


# A burst's reconstruct (bytes, seconds; F x H x W frame pixels, S^2 x H x W output pixels per channel):
# the libraries; per frame pixel (the frames and their weights in float32, a piece of positions at
# a time); per frame pixel where the lattice's batches are kept for the splat's second pass (bursts
# of up to hbis_torch.reconstruct.classical.sr.KEEP_SAMPLES samples); per frame pixel of each
# channel beyond the first; per output pixel (the lattice's sums, the image, the Wiener filter's
# spectra); per output pixel more where the lattice's holes are fitted (up to
# hbis_torch.reconstruct.classical.lattice_fit.MAX_FIT_NODES nodes: its normal equations); the
# learned method's own (the adaptation's window and the network's tiles, and its output).
_BURST_BASE = (300 * MiB, 2.0)
_BURST_PER_FRAME_PIXEL = (10, 0.8e-7)
_BURST_KEPT_PER_FRAME_PIXEL = 24
_BURST_PER_EXTRA_CHANNEL_PIXEL = (6, 0.4e-7)
_BURST_PER_OUTPUT_PIXEL = (42, 4e-7)  # (seconds: per output pixel of each channel)
_BURST_FITTED_PER_OUTPUT_PIXEL = 103
_BURST_LEARNED = (100 * MiB, 8)  # bytes, and bytes per output pixel and channel; its time: 1.5 x + 2 s
# A raw burst's joint demosaicking (per output pixel of the RGB image: each colour's sums, its
# plane in float64, the finished planes and the output in float32, the holes' whole-image blurs),
# in place of the output's terms above (it fits no holes).
_RAW_BURST_PER_OUTPUT_PIXEL = (80, 1.0e-6)
# A burst's assemble: the libraries; per frame pixel its float32 frames, their luminance and the
# registration's pyramids; per byte of the frames as decoded (bytes, seconds: decoding them).
_ASSEMBLE_BURST = (300 * MiB, 2.0)
_ASSEMBLE_BURST_PER_FRAME_PIXEL = (12.5, 6e-8)
_ASSEMBLE_BURST_PER_DECODED_BYTE = (1, 1e-8)


def estimate_reconstruct_burst(frames: int, width: int, height: int, channels: int = 1, scale: int = 2,
                               method: str = "classical", raw: bool = False) -> Estimate:
    """``hbis reconstruct`` of a burst stack of ``frames`` frames of ``width`` x ``height`` px
    (x ``channels``) at scale ``scale``, by ``method`` (the learned method adds its network's
    share; any other method is estimated as the classical one). ``raw``: a raw burst (one
    channel, a Bayer mosaic), which every method demosaicks jointly into RGB."""
    from hbis_torch.reconstruct.classical.lattice_fit import MAX_FIT_NODES
    from hbis_torch.reconstruct.classical.sr import KEEP_SAMPLES

    samples, nodes = frames * width * height, scale * scale * width * height
    memory, seconds = _BURST_BASE
    memory += samples * (_BURST_PER_FRAME_PIXEL[0] + (_BURST_KEPT_PER_FRAME_PIXEL if samples <= KEEP_SAMPLES else 0)
                         + (channels - 1) * _BURST_PER_EXTRA_CHANNEL_PIXEL[0])
    seconds += samples * (_BURST_PER_FRAME_PIXEL[1] + (channels - 1) * _BURST_PER_EXTRA_CHANNEL_PIXEL[1])
    if raw:
        memory += nodes * _RAW_BURST_PER_OUTPUT_PIXEL[0]
        seconds += nodes * _RAW_BURST_PER_OUTPUT_PIXEL[1]
        return Estimate(f"reconstructing a raw burst of {frames} frames of {width} x {height} px at S = {scale}",
                        int(memory), seconds)
    memory += nodes * (_BURST_PER_OUTPUT_PIXEL[0] + (_BURST_FITTED_PER_OUTPUT_PIXEL if nodes <= MAX_FIT_NODES else 0))
    seconds += nodes * channels * _BURST_PER_OUTPUT_PIXEL[1]
    if method == "learned":
        memory += _BURST_LEARNED[0] + _BURST_LEARNED[1] * nodes * channels
        seconds = 1.5 * seconds + 2.0
    colour = " (RGB)" if channels == 3 else ""
    return Estimate(f"reconstructing a burst of {frames} frames of {width} x {height} px{colour} at S = {scale}",
                    int(memory), seconds)


def estimate_assemble_burst(decoded_bytes: int, frame_pixels: int) -> Estimate:
    """``hbis assemble --burst``: the frames as decoded (``decoded_bytes``), and per frame pixel
    (``frame_pixels``, all frames') what the registration holds."""
    (memory, seconds), per_pixel, per_byte = (_ASSEMBLE_BURST, _ASSEMBLE_BURST_PER_FRAME_PIXEL,
                                              _ASSEMBLE_BURST_PER_DECODED_BYTE)
    return Estimate(f"assembling a burst of {decoded_bytes / MiB:.0f} MiB of frames",
                    int(memory + per_pixel[0] * frame_pixels + per_byte[0] * decoded_bytes),
                    seconds + per_pixel[1] * frame_pixels + per_byte[1] * decoded_bytes)


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
