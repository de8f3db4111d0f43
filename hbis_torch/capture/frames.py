"""Captured frames from files: one file per frame, a ``{index}`` pattern, a multi-page TIFF or a
video.

Every source is first *probed*: its headers give the frame count, the frame size and the dtype
(:class:`FrameInfo`, :func:`probe_source`), and nothing is decoded until every source has been
probed, all agree on size and dtype, and the frames together fit the decoding limit
(``HBIS_MAX_STACK_MB``, :func:`hbis_torch.tiff_io.max_decoded_bytes`). A 30000 x 30000 PNG among
small frames, or a video whose header declares a huge picture, is refused from its header in
milliseconds.

Every reader returns the frames in scan order as one array, shape (F, H, W) for grayscale or
(F, H, W, 3) for colour (RGB order), dtype uint8, uint16 or float32, exactly as stored. Problems
(a missing or unreadable file, frames of different sizes or dtypes, too much to decode) raise
:class:`~hbis_torch.errors.HbisInputError` with one line naming the file.

TIFFs are read with tifffile; other images have their header read by this module (PNG) or Pillow
and are decoded by OpenCV when it is installed (the ``camera`` extra), else Pillow; video files
(AVI, MP4, MKV, MOV, ...) are read with PyAV (the ``video`` extra: FFmpeg's demuxers and
decoders). OpenCV serves only live cameras (:mod:`hbis_torch.capture.cameras`).
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hbis_torch.errors import HbisInputError
from hbis_torch.notices import act

VIDEO_SUFFIXES = frozenset({".avi", ".mp4", ".mkv", ".mov", ".webm", ".m4v", ".mpg", ".mpeg", ".wmv"})
TIFF_SUFFIXES = frozenset({".tif", ".tiff"})
#: File name endings taken as raw frames (LibRaw's formats, :mod:`hbis_torch.capture.raw`); any other
#: file goes the usual way.
RAW_SUFFIXES = (".dng", ".cr2", ".cr3", ".crw", ".nef", ".nrw", ".arw", ".srf", ".sr2", ".orf", ".rw2", ".raf",
                ".pef", ".srw", ".3fr", ".erf", ".kdc", ".mrw", ".iiq", ".rwl", ".mos", ".dcr", ".mef", ".x3f")
FRAME_DTYPES = (np.dtype(np.uint8), np.dtype(np.uint16), np.dtype(np.float32))
MAX_FILE_PAGES = 100_000
"""The most pages (or video frames) one source may declare."""


@dataclass(frozen=True)
class FrameInfo:
    """What a frame source declares in its headers, before any pixel is decoded.

    Attributes
    ----------
    count : int or None
        Frames (pages) it holds; None where a video's container does not say.
    shape : tuple of int
        One frame: (H, W) or (H, W, 3), pixels.
    dtype : np.dtype
        uint8, uint16 or float32.
    """

    count: int | None
    shape: tuple
    dtype: np.dtype

    @property
    def frame_bytes(self) -> int:
        """Bytes one decoded frame takes."""
        return math.prod(self.shape) * self.dtype.itemsize

    def describe(self) -> str:
        h, w = self.shape[:2]
        kind = "RGB" if len(self.shape) == 3 else "grey"
        return f"{'?' if self.count is None else self.count} frame(s) of {w} x {h} {kind} {self.dtype}"


def _missing(path: Path) -> None:
    if not path.is_file():
        raise HbisInputError(f"{path}: no such file" if not path.exists() else f"{path}: not a file")


# --------------------------------------------------------------------------- probing (headers only)


_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def _png_header(path: Path) -> FrameInfo:
    """A PNG's IHDR: size, bit depth and colour type (16 bytes read)."""
    with open(path, "rb") as f:
        head = f.read(33)
    if len(head) < 33 or head[12:16] != b"IHDR":
        raise HbisInputError(f"{path}: not a readable PNG (no IHDR header)")
    width, height, depth, colour = struct.unpack(">IIBB", head[16:26])
    if width < 1 or height < 1:
        raise HbisInputError(f"{path}: the PNG header declares {width} x {height} pixels")
    grey = colour in (0, 4)  # grey, grey + alpha (colour 3, a palette, decodes to RGB)
    dtype = np.dtype(np.uint16 if depth == 16 else np.uint8)
    return FrameInfo(1, (height, width) if grey else (height, width, 3), dtype)


#: EXIF orientations (tag 274) that show the stored image turned a quarter (width and height swap).
_TURNED = (5, 6, 7, 8)


def _orientation(im) -> int:
    """The EXIF orientation of an open Pillow image (1, as stored, where it has none)."""
    try:
        value = int(im.getexif().get(0x0112, 1))
    except Exception:  # noqa: BLE001 - a damaged EXIF block is no orientation
        return 1
    return value if 1 <= value <= 8 else 1


def upright(image: np.ndarray, orientation: int) -> np.ndarray:
    """An image (H, W) or (H, W, C) as a viewer shows it under its EXIF ``orientation`` (1 to 8:
    as stored, mirrored, turned 180 degrees, flipped, transposed, turned 90 degrees clockwise,
    transversed, turned 90 degrees anticlockwise), as Pillow's ``ImageOps.exif_transpose``."""
    turned = {1: image, 2: image[:, ::-1], 3: image[::-1, ::-1], 4: image[::-1], 5: image.swapaxes(0, 1),
              6: np.rot90(image, -1), 7: image.swapaxes(0, 1)[::-1, ::-1], 8: np.rot90(image, 1)}[orientation]
    return np.ascontiguousarray(turned)


def _pillow_header(path: Path) -> FrameInfo:
    """Size and mode from Pillow, which reads only the header on open."""
    import warnings

    from PIL import Image

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # Pillow's own bomb warning: the limit here is ours
        try:
            with Image.open(path) as im:
                width, height, mode, frames = im.width, im.height, im.mode, getattr(im, "n_frames", 1)
                if _orientation(im) in _TURNED:  # shown turned a quarter: the frame is that way up
                    width, height = height, width
        except Image.DecompressionBombError as exc:
            raise HbisInputError(f"{path}: the image declares too many pixels to decode ({_first_line(exc)})") from None
    if mode in ("I;16", "I;16B", "I;16L", "I"):
        dtype, grey = np.dtype(np.uint16), True
    elif mode == "F":
        dtype, grey = np.dtype(np.float32), True
    else:
        dtype, grey = np.dtype(np.uint8), mode in ("1", "L", "LA")
    if frames != 1:
        raise HbisInputError(f"{path}: holds {frames} images; give one image per file, a multi-page TIFF or a video")
    return FrameInfo(1, (height, width) if grey else (height, width, 3), dtype)


def _tiff_header(path: Path) -> FrameInfo:
    import tifffile

    from hbis_torch.tiff_io import declared_pages, quiet_tifffile

    with quiet_tifffile(), tifffile.TiffFile(path) as tif:
        pages = declared_pages(tif, path, MAX_FILE_PAGES)  # counts, shapes, dtypes, truncation, the limit
        shape, dtype = tuple(int(n) for n in pages[0].shape), pages[0].dtype
        planar = getattr(pages[0], "planarconfig", None) == tifffile.PLANARCONFIG.SEPARATE
    if planar and len(shape) == 3 and shape[0] in (3, 4):
        # tifffile.imwrite(path, frames) stores 3 or 4 grey frames so, unless told otherwise
        raise HbisInputError(f"{path}: a page of {shape[0]} colour planes of {shape[2]} x {shape[1]} px (planar RGB), "
                             f"which is not read; {shape[0]} grey frames go one page each (tifffile.imwrite(path, "
                             "frames, photometric='minisblack')), an RGB frame as (H, W, 3) pixels")
    if len(shape) == 3 and shape[-1] in (1, 4):
        shape = shape[:2] if shape[-1] == 1 else (*shape[:2], 3)
    if dtype == np.float64:
        dtype = np.dtype(np.float32)
    if dtype not in FRAME_DTYPES:
        raise HbisInputError(f"{path}: frame dtype {dtype} is not one of uint8, uint16, float32")
    if not (len(shape) == 2 or (len(shape) == 3 and shape[-1] == 3)):
        raise HbisInputError(f"{path}: a frame must be grayscale (H, W) or RGB (H, W, 3), the pages are {shape}")
    return FrameInfo(len(pages), shape, np.dtype(dtype))


def probe_image(path) -> FrameInfo:
    """What an image file (TIFF, PNG, JPEG, ...) declares, read from its header only."""
    path = Path(path)
    _missing(path)
    try:
        if path.suffix.lower() in TIFF_SUFFIXES:
            return _tiff_header(path)
        with open(path, "rb") as f:
            png = f.read(8) == _PNG_SIGNATURE
        return _png_header(path) if png else _pillow_header(path)
    except HbisInputError:
        raise
    except Exception as exc:  # noqa: BLE001 - image libraries raise many types for bad files
        raise HbisInputError(f"{path}: not a readable image ({type(exc).__name__}: {_first_line(exc)})") from None


def _first_line(exc: BaseException) -> str:
    return (str(exc).splitlines() or [""])[0][:200]


def _import_av(path: Path):
    try:
        import av
    except ImportError:
        raise HbisInputError(f"reading the video {path} needs PyAV: pip install 'hbis-torch[video]' (or av)") from None
    return av


#: Videos of at most this many pixels a frame have their first frame decoded by the probe, for its
#: display rotation (a larger declared frame is the decoding limit's to refuse first).
MAX_TURN_PROBE_PX = 1 << 26


def _quarter_turns(container, stream) -> int:
    """Quarter turns anticlockwise (0 to 3) that show a video's first frame as a player does (its
    display matrix, which phones write for a portrait video); 0 where it has none or does not
    decode (the reading then says why)."""
    try:
        for frame in container.decode(stream):
            return _turns(frame)
    except Exception:  # noqa: BLE001 - FFmpeg raises many types for bad files
        return 0
    return 0


def _turns(frame) -> int:
    """A decoded video frame's display rotation in quarter turns anticlockwise (0 to 3)."""
    return round((getattr(frame, "rotation", 0) or 0) / 90) % 4


def _video_layout(pix_fmt: str | None) -> tuple[bool, np.dtype]:
    """(grey, dtype) of the frames a pixel format decodes to here."""
    fmt = pix_fmt or ""
    deep = any(tag in fmt for tag in ("16", "48", "64", "p10", "p12", "p14"))
    return fmt.startswith("gray"), np.dtype(np.uint16 if deep else np.uint8)


def probe_video(path) -> FrameInfo:
    """What a video file declares in its container and stream headers (nothing decoded).

    The frame count is the stream's, else its duration times its rate, else None (some containers
    do not say: then the decoding limit is enforced while decoding).
    """
    path = Path(path)
    _missing(path)
    av = _import_av(path)
    try:
        with av.open(str(path)) as container:
            if not container.streams.video:
                raise HbisInputError(f"{path}: holds no video stream")
            stream = container.streams.video[0]
            cc = stream.codec_context
            width, height, pix_fmt = int(cc.width or 0), int(cc.height or 0), cc.pix_fmt
            count = int(stream.frames or 0)
            if not count and stream.duration and stream.average_rate:
                count = round(float(stream.duration * stream.time_base * stream.average_rate))
            if 0 < width * height <= MAX_TURN_PROBE_PX and _quarter_turns(container, stream) % 2:
                width, height = height, width  # a phone's portrait video: shown turned a quarter
    except HbisInputError:
        raise
    except Exception as exc:  # noqa: BLE001 - FFmpeg raises many types for bad files
        raise HbisInputError(f"{path}: not a readable video ({type(exc).__name__}: {_first_line(exc)})") from None
    if width < 1 or height < 1:
        raise HbisInputError(f"{path}: the video stream declares {width} x {height} pixels")
    grey, dtype = _video_layout(pix_fmt)
    if count > MAX_FILE_PAGES:
        raise HbisInputError(f"{path}: the video declares {count} frames, more than {MAX_FILE_PAGES}")
    return FrameInfo(count or None, (height, width) if grey else (height, width, 3), dtype)


def is_video(path) -> bool:
    return Path(path).suffix.lower() in VIDEO_SUFFIXES


def probe_source(path) -> FrameInfo:
    """What one frame source (an image file, a multi-page TIFF, a video) declares."""
    return probe_video(path) if is_video(path) else probe_image(path)


def check_decoded_size(infos, names, limit: int | None = None) -> int:
    """Refuse frames that would take more than ``limit`` bytes once decoded (default
    ``HBIS_MAX_STACK_MB``), from the headers; returns the bytes declared."""
    from hbis_torch.tiff_io import max_decoded_bytes

    limit = max_decoded_bytes() if limit is None else limit
    total = 0
    for info, name in zip(infos, names):
        total += (info.count or 1) * info.frame_bytes
        if total > limit:
            raise HbisInputError(
                f"{name}: the frames declare {total / 2**20:.0f} MiB once decoded ({info.describe()} here), "
                f"over the limit of {limit / 2**20:.0f} MiB (raise it with the environment variable HBIS_MAX_STACK_MB)")
    return total


# --------------------------------------------------------------------------- decoding


def _as_frame(array: np.ndarray, where: str) -> np.ndarray:
    """One frame as (H, W) or (H, W, 3); alpha dropped; float64 stored as float32."""
    array = np.asarray(array)
    if array.ndim == 3 and array.shape[-1] == 4:
        array = array[..., :3]
    if array.ndim == 3 and array.shape[-1] == 2:  # grey + alpha
        array = array[..., 0]
    if array.ndim == 3 and array.shape[-1] == 1:
        array = array[..., 0]
    if not (array.ndim == 2 or (array.ndim == 3 and array.shape[-1] == 3)):
        raise HbisInputError(f"{where}: a frame must be grayscale (H, W) or RGB (H, W, 3), got shape {array.shape}")
    if array.dtype == np.float64:
        array = array.astype(np.float32)
    if array.dtype == bool:
        array = array.astype(np.uint8) * 255
    if array.dtype not in FRAME_DTYPES:
        raise HbisInputError(f"{where}: frame dtype {array.dtype} is not one of uint8, uint16, float32")
    return array


def read_image(path) -> np.ndarray:
    """The pages of one image file, (P, H, W) or (P, H, W, 3) (P = 1 except multi-page TIFFs).

    The header is checked first (:func:`probe_image`, the decoding limit); then the pixels are
    decoded and must have the size the header declared.
    """
    path = Path(path)
    info = probe_image(path)
    check_decoded_size([info], [str(path)])
    try:
        if path.suffix.lower() in TIFF_SUFFIXES:
            import tifffile

            from hbis_torch.tiff_io import quiet_tifffile

            with quiet_tifffile(), tifffile.TiffFile(path) as tif:
                pages = [p.asarray() for p in tif.pages]
        else:
            pages = [_decode_other(path)]
    except HbisInputError:
        raise
    except MemoryError:
        raise HbisInputError(f"{path}: not enough memory to decode it") from None
    except Exception as exc:  # noqa: BLE001 - image libraries raise many types for bad files
        raise HbisInputError(f"{path}: not a readable image ({type(exc).__name__}: {_first_line(exc)})") from None
    frames = [_as_frame(p, str(path)) for p in pages]
    if len({(f.shape, f.dtype) for f in frames}) != 1:
        raise HbisInputError(f"{path}: its pages differ in size or dtype")
    if frames[0].shape[:2] != info.shape[:2]:
        raise HbisInputError(f"{path}: decoded {frames[0].shape[1]} x {frames[0].shape[0]} pixels, but its header "
                             f"declares {info.shape[1]} x {info.shape[0]}")
    return np.stack(frames)


def _decode_other(path: Path) -> np.ndarray:
    try:
        import cv2
    except ImportError:
        cv2 = None
    import warnings

    from PIL import Image

    with open(path, "rb") as f:  # (a PNG's orientation is not read: its header is parsed here, not by Pillow)
        png = f.read(8) == _PNG_SIGNATURE
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with Image.open(path) as im:
            orientation = 1 if png else _orientation(im)
            if cv2 is None:
                if im.mode in ("I", "I;16", "I;16B", "I;16L"):
                    return upright(np.asarray(im).astype(np.uint16), orientation)
                if im.mode not in ("L", "RGB", "RGBA", "F"):
                    im = im.convert("RGB")
                return upright(np.asarray(im), orientation)
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)  # (which leaves the EXIF orientation to us)
    if image is None:
        raise ValueError("OpenCV cannot decode it")
    if image.ndim == 3:
        image = cv2.cvtColor(image, cv2.COLOR_BGRA2RGBA if image.shape[-1] == 4 else cv2.COLOR_BGR2RGB)
    return upright(image, orientation)


def read_video(path, count: int | None = None, info: FrameInfo | None = None) -> np.ndarray:
    """Frames of a video file with PyAV, (F, H, W) when every frame is grey (equal R, G, B),
    else (F, H, W, 3) RGB.

    The headers are checked first (:func:`probe_video`, the decoding limit); a stream that holds
    more frames, or frames of another size, than it declared is refused while decoding.
    ``count``: read at most this many frames (None: all).
    """
    from hbis_torch.tiff_io import max_decoded_bytes

    path = Path(path)
    info = info or probe_video(path)
    check_decoded_size([FrameInfo(min(info.count or 1, count or MAX_FILE_PAGES), info.shape, info.dtype)], [str(path)])
    av = _import_av(path)
    grey, dtype = len(info.shape) == 2, info.dtype
    fmt = ("gray16le" if grey else "rgb48le") if dtype == np.uint16 else ("gray" if grey else "rgb24")
    limit, frames = max_decoded_bytes(), []
    try:
        with av.open(str(path)) as container:
            for frame in container.decode(container.streams.video[0]):
                turns = _turns(frame)  # shown as a player shows it (a phone's portrait video)
                shown = (frame.width, frame.height) if turns % 2 else (frame.height, frame.width)
                if shown != info.shape[:2]:
                    raise HbisInputError(f"{path}: frame {len(frames)} is {shown[1]} x {shown[0]}, but the "
                                         f"stream declares {info.shape[1]} x {info.shape[0]}")
                if (len(frames) + 1) * info.frame_bytes > limit or len(frames) >= MAX_FILE_PAGES:
                    raise HbisInputError(f"{path}: the video holds more than {len(frames)} frames, over the limit "
                                         f"of {limit / 2**20:.0f} MiB (raise it with HBIS_MAX_STACK_MB)")
                image = frame.to_ndarray(format=fmt)
                frames.append(np.ascontiguousarray(np.rot90(image, turns)) if turns else image)
                if count is not None and len(frames) >= count:
                    break
    except HbisInputError:
        raise
    except MemoryError:
        raise HbisInputError(f"{path}: not enough memory to decode it") from None
    except Exception as exc:  # noqa: BLE001 - FFmpeg raises many types for bad files
        if not frames:
            raise HbisInputError(f"{path}: not a readable video ({type(exc).__name__}: {_first_line(exc)})") from None
        raise HbisInputError(f"{path}: the video is damaged after frame {len(frames) - 1} "
                             f"({type(exc).__name__}: {_first_line(exc)})") from None
    if not frames:
        raise HbisInputError(f"{path}: the video holds no frame that can be decoded")
    return rgb_frames(np.stack(frames))


def rgb_frames(frames: np.ndarray) -> np.ndarray:
    """RGB frames (F, H, W, 3) as grey (F, H, W) when all three channels are equal."""
    if frames.ndim == 4 and frames.shape[-1] == 3:
        if (frames[..., 0] == frames[..., 1]).all() and (frames[..., 1] == frames[..., 2]).all():
            return np.ascontiguousarray(frames[..., 0])
    return frames


def bgr_frames(frames: np.ndarray) -> np.ndarray:
    """OpenCV's BGR frames (F, H, W, 3) as RGB, or as gray (F, H, W) when all three are equal."""
    if frames.ndim == 4 and frames.shape[-1] == 3:
        return rgb_frames(np.ascontiguousarray(frames[..., ::-1]))
    return frames


def pattern_paths(pattern: str, count: int) -> list[Path]:
    """The files ``pattern.format(index=k)`` for k = 0 .. count - 1 (``{index:03d}`` works too)."""
    try:
        return [Path(pattern.format(index=k)) for k in range(count)]
    except (KeyError, IndexError, ValueError):
        raise HbisInputError(f"frame pattern {pattern!r} may only use {{index}} (e.g. frame_{{index:03d}}.tif)") from None


#: Image files a folder given as frames contributes (besides TIFFs and raw frames).
IMAGE_SUFFIXES = frozenset({".png", ".jpg", ".jpeg", ".bmp", ".webp", ".pgm", ".ppm", ".pnm", ".jp2", ".tga"})


def expand_sources(sources) -> list[str]:
    """Frame sources as given, each folder replaced by its frame files (images, TIFFs and raw
    frames, in name order with numbers compared as numbers: f2 before f10) and each wildcard
    (``*``, ``?``, ``[``) that names no file by the files it matches, in the same order (a shell
    that does not expand it, as Windows' does not, passes it on).

    Raises
    ------
    HbisInputError
        A folder that holds no frame file, or a wildcard that matches none.
    """
    import glob
    import re

    def in_order(paths):
        return sorted(paths, key=lambda p: [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", str(p))])

    out = []
    for source in map(str, sources):
        path = Path(source)
        if path.is_dir():
            kinds = IMAGE_SUFFIXES | TIFF_SUFFIXES | set(RAW_SUFFIXES)
            files = [f for f in path.iterdir()
                     if f.is_file() and f.suffix.lower() in kinds and not f.name.startswith(".")]
            if not files:
                raise HbisInputError(f"{source}: a folder that holds no frame file (images, TIFFs or raw frames; "
                                     "give a video by its name)")
            out += [str(f) for f in in_order(files)]
        elif not path.exists() and not is_pattern(source) and any(c in source for c in "*?["):
            files = [f for f in glob.glob(source) if Path(f).is_file()]
            if not files:
                raise HbisInputError(f"{source}: matches no file")
            out += in_order(files)
        else:
            out.append(source)
    return out


def is_pattern(text: str) -> bool:
    return "{index" in str(text)


def _source_paths(sources: list[str], count: int | None) -> list[Path]:
    if len(sources) == 1 and is_pattern(sources[0]):
        if count is None:
            raise HbisInputError("a frame pattern needs the number of frames (h^2 from the phases file)")
        return pattern_paths(sources[0], count)
    return [Path(s) for s in sources]


def probe_frames(sources, count: int | None = None) -> tuple[FrameInfo, list[Path], list[FrameInfo]]:
    """Probe every frame source (headers only) and check that they agree and fit the limit.

    Parameters
    ----------
    sources, count
        As for :func:`read_frames`.

    Returns
    -------
    total : FrameInfo
        All frames together: their count (None where a video does not say), size and dtype.
    paths : list of Path
        The files, in order.
    infos : list of FrameInfo
        What each file declares.
    """
    sources = [str(s) for s in sources]
    if not sources:
        raise HbisInputError("no frames given")
    paths = _source_paths(sources, count)
    if len(paths) > MAX_FILE_PAGES:
        raise HbisInputError(f"{len(paths)} frame files, more than {MAX_FILE_PAGES}")
    if len(paths) > 1:
        for p in paths:
            if is_video(p):
                raise HbisInputError(f"{p}: a video holds many frames; give it alone")
    infos = []
    for path in paths:
        info = probe_source(path)
        if len(paths) > 1 and (info.count or 1) > 1:
            raise HbisInputError(f"{path}: holds {info.count} pages; give one multi-page TIFF alone, "
                                 "or one file per frame")
        if infos and (info.shape, info.dtype) != (infos[0].shape, infos[0].dtype):
            first = infos[0]
            raise HbisInputError(f"{path}: its header declares {info.describe().split(' of ', 1)[1]}, but {paths[0]} "
                                 f"holds {first.describe().split(' of ', 1)[1]}: all frames must have one size and dtype")
        infos.append(info)
    check_decoded_size(infos, [str(p) for p in paths])
    counts = [i.count for i in infos]
    total = None if None in counts else sum(counts)
    return FrameInfo(total, infos[0].shape, infos[0].dtype), paths, infos


def read_frames(sources, count: int | None = None) -> tuple[np.ndarray, list[str]]:
    """Frames in scan order from files, a ``{index}`` pattern, a multi-page TIFF or a video.

    Every source's header is read first (:func:`probe_frames`): sizes, dtypes and the decoding
    limit are checked before any pixel is decoded.

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
    _, paths, infos = probe_frames(sources, count)
    if len(paths) == 1 and is_video(paths[0]):
        frames = read_video(paths[0], info=infos[0])
        return frames, [f"{paths[0]} frame {k}" for k in range(len(frames))]
    frames, names = [], []
    for path in paths:
        pages = read_image(path)
        frames.extend(pages)
        names.extend([str(path)] if len(pages) == 1 else [f"{path} page {k}" for k in range(len(pages))])
    first = frames[0]
    for frame, name in zip(frames, names):
        if frame.shape != first.shape:
            raise HbisInputError(f"{name}: frame of shape {frame.shape}, but {names[0]} has {first.shape}")
        if frame.dtype != first.dtype:
            raise HbisInputError(f"{name}: frame of dtype {frame.dtype}, but {names[0]} has {first.dtype}")
    return np.stack(frames), names


def bit_depth_hint(frames: np.ndarray) -> str | None:
    """A line for 16-bit frames whose values use at most 14 bits: a camera of 10 to 14 bits
    written to a 16-bit file, whose white the stack would otherwise put at 65535. The classical
    step follows the level; the learned method finds the noise outside its range and returns the
    classical image (8-bit values read as 16-bit, a simulated burst of 8 frames at S = 2: 32.83
    against 33.75 dB with the bit depth given), and a viewer shows the frames nearly black."""
    if frames.dtype != np.uint16:
        return None
    top = int(frames.max())
    bits = max(top.bit_length(), 1)
    if bits > 14:
        return None
    return act(f"the frames' values reach {top}, {bits} of the 16 bits their type holds: if the camera "
            f"records {bits} bits, pass --bit-depth {bits} (the stack maps 65535 to white)")
