"""The ``hbis-stack/1`` file: one multi-page TIFF of frames plus a JSON description.

A stack holds the frames of one sub-pixel scan in scan order, shape (F, rows, cols) (grayscale, or
raw Bayer with a ``cfa`` key) or (F, rows, cols, 3) (RGB), uint8, uint16 or float32 (float in [0, 1]). Page 0's ImageDescription holds one JSON object
(docs/design.md section 3)::

    {"format": "hbis-stack/1", "h": 4,
     "camera": {"pixel_pitch_um": 3.75, "rows": 960, "cols": 1280, "focal_length_mm": 12.0,
                "f_number": 1.4, "wavelength_nm": 550},
     "prisms": {"wedge_angle_deg": 4.0, "refractive_index": 1.5},
     "object_distance_mm": 50.0,
     "roi": [u0, v0, width, height],
     "phases_deg": [[phi1, phi2], ...],
     "bit_depth": 12}

Optional keys this module understands (all others are kept as they are): ``bit_depth`` (default:
8 for uint8, 16 for uint16), ``reference_index`` (the frame taken at the scan's initial phases,
default 0), ``black_level`` (digital number of a black pixel, default 0; integer frames only),
``camera.wavelength_nm`` (default 550), ``camera.lens`` (a lens calibration: ``K``, ``distortion``,
``image_size``), ``cfa`` (the Bayer pattern of raw colour frames: RGGB, BGGR, GRBG or GBRG).

Every problem with a file or a stack raises :class:`StackFormatError` (an HbisInputError) whose
one-line message starts with the file name and says what was wrong. Writes are atomic.

Reading checks what the TIFF headers declare (page count, each page's shape and dtype, where its
data lies) before decoding anything: at most 256 pages (h = 16), one shape and one dtype, data
inside the file, and no more than ``HBIS_MAX_STACK_MB`` MiB once decoded (default 4096, an
environment variable the user can raise; :mod:`hbis_torch.tiff_io`). A hostile file is refused in
one line, quickly.
A *burst* stack (``"kind": "burst"``) holds frames of a hand-held or otherwise freely moving camera
instead of a Risley scan: no optics, no phases; instead each frame's measured motion to the
reference (``motions``, F x 3 x 3 homographies frame px -> reference px), a registration
``confidence``, the ``motion_models`` picked and the ``gain_offset`` that matches its brightness
to the reference's; ``h`` is the output scale S (:func:`make_burst_meta`).
docs/stack-format.md describes the format for outside tools. The description itself (building and
checking it) is :mod:`hbis_torch.stack_format`'s; its public names are handed on here.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from hbis_torch.config import FoveaSystem
from hbis_torch.errors import HbisInputError, StackFormatError
from hbis_torch.io_utils import atomic_path, load_json
from hbis_torch.stack_format import (BURST_MIN_CONFIDENCE, BURST_MODELS, CFA_PATTERNS, FORMAT, FRAME_DTYPES, KINDS,
                                     MAX_PAGES, _jsonable, _system_from_meta, make_burst_meta, make_meta, system_meta,
                                     validate_stack)
from hbis_torch.tiff_io import read_tiff, write_tiff

__all__ = ["BURST_MIN_CONFIDENCE", "BURST_MODELS", "CFA_PATTERNS", "FORMAT", "FRAME_DTYPES", "KINDS", "MAX_PAGES",
           "Stack", "StackFormatError", "make_burst_meta", "make_meta", "object_pixel_um", "read_image", "read_stack",
           "system_meta", "validate_stack", "write_image", "write_stack"]


@dataclass
class Stack:
    """Frames of one sub-pixel scan and their hbis-stack/1 description.

    Attributes
    ----------
    frames : np.ndarray, shape (F, H, W) or (F, H, W, 3)
        uint8, uint16 or float32 (in [0, 1]), in scan order; RGB in the last axis.
    meta : dict
        The hbis-stack/1 JSON object, extra keys included.

    Examples
    --------
    A 2 x 2 scan's four 12-bit frames, written and read back in a temporary directory:

    >>> import os, tempfile
    >>> import numpy as np
    >>> from hbis_torch import FoveaSystem
    >>> from hbis_torch.scan.plan import plan_scan
    >>> from hbis_torch.stack_io import Stack, make_meta, read_stack, write_stack
    >>> system = FoveaSystem()
    >>> plan = plan_scan(system, 2)
    >>> meta = make_meta(system, 2, (600, 400, 16, 12), plan.phases_deg, bit_depth=12,
    ...                  reference_index=plan.reference_index)
    >>> frames = np.arange(4 * 12 * 16, dtype=np.uint16).reshape(4, 12, 16)
    >>> with tempfile.TemporaryDirectory() as tmp:
    ...     path = os.path.join(tmp, "stack.tif")
    ...     write_stack(path, Stack(frames, meta))
    ...     back = read_stack(path)
    >>> back.h, back.roi, back.reference_index, back.bit_depth
    (2, (600, 400, 16, 12), 3, 12)
    >>> np.array_equal(back.frames, frames)
    True
    >>> round(float(back.to_float().max()), 4)       # 767 / (2**12 - 1)
    0.1873
    """

    frames: np.ndarray
    meta: dict

    def validate(self, where: str = "stack") -> "Stack":
        """Raise StackFormatError unless the stack is valid; return self."""
        validate_stack(self.frames, self.meta, where)
        return self

    @property
    def h(self) -> int:
        """Refinement factor of the output grid (a scan's h, a burst's scale S)."""
        return int(self.meta["h"])

    @property
    def kind(self) -> str:
        """``"hbis"`` (a Risley scan; the default when the file has no ``kind``) or ``"burst"``."""
        return str(self.meta.get("kind", "hbis"))

    @property
    def motions(self) -> np.ndarray:
        """A burst's (F, 3, 3) float64 homographies, frame px -> reference px."""
        self._burst_only("motions")
        return np.asarray(self.meta["motions"], dtype=np.float64).reshape(-1, 3, 3)

    @property
    def confidence(self) -> np.ndarray:
        """A burst's (F,) float64 registration confidence in [0, 1]."""
        self._burst_only("confidence")
        return np.asarray(self.meta["confidence"], dtype=np.float64).reshape(-1)

    @property
    def gain_offset(self) -> np.ndarray:
        """A burst's (F, 2) float64 (gain, offset): ``gain * frame + offset`` matches the reference."""
        self._burst_only("gain_offset")
        return np.asarray(self.meta["gain_offset"], dtype=np.float64).reshape(-1, 2)

    def _burst_only(self, what: str) -> None:
        if self.kind != "burst":
            raise HbisInputError(f"{what} belongs to burst stacks; this stack is an HBIS scan (its motion is "
                                 "the optics')")

    @property
    def roi(self) -> tuple[int, int, int, int]:
        """(u0, v0, width, height) in sensor pixels."""
        return tuple(int(r) for r in self.meta["roi"])

    @property
    def phases_deg(self) -> np.ndarray:
        """(F, 2) float64 prism phases (phi1, phi2) in degrees (HBIS scans only)."""
        if self.kind == "burst":
            raise HbisInputError("a burst stack has no prism phases (its motion is in motions)")
        return np.asarray(self.meta["phases_deg"], dtype=np.float64).reshape(-1, 2)

    @property
    def reference_index(self) -> int:
        """Index of the frame taken at the scan's initial phases (0 when the file omits it)."""
        return int(self.meta.get("reference_index", 0))

    @property
    def bit_depth(self) -> int | None:
        """Significant bits; from the dtype (8 or 16) when the file omits it; None for float."""
        bd = self.meta.get("bit_depth")
        if bd is not None:
            return int(bd)
        if self.frames.dtype == np.float32:
            return None
        return self.frames.dtype.itemsize * 8

    @property
    def black_level(self) -> float:
        return float(self.meta.get("black_level", 0))

    @property
    def system(self) -> FoveaSystem:
        if self.kind == "burst" and "camera" not in self.meta:
            raise HbisInputError("a burst stack records no optics (camera, prisms)")
        return _system_from_meta(self.meta, "stack")

    @property
    def colour(self) -> bool:
        """True for RGB frames (F, H, W, 3) and for raw Bayer frames (a ``cfa`` key)."""
        return self.frames.ndim == 4 or self.meta.get("cfa") is not None

    def to_float(self, index=None) -> torch.Tensor:
        """Frames as a (F, H, W) (or (F, H, W, 3)) float32 tensor in [0, 1].

        Integer frames map black_level to 0 and 2**bit_depth - 1 to 1 (values below black clip
        to 0); float32 frames are returned as stored. ``index`` (a NumPy index into the frames:
        ``k`` one frame, ``(..., c)`` one colour channel) converts only those, with the same
        values as ``to_float()[index]``.
        """
        frames = self.frames if index is None else self.frames[index]
        if self.frames.dtype == np.float32:
            return torch.from_numpy(np.array(frames, dtype=np.float32))
        white = 2 ** self.bit_depth - 1
        black = self.black_level
        # Converted by torch, on its threads: numpy's float32 division of a full frame's stack
        # (80 MB of fresh memory) took 0.23-0.27 s, torch's 0.04 s, with the same bits.
        x = torch.from_numpy(np.require(frames, requirements=("C", "W"))).to(torch.float32)
        if black == 0:
            # only values above white (none in a valid file) need clipping
            x.div_(white)
            return x.clamp_(max=1.0) if float(x.max()) > 1.0 else x
        return x.sub_(black).div_(white - black).clamp_(0.0, 1.0)  # in place: a full frame's stack is 80 MB


#: How to make a stack, for the line that refuses a file that is none (a plain image, a burst's frames).
MAKE_A_STACK = ("make one with 'hbis assemble --burst --scale S FRAMES...' (frames of a moving camera), "
                "'hbis assemble --phases PHASES FRAMES...' (a prism scan) or 'hbis simulate'")


def read_stack(path) -> Stack:
    """Read and validate an hbis-stack/1 TIFF.

    Returns
    -------
    Stack
        frames (F, H, W) as stored, meta with every key of the file.

    Raises
    ------
    StackFormatError
        One line naming the file and what was wrong with it.
    """
    path = Path(path)
    frames, description = read_tiff(path, MAX_PAGES)
    if not description:
        raise StackFormatError(f"{path}: not an hbis-stack/1 file: page 0 has no ImageDescription (the stack's "
                               f"JSON); {MAKE_A_STACK}")
    try:
        meta = load_json(description, f"{path}: not an hbis-stack/1 file: page 0's ImageDescription")
    except HbisInputError as exc:
        raise StackFormatError(f"{exc}; {MAKE_A_STACK}") from None
    if not isinstance(meta, dict):
        raise StackFormatError(f"{path}: not an hbis-stack/1 file: page 0's ImageDescription is not a JSON object; "
                               f"{MAKE_A_STACK}")
    if "format" not in meta:  # a plain image (tifffile writes {"shape": ...}) or another program's file
        raise StackFormatError(f"{path}: not an hbis-stack/1 file (its JSON has no 'format'); {MAKE_A_STACK}")
    validate_stack(frames, meta, str(path))
    h = meta["h"]
    if meta.get("kind", "hbis") == "hbis" and len(frames) != h * h:  # a file is one whole scan (in memory, part of one may be a Stack)
        raise StackFormatError(f"{path}: {len(frames)} frame(s), but a scan with h = {h} has h x h = {h * h}")
    return Stack(frames, meta)


def object_pixel_um(system: FoveaSystem, h: int = 1) -> float:
    """Size on the object plane (at the object distance v) of one pixel of an image sampled
    ``h`` times finer than the sensor, in um: ``p * v / f' / h``. The pixel size every hbis TIFF
    records (stack frames: ``h = 1``; ground truths and reconstructions: the stack's ``h``)."""
    return 1e3 * system.object_pixel_mm / int(h)


def write_stack(path, stack: Stack) -> None:
    """Validate ``stack`` and write it atomically as an hbis-stack/1 TIFF at ``path``."""
    path = Path(path)
    frames = np.ascontiguousarray(stack.frames)
    meta = _jsonable(stack.meta)
    validate_stack(frames, meta, str(path))
    try:
        description = json.dumps(meta, allow_nan=False)
    except (TypeError, ValueError) as exc:
        raise StackFormatError(f"{path}: the stack's JSON cannot be written ({exc})") from None
    try:
        pixel_um = object_pixel_um(_system_from_meta(meta, str(path)))
    except (HbisInputError, KeyError):  # a burst records no optics
        pixel_um = None
    with atomic_path(path) as tmp:
        write_tiff(tmp, frames, description, pixel_um)


def write_image(path, image, meta: dict | None = None, pixel_size_um: float | None = None) -> None:
    """Write one float32 image (H, W) in [0, 1] (a ground truth or a reconstruction) atomically.

    ``meta`` (optional) goes to the ImageDescription as JSON. ``pixel_size_um`` (optional, on the
    object plane: :func:`object_pixel_um`) goes to the resolution tags and to the JSON as
    ``pixel_size_um`` with ``pixel_plane: "object"``.
    """
    path = Path(path)
    image = np.asarray(image.detach().cpu() if isinstance(image, torch.Tensor) else image)
    if not (image.ndim == 2 or (image.ndim == 3 and image.shape[-1] == 3)):
        raise HbisInputError(f"{path}: an image must have shape (H, W) or (H, W, 3), got {image.shape}")
    image = np.asarray(image, dtype=np.float32)  # no copy of a float32 image
    with np.errstate(over="ignore"):  # the sum is finite, unless values are not or it overflows
        finite = bool(np.isfinite(image.sum())) or bool(np.isfinite(image).all())
    if not finite:
        raise HbisInputError(f"{path}: the image contains NaN or infinite values")
    meta = dict(meta or {})
    if pixel_size_um is not None:
        meta.update(pixel_size_um=float(pixel_size_um), pixel_plane="object")
    description = json.dumps(_jsonable(meta), allow_nan=False)
    with atomic_path(path) as tmp:
        write_tiff(tmp, image, description, pixel_size_um)


def read_image(path) -> tuple[np.ndarray, dict]:
    """Read a single-page grayscale TIFF: (image (H, W), its JSON description or {})."""
    path = Path(path)
    arrays, description = read_tiff(path, max_pages=1)
    try:
        meta = load_json(description, str(path)) if description else {}
    except HbisInputError:
        meta = {}
    return arrays[0], meta if isinstance(meta, dict) else {}
