"""Lens calibrations: from a system file's ``[calibration]`` table or from OpenCV's own files.

OpenCV's calibration tools (``cv2.calibrateCamera`` and the ``calibration`` sample) save the camera
matrix and the distortion coefficients with ``cv2.FileStorage`` as YAML, XML or JSON, under names
such as ``camera_matrix`` / ``distortion_coefficients`` (the sample), ``K`` / ``D``, or
``cameraMatrix`` / ``distCoeffs``; ``image_width`` / ``image_height`` give the image size. Reading
them needs OpenCV (the ``camera`` extra).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from hbis_torch.config import LensCalibration
from hbis_torch.errors import HbisInputError

MATRIX_NAMES = ("camera_matrix", "cameraMatrix", "K", "camera_matrix_K", "intrinsics", "M")
DISTORTION_NAMES = ("distortion_coefficients", "dist_coeffs", "distCoeffs", "D", "distortion", "dist")
_KEYS = ("K", "distortion", "image_size", "opencv")


def calibration_from_arrays(matrix, distortion, image_size=None, where: str = "calibration") -> LensCalibration:
    """A LensCalibration from a 3 x 3 camera matrix K and OpenCV's distortion coefficients."""
    try:
        K = np.asarray(matrix, dtype=np.float64)
        d = np.asarray(distortion if distortion is not None else [], dtype=np.float64).ravel()
    except (TypeError, ValueError):
        raise HbisInputError(f"{where}: K and distortion must be numbers") from None
    if K.shape != (3, 3):
        raise HbisInputError(f"{where}: K must be a 3 x 3 matrix, got shape {K.shape}")
    if not np.isfinite(K).all() or abs(K[2, 2] - 1) > 1e-9 or np.abs(K[[1, 2, 2], [0, 0, 1]]).max() > 1e-9:
        raise HbisInputError(f"{where}: K must be [[fx, s, cx], [0, fy, cy], [0, 0, 1]]")
    if abs(K[0, 1]) > 1e-9:
        raise HbisInputError(f"{where}: K has a skew term ({K[0, 1]:g}); hbis-torch models square-axis sensors")
    try:
        return LensCalibration(float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]),
                               tuple(d.tolist()), tuple(image_size) if image_size is not None else None)
    except HbisInputError as exc:
        raise HbisInputError(f"{where}: {exc}") from None


def read_opencv_calibration(path) -> LensCalibration:
    """Read the YAML, XML or JSON that ``cv2.FileStorage`` wrote for a calibrated camera."""
    from hbis_torch.optional import import_cv2

    path = Path(path)
    if not path.is_file():
        raise HbisInputError(f"{path}: no such file")
    cv2 = import_cv2(f"reading the OpenCV calibration {path}")
    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except cv2.error as exc:
        raise HbisInputError(f"{path}: OpenCV cannot parse it ({str(exc).strip().splitlines()[-1]})") from None
    try:
        if not fs.isOpened():
            raise HbisInputError(f"{path}: OpenCV cannot open it as a FileStorage file (YAML, XML or JSON)")

        def first(names):
            for name in names:
                node = fs.getNode(name)
                if not node.empty():
                    return node
            return None

        k_node, d_node = first(MATRIX_NAMES), first(DISTORTION_NAMES)
        if k_node is None:
            raise HbisInputError(f"{path}: no camera matrix (looked for {', '.join(MATRIX_NAMES)})")
        matrix = k_node.mat()
        distortion = d_node.mat() if d_node is not None else None
        if distortion is None and d_node is not None and d_node.isSeq():
            distortion = [d_node.at(i).real() for i in range(d_node.size())]
        w, h = fs.getNode("image_width"), fs.getNode("image_height")
        size = (int(w.real()), int(h.real())) if not w.empty() and not h.empty() else None
    finally:
        fs.release()
    return calibration_from_arrays(matrix, distortion, size, str(path))


def calibration_from_mapping(data, path) -> LensCalibration:
    """The ``[calibration]`` table of a system file: ``K`` + ``distortion`` (+ ``image_size``
    [cols, rows]), or ``opencv`` = an OpenCV FileStorage file (relative to the system file)."""
    where = f"{path}: calibration"
    if not isinstance(data, dict):
        raise HbisInputError(f"{where} must be a table/object")
    unknown = sorted(set(data) - set(_KEYS))
    if unknown:
        raise HbisInputError(f"{where}: unknown key(s) {', '.join(unknown)} (known: {', '.join(_KEYS)})")
    if "opencv" in data:
        if "K" in data:
            raise HbisInputError(f"{where}: give either K and distortion or opencv, not both")
        return read_opencv_calibration(Path(path).parent / str(data["opencv"]))
    if "K" not in data:
        raise HbisInputError(f"{where}: needs K (3 x 3) and distortion, or opencv = \"FILE\"")
    return calibration_from_arrays(data["K"], data.get("distortion"), data.get("image_size"), where)
