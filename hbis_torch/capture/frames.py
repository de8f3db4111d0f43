"""Captured frames from files: one file per frame, a ``{index}`` pattern, a multi-page TIFF or a
video.

Every reader returns the frames in scan order as one array, shape (F, H, W) for grayscale or
(F, H, W, 3) for colour (RGB order), dtype uint8, uint16 or float32, exactly as stored. Problems
(a missing or unreadable file, frames of different sizes or dtypes) raise
:class:`~hbis_torch.errors.HbisInputError` with one line naming the file.

Images are read with tifffile (TIFF) or, for other formats, OpenCV when it is installed (the
``camera`` extra) and Pillow otherwise; videos need OpenCV.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from hbis_torch.errors import HbisInputError
from hbis_torch.optional import import_cv2

VIDEO_SUFFIXES = frozenset({".avi", ".mp4", ".mkv", ".mov", ".webm", ".m4v", ".mpg", ".mpeg", ".wmv"})
TIFF_SUFFIXES = frozenset({".tif", ".tiff"})
FRAME_DTYPES = (np.dtype(np.uint8), np.dtype(np.uint16), np.dtype(np.float32))


def _as_frame(array: np.ndarray, where: str) -> np.ndarray:
    """One frame as (H, W) or (H, W, 3); alpha dropped; float64 stored as float32."""
    array = np.asarray(array)
    if array.ndim == 3 and array.shape[-1] == 4:
        array = array[..., :3]
    if array.ndim == 3 and array.shape[-1] == 1:
        array = array[..., 0]
    if not (array.ndim == 2 or (array.ndim == 3 and array.shape[-1] == 3)):
        raise HbisInputError(f"{where}: a frame must be grayscale (H, W) or RGB (H, W, 3), got shape {array.shape}")
    if array.dtype == np.float64:
        array = array.astype(np.float32)
    if array.dtype not in FRAME_DTYPES:
        raise HbisInputError(f"{where}: frame dtype {array.dtype} is not one of uint8, uint16, float32")
    return array


def read_image(path) -> np.ndarray:
    """The pages of one image file, (P, H, W) or (P, H, W, 3) (P = 1 except multi-page TIFFs)."""
    path = Path(path)
    if not path.is_file():
        raise HbisInputError(f"{path}: no such file" if not path.exists() else f"{path}: not a file")
    try:
        if path.suffix.lower() in TIFF_SUFFIXES:
            import tifffile

            with tifffile.TiffFile(path) as tif:
                pages = [p.asarray() for p in tif.pages]
        else:
            pages = [_read_other(path)]
    except HbisInputError:
        raise
    except Exception as exc:  # noqa: BLE001 - image libraries raise many types for bad files
        raise HbisInputError(f"{path}: not a readable image ({type(exc).__name__}: {exc})") from None
    if not pages:
        raise HbisInputError(f"{path}: the file holds no image")
    frames = [_as_frame(p, str(path)) for p in pages]
    if len({(f.shape, f.dtype) for f in frames}) != 1:
        raise HbisInputError(f"{path}: its pages differ in size or dtype")
    return np.stack(frames)


def _read_other(path: Path) -> np.ndarray:
    try:
        import cv2
    except ImportError:
        cv2 = None
    if cv2 is not None:
        image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if image is None:
            raise ValueError("OpenCV cannot decode it")
        if image.ndim == 3:
            image = cv2.cvtColor(image, cv2.COLOR_BGRA2RGBA if image.shape[-1] == 4 else cv2.COLOR_BGR2RGB)
        return image
    from PIL import Image

    with Image.open(path) as im:
        if im.mode in ("I", "I;16", "I;16B"):
            return np.asarray(im).astype(np.uint16)
        if im.mode not in ("L", "RGB", "RGBA", "F"):
            im = im.convert("RGB")
        return np.asarray(im)


def read_video(path, count: int | None = None) -> np.ndarray:
    """Frames of a video file, (F, H, W) when every frame is gray (equal R, G, B), else (F, H, W, 3).

    ``count``: read at most this many frames (None: all).
    """
    path = Path(path)
    if not path.is_file():
        raise HbisInputError(f"{path}: no such file")
    cv2 = import_cv2(f"reading the video {path}")
    capture = cv2.VideoCapture(str(path))
    frames = []
    try:
        if not capture.isOpened():
            raise HbisInputError(f"{path}: OpenCV cannot open this video")
        while count is None or len(frames) < count:
            ok, frame = capture.read()
            if not ok:
                break
            frames.append(frame)
    finally:
        capture.release()
    if not frames:
        raise HbisInputError(f"{path}: the video holds no frames OpenCV can decode")
    return bgr_frames(np.stack(frames))


def bgr_frames(frames: np.ndarray) -> np.ndarray:
    """OpenCV's BGR frames (F, H, W, 3) as RGB, or as gray (F, H, W) when all three are equal."""
    if frames.ndim == 4 and frames.shape[-1] == 3:
        if (frames[..., 0] == frames[..., 1]).all() and (frames[..., 1] == frames[..., 2]).all():
            return np.ascontiguousarray(frames[..., 0])
        return np.ascontiguousarray(frames[..., ::-1])
    return frames


def pattern_paths(pattern: str, count: int) -> list[Path]:
    """The files ``pattern.format(index=k)`` for k = 0 .. count - 1 (``{index:03d}`` works too)."""
    try:
        return [Path(pattern.format(index=k)) for k in range(count)]
    except (KeyError, IndexError, ValueError):
        raise HbisInputError(f"frame pattern {pattern!r} may only use {{index}} (e.g. frame_{{index:03d}}.tif)") from None


def is_pattern(text: str) -> bool:
    return "{index" in str(text)


def read_frames(sources, count: int | None = None) -> tuple[np.ndarray, list[str]]:
    """Frames in scan order from files, a ``{index}`` pattern, a multi-page TIFF or a video.

    Parameters
    ----------
    sources : list of str or Path
        Several image files (one frame each, in scan order); or one of: a pattern holding
        ``{index}`` (replaced by 0, 1, ...), a multi-page TIFF, a video file.
    count : int or None
        Frames expected (h^2); a pattern needs it. Other sources are read whole and checked by
        the caller.

    Returns
    -------
    frames : np.ndarray, shape (F, H, W) or (F, H, W, 3)
        uint8, uint16 or float32 as stored.
    names : list of str
        Where each frame came from (for messages).
    """
    sources = [str(s) for s in sources]
    if not sources:
        raise HbisInputError("no frames given")
    if len(sources) == 1 and is_pattern(sources[0]):
        if count is None:
            raise HbisInputError("a frame pattern needs the number of frames (h^2 from the phases file)")
        paths = pattern_paths(sources[0], count)
    elif len(sources) == 1 and Path(sources[0]).suffix.lower() in VIDEO_SUFFIXES:
        frames = read_video(sources[0])
        return frames, [f"{sources[0]} frame {k}" for k in range(len(frames))]
    else:
        paths = [Path(s) for s in sources]
    frames, names = [], []
    for path in paths:
        pages = read_image(path)
        if len(paths) > 1 and len(pages) > 1:
            raise HbisInputError(f"{path}: holds {len(pages)} pages; give one multi-page TIFF alone, "
                                 "or one file per frame")
        frames.extend(pages)
        names.extend([str(path)] if len(pages) == 1 else [f"{path} page {k}" for k in range(len(pages))])
    first = frames[0]
    for frame, name in zip(frames, names):
        if frame.shape != first.shape:
            raise HbisInputError(f"{name}: frame of shape {frame.shape}, but {names[0]} has {first.shape}")
        if frame.dtype != first.dtype:
            raise HbisInputError(f"{name}: frame of dtype {frame.dtype}, but {names[0]} has {first.dtype}")
    return np.stack(frames), names
