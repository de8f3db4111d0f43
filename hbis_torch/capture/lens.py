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

from hbis_torch.config import MAX_SENSOR_SIDE, LensCalibration
from hbis_torch.errors import HbisInputError

MATRIX_NAMES = ("camera_matrix", "cameraMatrix", "K", "camera_matrix_K", "intrinsics", "M")
DISTORTION_NAMES = ("distortion_coefficients", "dist_coeffs", "distCoeffs", "D", "distortion", "dist")
_KEYS = ("K", "distortion", "image_size", "opencv")
MAX_CALIBRATION_BYTES = 1 << 20
"""A calibration file is a few kB; anything over 1 MiB is refused before it is parsed."""
MAX_MATRIX_SIDE = 64
"""The largest rows or cols a calibration matrix may declare (K is 3 x 3, distortion at most 1 x 14)."""
_STEREO = (("M1", "D1"), ("M2", "D2"), ("K1", "D1"), ("K2", "D2"), ("cameraMatrix1", "distCoeffs1"),
           ("cameraMatrix2", "distCoeffs2"))
# Values no real calibration has: a focal length or principal point beyond this many pixels, a
# distortion coefficient beyond this magnitude.
_MAX_PIXELS = 1e6
_MAX_DISTORTION = 1e4


def calibration_from_arrays(matrix, distortion, image_size=None, where: str = "calibration") -> LensCalibration:
    """A LensCalibration from a 3 x 3 camera matrix K and OpenCV's distortion coefficients."""
    try:
        K = np.asarray(matrix, dtype=np.float64)
        d = np.asarray(distortion if distortion is not None else [], dtype=np.float64).ravel()
    except (TypeError, ValueError, OverflowError):
        raise HbisInputError(f"{where}: K and distortion must be numbers") from None
    if K.shape != (3, 3):
        raise HbisInputError(f"{where}: K must be a 3 x 3 matrix, got shape {K.shape}")
    if not np.isfinite(K).all():
        raise HbisInputError(f"{where}: K holds a value that is not finite")
    if abs(K[2, 2] - 1) > 1e-9 or np.abs(K[[1, 2, 2], [0, 0, 1]]).max() > 1e-9:
        raise HbisInputError(f"{where}: K must be [[fx, s, cx], [0, fy, cy], [0, 0, 1]]")
    if abs(K[0, 1]) > 1e-9:
        raise HbisInputError(f"{where}: K has a skew term ({K[0, 1]:g}); hbis-torch models square-axis sensors")
    if not (0 < K[0, 0] <= _MAX_PIXELS and 0 < K[1, 1] <= _MAX_PIXELS):
        raise HbisInputError(f"{where}: focal lengths fx = {K[0, 0]:g}, fy = {K[1, 1]:g} px must lie in (0, {_MAX_PIXELS:g}]")
    if max(abs(K[0, 2]), abs(K[1, 2])) > _MAX_PIXELS:
        raise HbisInputError(f"{where}: principal point ({K[0, 2]:g}, {K[1, 2]:g}) px is absurd")
    if not np.isfinite(d).all() or (d.size and np.abs(d).max() > _MAX_DISTORTION):
        raise HbisInputError(f"{where}: distortion coefficients must be finite and below {_MAX_DISTORTION:g} in size")
    if image_size is not None:
        try:
            size = tuple(int(v) for v in image_size)
        except (TypeError, ValueError, OverflowError):
            raise HbisInputError(f"{where}: image_size must be two whole numbers (cols, rows)") from None
        if len(size) != 2 or not all(1 <= v <= MAX_SENSOR_SIDE for v in size):
            raise HbisInputError(f"{where}: image_size must be (cols, rows) within 1..{MAX_SENSOR_SIDE}, got {size}")
        image_size = size
    try:
        return LensCalibration(float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]),
                               tuple(d.tolist()), image_size)
    except HbisInputError as exc:
        raise HbisInputError(f"{where}: {exc}") from None


def split_camera(spec) -> tuple[Path, str | None]:
    """``FILE`` or ``FILE:NAME`` (a stereo calibration's camera, e.g. ``intrinsics.yml:M1``)."""
    text = str(spec)
    path = Path(text)
    if not path.exists() and ":" in text:
        head, name = text.rsplit(":", 1)
        if name.isidentifier() and Path(head).exists():
            return Path(head), name
    return path, None


def _number(node, key: str, where: str) -> float:
    if not (node.isReal() or node.isInt()):
        raise HbisInputError(f"{where}: {key} holds something that is not a number")
    return float(node.real())


def _whole(node, key: str, where: str) -> int:
    if not node.isInt():
        raise HbisInputError(f"{where}: {key} must be a whole number")
    return int(node.real())


def _read_matrix(node, key: str, where: str) -> np.ndarray:
    """A FileStorage node as a float64 array, its declared shape checked before anything is read:
    an ``opencv-matrix`` map (rows, cols, dt, data), a list (of lists) of numbers, or a number."""
    if node.isMap():
        keys = set(node.keys())
        if not {"rows", "cols", "data"} <= keys:
            raise HbisInputError(f"{where}: {key} is not a matrix (an opencv-matrix with rows, cols and data)")
        rows, cols = _whole(node.getNode("rows"), f"{key}.rows", where), _whole(node.getNode("cols"), f"{key}.cols", where)
        if not (1 <= rows <= MAX_MATRIX_SIDE and 1 <= cols <= MAX_MATRIX_SIDE):
            raise HbisInputError(f"{where}: {key} declares a {rows} x {cols} matrix; a calibration's are at most "
                                 f"{MAX_MATRIX_SIDE} x {MAX_MATRIX_SIDE}")
        data = node.getNode("data")
        count = data.size() if data.isSeq() else 1
        if count != rows * cols:
            raise HbisInputError(f"{where}: {key} declares {rows} x {cols} = {rows * cols} numbers but its data holds {count}")
        items = [data.at(i) for i in range(count)] if data.isSeq() else [data]
        return np.array([_number(v, key, where) for v in items]).reshape(rows, cols)
    if node.isSeq():
        count = node.size()
        if count > MAX_MATRIX_SIDE:
            raise HbisInputError(f"{where}: {key} holds {count} entries; a calibration matrix has at most {MAX_MATRIX_SIDE} rows")
        rows = [node.at(i) for i in range(count)]
        if all(r.isSeq() for r in rows) and rows:
            widths = {r.size() for r in rows}
            if len(widths) != 1 or widths.pop() > MAX_MATRIX_SIDE:
                raise HbisInputError(f"{where}: {key} has rows of different or absurd lengths")
            return np.array([[_number(r.at(j), key, where) for j in range(r.size())] for r in rows])
        return np.array([_number(r, key, where) for r in rows])
    return np.array([_number(node, key, where)])


def _pick(fs, names, where: str, camera: str | None):
    """(key, node) of the first of ``names`` the file holds, or of ``camera`` when given."""
    if camera is not None:
        node = fs.getNode(camera)
        if node.empty():
            raise HbisInputError(f"{where}: no camera {camera!r} in the file")
        return camera, node
    for name in names:
        node = fs.getNode(name)
        if not node.empty():
            return name, node
    return None, None


def _camera_keys(fs, where: str, camera: str | None) -> tuple[str, str | None]:
    """The keys of the camera matrix and its distortion: ``FILE:M1`` picks a stereo file's camera."""
    if camera is not None:
        _pick(fs, (), where, camera)
        partner = dict(_STEREO).get(camera)
        if partner is None and camera[-1:].isdigit():  # any NAME<k>: a distortion named D<k>
            partner = f"D{camera[-1]}"
        return camera, partner
    key, _ = _pick(fs, MATRIX_NAMES, where, None)
    if key is None:
        stereo = [m for m, _ in _STEREO if not fs.getNode(m).empty()]
        if stereo:
            raise HbisInputError(f"{where}: a stereo calibration with cameras {', '.join(stereo)}: choose one "
                                 f"with FILE:{stereo[0]}")
        raise HbisInputError(f"{where}: no camera matrix (looked for {', '.join(MATRIX_NAMES)})")
    d_key, _ = _pick(fs, DISTORTION_NAMES, where, None)
    return key, d_key


def read_opencv_calibration(spec) -> LensCalibration:
    """Read the YAML, XML or JSON that ``cv2.FileStorage`` wrote for a calibrated camera.

    ``spec`` is the file, or ``FILE:NAME`` for one camera of a stereo calibration (``M1`` with
    ``D1``, ``M2`` with ``D2``, ...). Every declared shape is checked before anything is read,
    and every value for being a finite, plausible number; a problem is one line naming the file
    and the key.
    """
    from hbis_torch.optional import import_cv2

    path, camera = split_camera(spec)
    where = f"{path}" + (f":{camera}" if camera else "")
    if not path.is_file():
        raise HbisInputError(f"{path}: no such file" if not path.exists() else f"{path}: not a file")
    if path.stat().st_size > MAX_CALIBRATION_BYTES:
        raise HbisInputError(f"{path}: {path.stat().st_size} bytes, more than a calibration file holds "
                             f"({MAX_CALIBRATION_BYTES} at most)")
    cv2 = import_cv2(f"reading the OpenCV calibration {path}")
    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except Exception as exc:  # noqa: BLE001 - cv2.error, or a SystemError from its bindings on garbage
        detail = (str(exc).strip().splitlines() or [type(exc).__name__])[-1][:200]
        raise HbisInputError(f"{path}: OpenCV cannot parse it ({detail})") from None
    try:
        if not fs.isOpened():
            raise HbisInputError(f"{path}: OpenCV cannot open it as a FileStorage file (YAML, XML or JSON)")
        k_key, d_key = _camera_keys(fs, where, camera)
        matrix = _read_matrix(fs.getNode(k_key), k_key, where)
        if matrix.shape != (3, 3):
            raise HbisInputError(f"{where}: {k_key} must be a 3 x 3 matrix, got shape {matrix.shape}")
        d_node = fs.getNode(d_key) if d_key else None
        distortion = _read_matrix(d_node, d_key, where) if d_node is not None and not d_node.empty() else None
        w, h = fs.getNode("image_width"), fs.getNode("image_height")
        size = None
        if not w.empty() and not h.empty():
            size = (_whole(w, "image_width", where), _whole(h, "image_height", where))
    except cv2.error as exc:
        raise HbisInputError(f"{where}: OpenCV cannot read it ({str(exc).strip().splitlines()[-1]})") from None
    finally:
        fs.release()
    return calibration_from_arrays(matrix, distortion, size, f"{where} ({k_key}{', ' + d_key if d_key else ''})")


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
