"""Captured frames + the scan's phases file -> one ``hbis-stack/1`` stack.

Every check runs before anything is written: the frame count is h^2 and matches the phases file,
the frames share one size and dtype, the bit depth fits the dtype and the values, the ROI lies
inside the sensor and matches the frames, the phases are finite and belong to this scan, and the
calibration images (dark, flat, bad pixels) have the frames' size or the sensor's.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from hbis_torch.capture.calibration import FrameCalibration, calibrate_stack
from hbis_torch.capture.phases import ScanPhases, check_phases_for
from hbis_torch.checks import check_roi
from hbis_torch.config import FoveaSystem
from hbis_torch.errors import HbisInputError
from hbis_torch.stack_io import Stack, make_meta, validate_stack


def frames_roi(system: FoveaSystem, frame_shape, roi=None):
    """The ROI of frames of ``frame_shape`` (H, W[, 3]) and how to cut them.

    With ``roi`` None the frames must cover the whole sensor. With a ROI the frames are either of
    its size (the camera read out the ROI) or of the sensor's (the ROI is cut out of them).

    Returns
    -------
    roi : (u0, v0, width, height)
    crop : bool
        True when the frames are full-sensor and must be cut to ``roi``.
    """
    cam = system.camera
    height, width = frame_shape[:2]
    if roi is None:
        if (height, width) != (cam.rows, cam.cols):
            raise HbisInputError(f"the frames are {width} x {height} pixels but the sensor is {cam.cols} x {cam.rows}: "
                                 "give --roi U0,V0,W,H (where the frames sit on the sensor) or the sensor's --rows/--cols")
        return (0, 0, cam.cols, cam.rows), False
    roi = check_roi(cam, roi)
    if (height, width) == (roi[3], roi[2]):
        return roi, False
    if (height, width) == (cam.rows, cam.cols):
        return roi, True
    raise HbisInputError(f"the frames are {width} x {height} pixels, neither the ROI's {roi[2]} x {roi[3]} "
                         f"nor the sensor's {cam.cols} x {cam.rows}")


def assemble_stack(
    frames: np.ndarray,
    scan: ScanPhases,
    system: FoveaSystem,
    roi=None,
    bit_depth: int | None = None,
    black_level: float | None = None,
    calibration: FrameCalibration | None = None,
    cfa: str | None = None,
    **extra,
) -> Stack:
    """Build and validate the stack of a captured scan.

    Parameters
    ----------
    frames : np.ndarray, shape (F, H, W) or (F, H, W, 3)
        uint8, uint16 or float32 (in [0, 1]), in scan order.
    scan : ScanPhases
        The phases file of the scan: its read-back phases become ``phases_deg``, its h and
        ``reference_index`` are kept.
    system : FoveaSystem
    roi : (u0, v0, width, height) or None
        Where the frames sit on the sensor (see :func:`frames_roi`).
    bit_depth : int or None
        Significant bits of integer frames (default: the dtype's 8 or 16).
    black_level : float or None
        Digital number of black (stored when given).
    calibration : FrameCalibration or None
        Dark, flat and bad pixels; when given the stack holds corrected float32 frames.
    cfa : str or None
        Bayer pattern of raw colour frames ("RGGB", "BGGR", "GRBG", "GBRG"), stored as ``cfa``.
    **extra
        Further keys for the stack's JSON.

    Returns
    -------
    Stack
    """
    frames = np.asarray(frames)
    if frames.ndim not in (3, 4) or len(frames) == 0:
        raise HbisInputError(f"frames must have shape (F, H, W) or (F, H, W, 3), got {frames.shape}")
    check_phases_for(scan, system, len(frames))
    roi, crop = frames_roi(system, frames.shape[1:], roi)
    if crop:
        u0, v0, width, height = roi
        frames = frames[:, v0:v0 + height, u0:u0 + width]
    if bit_depth is not None:
        if frames.dtype == np.float32:
            raise HbisInputError("--bit-depth is for integer frames; these are float32")
        container = frames.dtype.itemsize * 8
        if isinstance(bit_depth, bool) or not 1 <= int(bit_depth) <= container:
            raise HbisInputError(f"bit depth {bit_depth} does not fit {frames.dtype} frames (1..{container})")
    if frames.dtype != np.float32 and frames.size:
        white = 2 ** (bit_depth or frames.dtype.itemsize * 8) - 1
        top = int(frames.max())
        if top > white:
            raise HbisInputError(f"pixel values reach {top}, more than {bit_depth} bits hold (largest {white}): "
                                 "give the camera's real --bit-depth")
    if black_level is not None:
        extra["black_level"] = float(black_level)
    if cfa is not None:
        extra["cfa"] = cfa
    meta = make_meta(system, scan.h, roi, scan.phases_deg, bit_depth=bit_depth,
                     reference_index=scan.reference_index,
                     capture={"phases_file": Path(scan.path).name, "targets_deg": scan.targets_deg.tolist()},
                     **extra)
    frames = np.ascontiguousarray(frames)
    validate_stack(frames, meta, "assembled stack")
    stack = Stack(frames, meta)
    if calibration:
        stack = calibrate_stack(stack, calibration).validate("calibrated stack")
    return stack
