"""From the bench to a stack: captured frames, the scan's phases file, calibration, cameras.

* :mod:`~hbis_torch.capture.frames`: frames from files, ``{index}`` patterns, multi-page TIFFs
  and videos.
* :mod:`~hbis_torch.capture.phases`: the phases file of ``hbis motors scan --out``.
* :mod:`~hbis_torch.capture.calibration`: dark frame, flat field, bad-pixel map.
* :mod:`~hbis_torch.capture.assemble`: frames + phases -> an ``hbis-stack/1`` stack.
"""

from hbis_torch.capture.assemble import assemble_stack, frames_roi
from hbis_torch.capture.calibration import (
    FrameCalibration,
    calibrate_stack,
    load_calibration,
)
from hbis_torch.capture.frames import read_frames
from hbis_torch.capture.phases import ScanPhases, check_phases_for, read_phases

__all__ = [
    "FrameCalibration",
    "ScanPhases",
    "assemble_stack",
    "calibrate_stack",
    "check_phases_for",
    "frames_roi",
    "load_calibration",
    "read_frames",
    "read_phases",
]
