"""The system file: camera, prisms, object distance and lens calibration in one JSON or TOML file.

TOML example (JSON holds the same keys)::

    object_distance_mm = 50.0

    [camera]
    pixel_pitch_um = 3.75
    rows = 960
    cols = 1280
    focal_length_mm = 12.0
    f_number = 1.4
    wavelength_nm = 550.0

    [prisms]
    wedge_angle_deg = 4.0
    refractive_index = 1.5

    [calibration]              # optional: OpenCV's pinhole model of the real lens
    K = [[3205.1, 0.0, 641.3], [0.0, 3204.7, 478.9], [0.0, 0.0, 1.0]]
    distortion = [-0.12, 0.05, 0.0003, -0.0002, 0.0]
    # or: opencv = "calib.yml"  (what cv2.FileStorage wrote; relative to this file)

Missing keys take the paper's Table 1 values. Unknown keys are refused (a typo must not pass
silently).
"""

from __future__ import annotations

import logging
import math
from pathlib import Path

from hbis_torch.config import Camera, FoveaSystem, Prisms
from hbis_torch.errors import HbisInputError
from hbis_torch.io_utils import load_json

log = logging.getLogger(__name__)
MAX_SYSTEM_FILE_BYTES = 1 << 20
"""A system file is a few hundred bytes; anything over 1 MiB is refused before it is parsed."""
OFF_CENTRE_WARNING = 0.05
"""Warn when a calibration without an image size puts the principal point farther than this
fraction of the sensor's diagonal from its centre (likely a calibration of another camera or
binning)."""

_CAMERA = ("pixel_pitch_um", "rows", "cols", "focal_length_mm", "f_number", "wavelength_nm")
_PRISMS = ("wedge_angle_deg", "refractive_index")


def _load_mapping(path: Path) -> dict:
    try:
        if path.stat().st_size > MAX_SYSTEM_FILE_BYTES:
            raise HbisInputError(f"{path}: {path.stat().st_size} bytes, more than a system file holds "
                                 f"({MAX_SYSTEM_FILE_BYTES} at most)")
        text = path.read_bytes()
    except FileNotFoundError:
        raise HbisInputError(f"{path}: no such file") from None
    except OSError as exc:
        raise HbisInputError(f"{path}: cannot be read ({exc.strerror})") from None
    if path.suffix.lower() != ".toml":
        data = load_json(text, str(path))  # hostile-safe: huge integers, deep nesting, duplicate keys
    else:
        try:
            import tomllib

            data = tomllib.loads(text.decode("utf-8"))
        except (ValueError, UnicodeDecodeError, RecursionError) as exc:
            raise HbisInputError(f"{path}: not valid TOML ({(str(exc).splitlines() or [''])[0]})") from None
    if not isinstance(data, dict):
        raise HbisInputError(f"{path}: a system file holds one object (camera, prisms, object_distance_mm)")
    return data


def _block(data: dict, key: str, allowed, path) -> dict:
    block = data.get(key, {})
    if not isinstance(block, dict):
        raise HbisInputError(f"{path}: [{key}] must be a table/object")
    unknown = sorted(set(block) - set(allowed))
    if unknown:
        raise HbisInputError(f"{path}: unknown key(s) {', '.join(key + '.' + k for k in unknown)} "
                             f"(known: {', '.join(allowed)})")
    return block


def load_system(path) -> FoveaSystem:
    """The FoveaSystem a JSON (``.json``) or TOML (``.toml``) system file describes."""
    path = Path(path)
    data = _load_mapping(path)
    unknown = sorted(set(data) - {"camera", "prisms", "object_distance_mm", "calibration"})
    if unknown:
        raise HbisInputError(f"{path}: unknown key(s) {', '.join(unknown)} "
                             "(known: camera, prisms, object_distance_mm, calibration)")
    cam = _block(data, "camera", _CAMERA, path)
    pr = _block(data, "prisms", _PRISMS, path)
    try:
        camera = Camera(**cam)
        prisms = Prisms(**pr)
        system = FoveaSystem(camera, prisms, float(data.get("object_distance_mm", FoveaSystem().object_distance_mm)))
    except (HbisInputError, TypeError, ValueError) as exc:
        raise HbisInputError(f"{path}: {exc}") from None
    if "calibration" in data:
        from hbis_torch.capture.lens import calibration_from_mapping

        calibration = calibration_from_mapping(data["calibration"], path)
        system = with_lens(system, calibration, str(path))
    return system


def with_lens(system: FoveaSystem, calibration, where: str) -> FoveaSystem:
    """``system`` with its camera's lens calibration replaced (checked against the sensor size)."""
    from dataclasses import replace

    cam = system.camera
    if calibration is not None and calibration.image_size is not None:
        cols, rows = calibration.image_size
        if (rows, cols) != (cam.rows, cam.cols):
            raise HbisInputError(f"{where}: the calibration is for a {cols} x {rows} sensor but the camera has "
                                 f"{cam.cols} x {cam.rows} pixels: a calibration of another camera or binning")
    elif calibration is not None:
        off = principal_point_offset(calibration, cam.cols, cam.rows)
        if off > OFF_CENTRE_WARNING * math.hypot(cam.cols, cam.rows):
            log.warning("%s: the calibration records no image size and its principal point (%.1f, %.1f) lies "
                        "%.0f px from the centre of the %d x %d sensor: is it a calibration of this camera at "
                        "this resolution?", where, calibration.cx, calibration.cy, off, cam.cols, cam.rows)
    try:
        return replace(system, camera=replace(system.camera, lens=calibration))
    except HbisInputError as exc:
        raise HbisInputError(f"{where}: {exc}") from None


def principal_point_offset(calibration, cols: int, rows: int) -> float:
    """Distance in pixels from the calibration's principal point to the centre of a ``cols`` x
    ``rows`` sensor (pixel centres 0-based, as OpenCV counts them)."""
    return math.hypot(calibration.cx - (cols - 1) / 2, calibration.cy - (rows - 1) / 2)
