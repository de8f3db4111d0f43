"""The JSON description of an ``hbis-stack/1`` file: how it is built and what is checked in it.

Both kinds of stack (docs/design.md section 3): an HBIS scan (optics, ``phases_deg``) built by
:func:`make_meta`, and a burst (``"kind": "burst"``: per-frame ``motions``, ``confidence``,
``motion_models``, ``gain_offset``) built by :func:`make_burst_meta`; :func:`validate_stack`
checks a description against its frames. Every problem raises :class:`StackFormatError` with a
one-line message. Reading and writing the file are :mod:`hbis_torch.stack_io`'s, which hands
these names on.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from hbis_torch.checks import MAX_H, MAX_PHASE_DEG
from hbis_torch.config import Camera, FoveaSystem, LensCalibration, Prisms
from hbis_torch.errors import HbisInputError, StackFormatError

FORMAT = "hbis-stack/1"
FRAME_DTYPES = (np.dtype(np.uint8), np.dtype(np.uint16), np.dtype(np.float32))
CFA_PATTERNS = ("RGGB", "BGGR", "GRBG", "GBRG")
"""Bayer patterns of raw colour frames: the colours of the top-left 2 x 2 pixels, row by row."""
_CAMERA_KEYS = ("pixel_pitch_um", "rows", "cols", "focal_length_mm", "f_number")
_PRISM_KEYS = ("wedge_angle_deg", "refractive_index")
_TOP_KEYS = ("format", "h", "camera", "prisms", "object_distance_mm", "roi", "phases_deg")
KINDS = ("hbis", "burst")
"""What a stack holds: an HBIS (Risley) scan, the default, or a burst of freely moving frames."""
_BURST_KEYS = ("format", "kind", "h", "roi", "motions", "confidence", "motion_models", "gain_offset")
BURST_MIN_CONFIDENCE = 0.5
"""A burst frame whose registration confidence is below this is not trusted (left out)."""
BURST_MODELS = ("identity", "translation", "similarity", "affine", "homography")
"""Motion models a burst frame may record, simplest first."""

#: Most pages a stack file may hold: h x h frames with h <= MAX_H.
MAX_PAGES = MAX_H * MAX_H


def _is_int(value) -> bool:
    return isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_))


def _is_number(value) -> bool:
    return isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(
        value, (bool, np.bool_)
    )


def _jsonable(value):
    """Plain-Python copy of ``value`` (numpy and torch scalars/arrays become numbers/lists)."""
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, torch.Tensor):
        return _jsonable(value.detach().cpu().numpy())
    if isinstance(value, np.ndarray):
        return _jsonable(value.tolist())
    if isinstance(value, np.generic):
        return value.item()
    return value


def system_meta(system: FoveaSystem) -> dict:
    """The ``camera``, ``prisms`` and ``object_distance_mm`` entries describing ``system``."""
    cam, pr = system.camera, system.prisms
    meta = {
        "camera": {
            "pixel_pitch_um": float(cam.pixel_pitch_um),
            "rows": int(cam.rows),
            "cols": int(cam.cols),
            "focal_length_mm": float(cam.focal_length_mm),
            "f_number": float(cam.f_number),
            "wavelength_nm": float(cam.wavelength_nm),
        },
        "prisms": {
            "wedge_angle_deg": float(pr.wedge_angle_deg),
            "refractive_index": float(pr.refractive_index),
        },
        "object_distance_mm": float(system.object_distance_mm),
    }
    if cam.lens is not None:
        meta["camera"]["lens"] = cam.lens.to_dict()
    return meta


def _lens_from_meta(lens) -> LensCalibration | None:
    """``camera.lens`` ({"K": 3 x 3, "distortion": [...], "image_size": [cols, rows]}) or None."""
    if lens is None:
        return None
    if not isinstance(lens, dict) or "K" not in lens:
        raise HbisInputError("camera.lens must be an object with K (3 x 3) and distortion")
    K = np.asarray(lens["K"], dtype=np.float64)
    if K.shape != (3, 3):
        raise HbisInputError(f"camera.lens.K must be 3 x 3, got shape {K.shape}")
    size = lens.get("image_size")
    return LensCalibration(float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]),
                           tuple(lens.get("distortion", ())), tuple(size) if size is not None else None)


def make_meta(
    system: FoveaSystem,
    h: int,
    roi,
    phases_deg,
    bit_depth: int | None = None,
    reference_index: int | None = None,
    **extra,
) -> dict:
    """Build an hbis-stack/1 JSON object.

    Parameters
    ----------
    system : FoveaSystem
        Camera, prisms and object distance.
    h : int
        Resolution improvement factor of the scan.
    roi : (u0, v0, width, height)
        Where the frames sit on the sensor, in pixels.
    phases_deg : array-like, shape (F, 2)
        Prism phases (phi1, phi2) of each frame in degrees, in scan order.
    bit_depth : int or None
        Significant bits of integer frames (omitted when None).
    reference_index : int or None
        Index of the frame taken at the scan's initial phases (stored when given).
    **extra
        Further keys, kept as they are (must be JSON-serialisable).
    """
    meta = {"format": FORMAT, "h": int(h), **system_meta(system)}
    meta["roi"] = [int(r) for r in roi]
    meta["phases_deg"] = np.asarray(phases_deg, dtype=np.float64).reshape(-1, 2).tolist()
    if bit_depth is not None:
        meta["bit_depth"] = int(bit_depth)
    if reference_index is not None:
        meta["reference_index"] = int(reference_index)
    meta.update(_jsonable(extra))
    return meta


def _system_from_meta(meta: dict, where: str) -> FoveaSystem:
    cam, pr = meta["camera"], meta["prisms"]
    try:
        camera = Camera(
            pixel_pitch_um=float(cam["pixel_pitch_um"]),
            rows=cam["rows"],
            cols=cam["cols"],
            focal_length_mm=float(cam["focal_length_mm"]),
            f_number=float(cam["f_number"]),
            wavelength_nm=float(cam.get("wavelength_nm", 550.0)),
            lens=_lens_from_meta(cam.get("lens")),
        )
        prisms = Prisms(float(pr["wedge_angle_deg"]), float(pr["refractive_index"]))
        return FoveaSystem(camera, prisms, float(meta["object_distance_mm"]))
    except (HbisInputError, TypeError, ValueError) as exc:
        raise StackFormatError(f"{where}: {exc}") from None


def _check_meta(meta, where: str) -> None:
    """Check the JSON object alone (keys, types, values); frames are checked separately."""
    if not isinstance(meta, dict):
        raise StackFormatError(f"{where}: the description is not a JSON object")
    kind = meta.get("kind", "hbis")
    if kind not in KINDS:
        raise StackFormatError(f"{where}: kind must be one of {', '.join(KINDS)}, got {kind!r}")
    if kind == "burst":
        _check_burst_meta(meta, where)
        return
    missing = [k for k in _TOP_KEYS if k not in meta]
    if missing:
        raise StackFormatError(f"{where}: missing key(s) {', '.join(missing)} in the stack JSON")
    if meta["format"] != FORMAT:
        raise StackFormatError(f"{where}: format is {meta['format']!r}, expected {FORMAT!r}")
    if not _is_int(meta["h"]) or not 1 <= meta["h"] <= MAX_H:
        raise StackFormatError(f"{where}: h must be an integer from 1 to {MAX_H}, got {meta['h']!r}")
    for key, needed in (("camera", _CAMERA_KEYS), ("prisms", _PRISM_KEYS)):
        block = meta[key]
        if not isinstance(block, dict):
            raise StackFormatError(f"{where}: {key} must be a JSON object")
        gone = [k for k in needed if k not in block]
        if gone:
            raise StackFormatError(f"{where}: missing key(s) {', '.join(key + '.' + k for k in gone)}")
        for k, v in block.items():
            if k in needed or k == "wavelength_nm":
                if not _is_number(v) or not math.isfinite(v):
                    raise StackFormatError(f"{where}: {key}.{k} must be a finite number, got {v!r}")
    for k in ("rows", "cols"):
        if not _is_int(meta["camera"][k]):
            raise StackFormatError(f"{where}: camera.{k} must be an integer, got {meta['camera'][k]!r}")
    od = meta["object_distance_mm"]
    if not _is_number(od) or not math.isfinite(od):
        raise StackFormatError(f"{where}: object_distance_mm must be a finite number, got {od!r}")
    roi = meta["roi"]
    if not isinstance(roi, (list, tuple)) or len(roi) != 4 or not all(_is_int(r) for r in roi):
        raise StackFormatError(f"{where}: roi must be four integers [u0, v0, width, height], got {roi!r}")
    phases = meta["phases_deg"]
    if (
        not isinstance(phases, (list, tuple))
        or len(phases) == 0
        or not all(isinstance(p, (list, tuple)) and len(p) == 2 for p in phases)
        or not all(_is_number(x) for p in phases for x in p)
    ):
        raise StackFormatError(f"{where}: phases_deg must be a non-empty list of [phi1, phi2] numbers")
    if not np.isfinite(np.asarray(phases, dtype=np.float64)).all():
        raise StackFormatError(f"{where}: phases_deg contains NaN or infinite values")
    if np.abs(np.asarray(phases, dtype=np.float64)).max() > MAX_PHASE_DEG:
        raise StackFormatError(f"{where}: phases_deg must lie within +-{MAX_PHASE_DEG:g} degrees")
    bd = meta.get("bit_depth")
    if bd is not None and (not _is_int(bd) or not 1 <= bd <= 16):
        raise StackFormatError(f"{where}: bit_depth must be an integer from 1 to 16, got {bd!r}")
    ref = meta.get("reference_index")
    if ref is not None and (not _is_int(ref) or not 0 <= ref < len(phases)):
        raise StackFormatError(
            f"{where}: reference_index {ref!r} is not a frame index (0..{len(phases) - 1})"
        )
    black = meta.get("black_level", 0)
    if not _is_number(black) or not math.isfinite(black) or black < 0:
        raise StackFormatError(f"{where}: black_level must be a non-negative number, got {black!r}")


def _check_burst_meta(meta: dict, where: str) -> None:
    """The JSON of a burst stack: its keys, types and values (one entry per frame is checked
    against the frames in :func:`validate_stack`)."""
    missing = [k for k in _BURST_KEYS if k not in meta]
    if missing:
        raise StackFormatError(f"{where}: missing key(s) {', '.join(missing)} in the burst stack JSON")
    if meta["format"] != FORMAT:
        raise StackFormatError(f"{where}: format is {meta['format']!r}, expected {FORMAT!r}")
    if not _is_int(meta["h"]) or not 1 <= meta["h"] <= MAX_H:
        raise StackFormatError(f"{where}: h (the burst's scale) must be an integer from 1 to {MAX_H}, "
                               f"got {meta['h']!r}")
    if "scale" in meta and meta["scale"] != meta["h"]:
        raise StackFormatError(f"{where}: scale {meta['scale']!r} differs from h {meta['h']!r}")
    roi = meta["roi"]
    if not isinstance(roi, (list, tuple)) or len(roi) != 4 or not all(_is_int(r) for r in roi) \
            or min(roi) < 0:
        raise StackFormatError(f"{where}: roi must be four integers [u0, v0, width, height] >= 0, got {roi!r}")
    count = _per_frame_count(meta, where)
    try:
        motions = np.asarray(meta["motions"], dtype=np.float64)
        gain_offset = np.asarray(meta["gain_offset"], dtype=np.float64)
        confidence = np.asarray(meta["confidence"], dtype=np.float64)
    except (TypeError, ValueError):
        raise StackFormatError(f"{where}: motions, gain_offset and confidence must hold numbers only") from None
    if motions.shape != (count, 3, 3) or not np.isfinite(motions).all():
        raise StackFormatError(f"{where}: motions must be one finite 3 x 3 homography per frame, got shape "
                               f"{motions.shape}")
    if (np.abs(motions[:, 2, 2]) < 1e-12).any() or (np.abs(np.linalg.det(motions)) < 1e-12).any():
        raise StackFormatError(f"{where}: motions holds a singular homography")
    if gain_offset.shape != (count, 2) or not np.isfinite(gain_offset).all() or (gain_offset[:, 0] <= 0).any():
        raise StackFormatError(f"{where}: gain_offset must be one finite [gain > 0, offset] per frame")
    if confidence.shape != (count,) or not np.isfinite(confidence).all() \
            or (confidence < 0).any() or (confidence > 1).any():
        raise StackFormatError(f"{where}: confidence must be one number in [0, 1] per frame")
    models = meta["motion_models"]
    if not all(m in BURST_MODELS for m in models):
        raise StackFormatError(f"{where}: motion_models must each be one of {', '.join(BURST_MODELS)}")
    ref = meta.get("reference_index", 0)
    if not _is_int(ref) or not 0 <= ref < count:
        raise StackFormatError(f"{where}: reference_index {ref!r} is not a frame index (0..{count - 1})")
    bd = meta.get("bit_depth")
    if bd is not None and (not _is_int(bd) or not 1 <= bd <= 16):
        raise StackFormatError(f"{where}: bit_depth must be an integer from 1 to 16, got {bd!r}")
    black = meta.get("black_level", 0)
    if not _is_number(black) or not math.isfinite(black) or black < 0:
        raise StackFormatError(f"{where}: black_level must be a non-negative number, got {black!r}")


def _per_frame_count(meta: dict, where: str) -> int:
    """The number of frames a burst's per-frame lists agree on."""
    lengths = {k: len(meta[k]) if isinstance(meta[k], (list, tuple)) else -1
               for k in ("motions", "confidence", "motion_models", "gain_offset")}
    if len(set(lengths.values())) != 1 or min(lengths.values()) < 1:
        raise StackFormatError(f"{where}: motions, confidence, motion_models and gain_offset must be lists of "
                               f"one entry per frame, got lengths {lengths}")
    return lengths["motions"]


def validate_stack(frames: np.ndarray, meta: dict, where: str = "stack") -> None:
    """Raise StackFormatError unless ``frames`` and ``meta`` form a valid hbis-stack/1 stack.

    Parameters
    ----------
    frames : np.ndarray, shape (F, H, W)
        uint8, uint16 or float32 in [0, 1].
    meta : dict
        The JSON object.
    where : str
        Prefix of the error message (the file name when reading or writing).
    """
    _check_meta(meta, where)
    if not isinstance(frames, np.ndarray):
        raise StackFormatError(f"{where}: frames must be a numpy array, got {type(frames).__name__}")
    if not (frames.ndim == 3 or (frames.ndim == 4 and frames.shape[-1] == 3)):
        raise StackFormatError(
            f"{where}: frames must have shape (F, rows, cols) (grayscale) or (F, rows, cols, 3) (RGB), "
            f"got {frames.shape}"
        )
    cfa = meta.get("cfa")
    if cfa is not None and (cfa not in CFA_PATTERNS or frames.ndim != 3):
        raise StackFormatError(f"{where}: cfa must be one of {', '.join(CFA_PATTERNS)} on raw (F, rows, cols) "
                               f"frames, got {cfa!r} with frames {frames.shape}")
    if frames.dtype not in FRAME_DTYPES:
        raise StackFormatError(
            f"{where}: frame dtype {frames.dtype} is not one of uint8, uint16, float32"
        )
    if meta.get("kind", "hbis") == "burst":
        if frames.shape[0] != len(meta["motions"]):
            raise StackFormatError(f"{where}: {frames.shape[0]} frame(s) but {len(meta['motions'])} entries in "
                                   "motions (one per frame)")
        _check_stuck_pixels(meta.get("stuck_pixels", []), frames.shape[1:3], where)
    else:
        _check_scan_geometry(frames, meta, where)
    u0, v0, width, height = meta["roi"]
    if (height, width) != frames.shape[1:3]:
        raise StackFormatError(
            f"{where}: roi is {width} x {height} (width x height) but the frames are "
            f"{frames.shape[2]} x {frames.shape[1]}"
        )
    bd = meta.get("bit_depth")
    if frames.dtype == np.float32:
        if not np.isfinite(frames).all():
            raise StackFormatError(f"{where}: frames contain NaN or infinite values")
        lo, hi = float(frames.min()), float(frames.max())
        if lo < 0.0 or hi > 1.0:
            raise StackFormatError(
                f"{where}: float32 frames must lie in [0, 1], found values in [{lo:g}, {hi:g}]"
            )
        return
    container = frames.dtype.itemsize * 8
    if bd is not None and bd > container:
        raise StackFormatError(f"{where}: bit_depth {bd} does not fit {frames.dtype} frames")
    white = 2 ** (bd or container) - 1
    top = int(frames.max())
    if top > white:
        raise StackFormatError(
            f"{where}: pixel values up to {top} exceed bit_depth {bd} (largest allowed {white})"
        )
    black = meta.get("black_level", 0)
    if black >= white:
        raise StackFormatError(f"{where}: black_level {black} is not below the white level {white}")


def _check_stuck_pixels(stuck, shape: tuple[int, int], where: str) -> None:
    """A burst's ``stuck_pixels``: [row, col] pairs of integers inside the frames."""
    pairs = isinstance(stuck, (list, tuple)) and all(
        isinstance(p, (list, tuple)) and len(p) == 2 and all(_is_int(i) for i in p) for p in stuck)
    if not pairs or any(not (0 <= r < shape[0] and 0 <= c < shape[1]) for r, c in stuck):
        raise StackFormatError(f"{where}: stuck_pixels must be [row, col] pairs of integers inside the "
                               f"{shape[1]} x {shape[0]} frames")


def _check_scan_geometry(frames: np.ndarray, meta: dict, where: str) -> None:
    """An HBIS scan's frames against its phases and its sensor."""
    n_frames, n_phases = frames.shape[0], len(meta["phases_deg"])
    if n_frames != n_phases:
        raise StackFormatError(
            f"{where}: {n_frames} frame(s) but {n_phases} entries in phases_deg (one per frame)"
        )
    system = _system_from_meta(meta, where)
    u0, v0, width, height = meta["roi"]
    cam = system.camera
    if width < 1 or height < 1 or u0 < 0 or v0 < 0 or u0 + width > cam.cols or v0 + height > cam.rows:
        raise StackFormatError(
            f"{where}: roi {list(meta['roi'])} lies outside the {cam.rows} x {cam.cols} "
            "(rows x cols) sensor"
        )


def make_burst_meta(h: int, roi, motions, confidence, motion_models, gain_offset,
                    reference_index: int = 0, bit_depth: int | None = None, **extra) -> dict:
    """Build the JSON object of a burst stack (``"kind": "burst"``).

    Parameters
    ----------
    h : int
        Output scale S: the reconstruction is the reference frame's grid refined S times.
    roi : (u0, v0, width, height)
        Where the frames were cut from the captured ones ((0, 0, W, H) when not cut).
    motions : array-like, shape (F, 3, 3)
        Homography of each frame: frame pixel (u, v) -> reference pixel, LR px, pixel centres
        at integers (:mod:`hbis_torch.reconstruct.positions`); the identity for the reference.
    confidence : array-like, shape (F,)
        Registration confidence in [0, 1] (0: the motion is not to be trusted).
    motion_models : sequence of str, length F
        The model each motion was fitted with (:data:`BURST_MODELS`).
    gain_offset : array-like, shape (F, 2)
        (g, o) per frame: ``g * frame + o`` matches the reference's brightness (values in [0, 1]).
    reference_index : int
    bit_depth : int or None
    **extra
        Further keys, kept as they are.
    """
    meta = {"format": FORMAT, "kind": "burst", "h": int(h), "scale": int(h), "roi": [int(r) for r in roi],
            "reference_index": int(reference_index),
            "motions": np.asarray(motions, dtype=np.float64).reshape(-1, 3, 3).tolist(),
            "confidence": [float(c) for c in np.asarray(confidence, dtype=np.float64).reshape(-1)],
            "motion_models": [str(m) for m in motion_models],
            "gain_offset": np.asarray(gain_offset, dtype=np.float64).reshape(-1, 2).tolist()}
    if bit_depth is not None:
        meta["bit_depth"] = int(bit_depth)
    meta.update(_jsonable(extra))
    return meta
