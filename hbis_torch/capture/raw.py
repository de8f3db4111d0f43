"""Raw camera frames (DNG and what LibRaw reads) -> one raw-Bayer burst stack.

A raw frame is the sensor's own mosaic: one colour per pixel under a 2 x 2 Bayer pattern
(RGGB, BGGR, GRBG, GBRG), before any demosaicking, white balance or tone curve. LibRaw (through
``rawpy``, the optional extra ``[raw]``) reads DNG and most cameras' raw formats; a DNG's own tags
(noise profile, camera, exposure) are read with tifffile.

What :func:`read_raw` keeps of each file (:class:`RawFrame`): the visible mosaic (uint16), the
pattern, the black level of each of the four pattern positions, the white level, the as-shot white
balance, the camera -> sRGB colour matrix, the orientation, the camera's name, the exposure time
and ISO, and the DNG noise profile.

:func:`check_raw_frames` reads the burst's metadata together before any work: a frame of another
size, pattern or camera is refused in one line; what has a safe default is used with a warning
that names it (no white balance: the daylight one, else none; no colour matrix: the camera's
RGB taken as sRGB; mixed orientations: the reference's); frames of different exposures, ISO or
levels are normalised to the reference's and said so.

:func:`assemble_raw_burst` registers the frames on the luminance of each 2 x 2 cell (a quarter
of the pixels, one value per cell: the white-balanced mean of its four samples) with
:func:`~hbis_torch.capture.burst.register_burst` (its homographies and, on frames large enough,
its local shifts, both carried from the cells' grid to the pixels': cell (x, y) is pixel
(2 x + 0.5, 2 y + 0.5), so a shift doubles and so does a tile), and writes the mosaics unchanged
(uint16) in a
burst stack with a ``cfa`` key and a ``raw`` block (docs/raw-bursts.md), which
:mod:`hbis_torch.reconstruct.classical.raw_burst` demosaicks and super-resolves jointly.

Units: a *normalised* sample is ``gain * (raw - black) / (white - black)`` (1 at the white
level for the reference's exposure); positions and motions in full-resolution pixels, frame px
-> reference px, pixel centres at integers.
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
from pathlib import Path

import numpy as np

from hbis_torch.capture.frames import RAW_SUFFIXES
from hbis_torch.capture.sharpness import SHARPEST, choose_reference
from hbis_torch.errors import HbisInputError
from hbis_torch.notices import act

#: A normalised sample at or above this (before the exposure gain) is clipped (saturated).
CLIP_LEVEL = 0.99
#: LibRaw's orientation codes (``sizes.flip``) by name.
ORIENTATIONS = {0: "as recorded", 3: "rotated 180 deg", 5: "rotated 90 deg counter-clockwise",
                6: "rotated 90 deg clockwise"}
RAW_HINT = "pip install 'hbis-torch[raw]' (rawpy)"


@dataclasses.dataclass
class RawFrame:
    """What one raw file holds (:func:`read_raw`).

    Attributes
    ----------
    name : str
    mosaic : np.ndarray, shape (H, W), uint16
        The visible area of the sensor, as recorded.
    cfa : str
        The pattern of the top-left 2 x 2 pixels, e.g. ``"RGGB"``.
    black : np.ndarray, shape (2, 2), float64
        Black level of each pattern position (raw units).
    white : float
        White (saturation) level, raw units.
    white_balance : np.ndarray, shape (3,), or None
        As-shot multipliers (R, G, B), G = 1; None where the file has none.
    colour_matrix : np.ndarray, shape (3, 3), or None
        Linear sRGB from white-balanced camera RGB (LibRaw's ``rgb_cam``); None where the file
        has none.
    orientation : int
        LibRaw's ``flip`` (0, 3, 5, 6: :data:`ORIENTATIONS`).
    camera : str or None
    exposure_s, iso : float or None
    noise_profile : np.ndarray, shape (3, 2), or None
        DNG NoiseProfile: variance ``S x + O`` of a normalised sample x, per colour (R, G, B).
    daylight_balance : np.ndarray, shape (3,), or None
    """

    name: str
    mosaic: np.ndarray
    cfa: str
    black: np.ndarray
    white: float
    white_balance: np.ndarray | None
    colour_matrix: np.ndarray | None
    orientation: int
    camera: str | None
    exposure_s: float | None
    iso: float | None
    noise_profile: np.ndarray | None
    daylight_balance: np.ndarray | None = None


def import_rawpy(what: str = "reading raw frames"):
    """rawpy, or one clear HbisInputError saying how to install it."""
    try:
        import rawpy
    except ImportError:
        raise HbisInputError(f"{what} needs rawpy (LibRaw): {RAW_HINT}") from None
    return rawpy


def is_raw_path(path) -> bool:
    """Whether ``path`` names a raw file by its ending (:data:`RAW_SUFFIXES`)."""
    return Path(str(path)).suffix.lower() in RAW_SUFFIXES


def is_raw_burst(paths) -> bool:
    """Whether a list of frame paths is raw frames (every one ends as a raw file does); a list
    that mixes raw and other files is refused in one line."""
    raw = [is_raw_path(p) for p in paths]
    if any(raw) and not all(raw):
        first = next(str(p) for p, r in zip(paths, raw) if not r)
        raise HbisInputError(f"{first} is not a raw file, but other frames are: a burst is all raw frames or none")
    return bool(raw) and all(raw)


@contextlib.contextmanager
def _quiet_stderr():
    """LibRaw writes its own lines ("Unexpected end of file") to the C stderr: keep them off the
    terminal, so that the one line saying what went wrong is ours."""
    try:
        fd = os.dup(2)
    except OSError:  # no stderr to silence
        yield
        return
    try:
        with open(os.devnull, "wb") as null:
            os.dup2(null.fileno(), 2)
            yield
    finally:
        os.dup2(fd, 2)
        os.close(fd)


def _dng_tags(path) -> dict:
    """The DNG tags LibRaw does not hand on (camera, exposure, ISO, noise profile, whether a
    colour matrix is present), read with tifffile; {} for other files."""
    import tifffile

    tags = {}
    try:
        with tifffile.TiffFile(path) as tif:
            for tag in tif.pages[0].tags.values():
                tags[tag.code] = tag.value
            exif = tags.get(34665)
            if isinstance(exif, dict):
                tags.update({("exif", k): v for k, v in exif.items()})
    except Exception:  # not a TIFF-based file (or a damaged one, which LibRaw reports)
        return {}
    return tags


def _rational(value) -> float | None:
    try:
        values = np.asarray(value, dtype=np.float64).ravel()
    except (TypeError, ValueError):
        return None
    if values.size == 2 and values[1] != 0:
        return float(values[0] / values[1])
    if values.size == 1 and np.isfinite(values[0]):
        return float(values[0])
    return None


def raw_size(path) -> tuple[int, int] | None:
    """The visible (height, width) of a raw file from its header (LibRaw opens it without
    unpacking the pixels); None where LibRaw cannot open it (:func:`read_raw` says why)."""
    rawpy = import_rawpy()
    raw = rawpy.RawPy()
    try:
        with _quiet_stderr():
            raw.open_file(str(path))
        return int(raw.sizes.height), int(raw.sizes.width)
    except rawpy.LibRawError:
        return None
    finally:
        raw.close()


def read_raw(path) -> RawFrame:
    """Read one raw file (LibRaw through rawpy), refusing in one line what cannot be used.

    Parameters
    ----------
    path : str or Path

    Returns
    -------
    RawFrame

    Raises
    ------
    HbisInputError
        A file LibRaw cannot read (not raw, truncated, damaged), a sensor that is not a 2 x 2
        Bayer mosaic (X-Trans, four colours, Foveon), or levels that contradict each other.
    """
    rawpy = import_rawpy()
    path = Path(path)
    if not path.is_file():
        raise HbisInputError(f"{path}: no such file")
    try:
        with _quiet_stderr(), rawpy.imread(str(path)) as raw:
            mosaic = np.array(raw.raw_image_visible, dtype=np.uint16, copy=True)
            colours = np.array(raw.raw_colors_visible[:2, :2])
            desc = raw.color_desc.decode("ascii", "replace")
            num_colors = int(raw.num_colors)
            black_by_colour = list(raw.black_level_per_channel)
            white = float(raw.white_level)
            wb = np.array(raw.camera_whitebalance, dtype=np.float64)
            daylight = np.array(raw.daylight_whitebalance, dtype=np.float64)
            matrix = np.array(raw.color_matrix, dtype=np.float64)[:, :3]
            flip = int(raw.sizes.flip)
            other = raw.other if hasattr(raw, "other") else None
            pattern = raw.raw_pattern
    except rawpy.LibRawError as error:
        reason = str(error).strip("b'\"") or type(error).__name__
        raise HbisInputError(f"{path}: not a raw file LibRaw can read (truncated or damaged?): {reason}") from None
    if pattern is None or np.shape(pattern) != (2, 2) or num_colors != 3 or set(desc[:3]) != set("RGB"):
        raise HbisInputError(f"{path}: the sensor is not a 2 x 2 Bayer mosaic (colours {desc!r}, pattern "
                             f"{np.shape(pattern) if pattern is not None else None}): only Bayer raw frames are read")
    cfa = "".join(desc[int(c)] for c in colours.ravel())
    if sorted(cfa) != sorted("RGGB"):
        raise HbisInputError(f"{path}: the pattern {cfa} is not one of RGGB, BGGR, GRBG, GBRG")
    if mosaic.ndim != 2 or min(mosaic.shape) < 2:
        raise HbisInputError(f"{path}: the mosaic's shape {mosaic.shape} is not an image")
    black = np.array([[black_by_colour[int(c)] for c in row] for row in colours], dtype=np.float64)
    if not white > float(black.max()):
        raise HbisInputError(f"{path}: the white level {white:g} is not above the black level {black.max():g}")
    tags = _dng_tags(path) if path.suffix.lower() == ".dng" else {}

    def balance(values):
        values = values[:3]
        if not (np.isfinite(values).all() and (values > 0).all()):
            return None
        return values / values[1]

    colour_matrix = matrix if np.isfinite(matrix).all() and np.abs(matrix).sum() > 0 else None
    if tags and 50721 not in tags:  # a DNG without ColorMatrix1: LibRaw may fill in its own table
        colour_matrix = None
    camera = None
    if tags:
        make, model = str(tags.get(271, "")).strip(), str(tags.get(272, "")).strip()
        camera = str(tags.get(50708, "")).strip() or f"{make} {model}".strip() or None
    exposure = _rational(tags.get(33434, tags.get(("exif", "ExposureTime")))) if tags else None
    iso = _rational(tags.get(34855, tags.get(("exif", "ISOSpeedRatings")))) if tags else None
    if other is not None:
        exposure = exposure or (float(other.shutter_speed) or None)
        iso = iso or (float(other.iso_speed) or None)
    noise = None
    if 51041 in tags:
        values = np.asarray(tags[51041], dtype=np.float64).ravel()
        if values.size == 2:
            values = np.tile(values, 3)
        if values.size == 6 and np.isfinite(values).all() and (values >= 0).all() and (values[0::2] > 0).any():
            noise = values.reshape(3, 2)
    return RawFrame(path.name, mosaic, cfa, black, white, balance(wb), colour_matrix, flip, camera,
                    exposure, iso, noise, balance(daylight))


def check_raw_frames(frames: list, reference: int = 0) -> tuple[dict, np.ndarray, list]:
    """Check a burst's raw frames against each other and the reference, before any work.

    Parameters
    ----------
    frames : list of RawFrame
    reference : int

    Returns
    -------
    raw : dict
        The stack's ``raw`` block: ``black`` (F, 2, 2) and ``white`` (F,) of each frame,
        ``gain`` (F,) (each frame's exposure x ISO relative to the reference's, 1 where unknown),
        ``white_balance`` (3,), ``colour_matrix`` (3, 3), ``orientation``, ``camera``,
        ``exposure_s``, ``iso``, ``noise_profile`` ((3, 2) or None), ``clip_level``, ``files``;
        :func:`raw_burst_stack` adds ``grey_scale`` (the registration luminance's unit).
    gain : np.ndarray, shape (F,)
    messages : list of str
        The warnings (each naming the default used) and the normalisations.

    Raises
    ------
    HbisInputError
        Frames of another size, pattern or camera than the reference's.
    """
    ref = frames[reference]
    messages: list[str] = []
    for k, f in enumerate(frames):
        if f.mosaic.shape != ref.mosaic.shape:
            raise HbisInputError(f"frame {k} ({f.name}) is {f.mosaic.shape[1]} x {f.mosaic.shape[0]}, the reference "
                                 f"{ref.mosaic.shape[1]} x {ref.mosaic.shape[0]}: one burst, one sensor size")
        if f.cfa != ref.cfa:
            raise HbisInputError(f"frame {k} ({f.name}) has the pattern {f.cfa}, the reference {ref.cfa}: "
                                 "one burst, one sensor")
        if f.camera and ref.camera and f.camera != ref.camera:
            raise HbisInputError(f"frame {k} ({f.name}) is from '{f.camera}', the reference from '{ref.camera}': "
                                 "frames of different cameras are not one burst")
    levels = [k for k, f in enumerate(frames) if f.white != ref.white or not np.array_equal(f.black, ref.black)]
    if levels:
        messages.append(act(f"frame(s) {levels} have black or white levels of their own: each frame is normalised by "
                        "its own levels"))
    gain = np.ones(len(frames))
    known = all(f.exposure_s and f.iso for f in frames)
    if known:
        product = np.array([f.exposure_s * f.iso for f in frames])
        gain = product[reference] / product
        if not np.allclose(gain, 1.0, rtol=1e-3):
            differ = [k for k in range(len(frames)) if abs(gain[k] - 1) > 1e-3]
            messages.append(act(f"frame(s) {differ} were exposed differently (exposure x ISO): each is scaled to the "
                            "reference's exposure; their clipped samples are left out"))
    elif any(f.exposure_s for f in frames) and len({f.exposure_s for f in frames}) > 1:
        messages.append(act("some frames do not record their exposure: brightness differences are matched from the "
                        "data (the registration's gain and offset)"))
    balance = ref.white_balance
    if balance is None:
        if ref.daylight_balance is not None:
            balance = ref.daylight_balance
            messages.append(act(f"the reference frame ({ref.name}) records no white balance: the camera's daylight "
                            f"balance {np.round(balance, 3).tolist()} is used"))
        else:
            balance = np.ones(3)
            messages.append(act(f"the reference frame ({ref.name}) records no white balance: none is applied "
                            "(multipliers 1, 1, 1)"))
    matrix = ref.colour_matrix
    if matrix is None:
        matrix = np.eye(3)
        messages.append(act(f"the reference frame ({ref.name}) records no colour matrix: the camera's RGB is taken as "
                        "linear sRGB (the identity), so colours are the sensor's own"))
    flips = sorted({f.orientation for f in frames})
    if len(flips) > 1:
        odd = [k for k, f in enumerate(frames) if f.orientation != ref.orientation]
        messages.append(act(f"frame(s) {odd} record another orientation than the reference's "
                        f"({ORIENTATIONS.get(ref.orientation, ref.orientation)}): the mosaics are all as the sensor "
                        "recorded them, so they are registered as they are and the output takes the reference's"))
    over = [k for k, f in enumerate(frames) if int(f.mosaic.max()) > f.white]
    if over:
        messages.append(act(f"frame(s) {over} hold values above their white level ({frames[over[0]].white:g}): those "
                        "samples are taken as clipped"))
    raw = {"black": np.stack([f.black for f in frames]).tolist(), "white": [float(f.white) for f in frames],
           "gain": gain.tolist(), "white_balance": np.asarray(balance, dtype=np.float64).tolist(),
           "colour_matrix": np.asarray(matrix, dtype=np.float64).tolist(), "orientation": int(ref.orientation),
           "camera": ref.camera, "exposure_s": ref.exposure_s, "iso": ref.iso,
           "noise_profile": None if ref.noise_profile is None else ref.noise_profile.tolist(),
           "clip_level": CLIP_LEVEL, "files": [f.name for f in frames]}
    return raw, gain, messages


def normalised(mosaics: np.ndarray, raw: dict) -> tuple[np.ndarray, np.ndarray]:
    """Raw mosaics -> normalised samples and where they clipped.

    Parameters
    ----------
    mosaics : np.ndarray, shape (F, H, W), uint16
        As recorded (the pattern's top-left at (0, 0)).
    raw : dict
        The stack's ``raw`` block (:func:`check_raw_frames`): ``black`` (F, 2, 2), ``white`` (F,),
        ``gain`` (F,), ``clip_level``.

    Returns
    -------
    values : np.ndarray, shape (F, H, W), float32
        ``gain * (raw - black) / (white - black)``, not clipped (noise below black stays
        negative, so that averages keep no bias).
    clipped : np.ndarray, shape (F, H, W), bool
        Samples at or above the clip level of their own frame (before the gain).
    """
    F, H, W = mosaics.shape
    black = np.asarray(raw["black"], dtype=np.float32)
    white = np.asarray(raw["white"], dtype=np.float32)
    gain = np.asarray(raw["gain"], dtype=np.float32)
    clip = float(raw.get("clip_level", CLIP_LEVEL))
    values = np.empty((F, H, W), dtype=np.float32)
    clipped = np.empty((F, H, W), dtype=bool)
    # a frame at a time: no (F, H, W) temporaries beside the result (a 12 MP burst of 16 frames
    # held four of 768 MB each), the same float32 arithmetic
    for k in range(F):
        tiled = np.tile(black[k], ((H + 1) // 2, (W + 1) // 2))[:H, :W]
        level = mosaics[k].astype(np.float32)
        np.divide(level - tiled, white[k] - tiled, out=values[k])
        np.greater_equal(values[k], clip, out=clipped[k])
        clipped[k] |= level >= white[k]
        values[k] *= gain[k]
    return values, clipped


def shifted_cfa(cfa: str, dv: int, du: int) -> str:
    """The pattern of a crop starting ``dv`` rows and ``du`` columns into one of pattern ``cfa``."""
    grid = np.array(list(cfa)).reshape(2, 2)
    return "".join(np.roll(grid, (-(dv % 2), -(du % 2)), axis=(0, 1)).ravel())


def cell_luminance(values: np.ndarray, cfa: str, balance) -> np.ndarray:
    """The luminance of each 2 x 2 cell: the white-balanced mean of its four samples.

    Parameters
    ----------
    values : np.ndarray, shape (F, H, W), float32
        Normalised samples; H and W even.
    cfa : str
    balance : sequence of 3 floats
        White-balance multipliers (R, G, B).

    Returns
    -------
    np.ndarray, shape (F, H/2, W/2), float32
        Where the cell (i, j) is centred on the full-resolution point (2 j + 0.5, 2 i + 0.5).
    """
    wb = np.asarray(balance, dtype=np.float32)
    total = 0
    for k, colour in enumerate(cfa):
        total = total + wb["RGB".index(colour)] * values[:, k // 2::2, k % 2::2]
    return (total / 4).astype(np.float32)


def registration_grey(values: np.ndarray, cfa: str, balance, reference: int = 0,
                      clipped: np.ndarray | None = None) -> tuple[np.ndarray, float]:
    """:func:`cell_luminance` scaled into [0, 1] for the registration: (F, H/2, W/2) float32,
    the reference's 99.9th percentile at 1, clipped; and that scale (luminance units). A cell
    with a clipped sample (``clipped`` (F, H, W) bool) is set to 1, saturated, so that the
    registration's brightness fit leaves it out (a clipped sample, scaled by its frame's exposure
    gain, is darker than the scene)."""
    grey = cell_luminance(values, cfa, balance)
    top = max(float(np.percentile(grey[reference], 99.9)), 1e-6)
    grey = np.clip(grey / top, 0, 1)
    if clipped is not None:
        F, H, W = clipped.shape
        grey[clipped.reshape(F, H // 2, 2, W // 2, 2).any(axis=(2, 4))] = 1.0
    return grey.astype(np.float32), top


def centre_cells(values: np.ndarray):
    """The mean of each 2 x 2 cell of the mosaics' (F, H, W) centre, whatever their colours, a
    luminance to compare the frames' sharpness by: (F, h, w) float32 Tensor, the cells of the
    central square that :func:`~hbis_torch.capture.sharpness.frame_sharpness` reads (a 12 MP
    burst's are not all made). The mosaics may be raw levels or normalised values: the sharpness
    is the same for both."""
    import torch

    from hbis_torch.capture.sharpness import CENTRE_PX

    F, H, W = values.shape
    rows, cols = min(H // 2, CENTRE_PX), min(W // 2, CENTRE_PX)
    top, left = (H // 2 - rows) // 2 * 2, (W // 2 - cols) // 2 * 2  # even: whole cells of the pattern
    centre = values[:, top:top + 2 * rows, left:left + 2 * cols]
    return torch.from_numpy(centre.reshape(F, rows, 2, cols, 2).mean(axis=(2, 4)).astype(np.float32))


def assemble_raw_burst(paths, scale: int, reference: int = 0, motion: str = "auto", roi=None,
                       bit_depth: int | None = None) -> tuple:
    """Read raw frames, check them together, register them and build a raw burst stack.

    Parameters
    ----------
    paths : list of str or Path
        Raw files (:data:`RAW_SUFFIXES`), in capture order; at least 2.
    scale : int
        Output scale S (1..16; 1 is a burst demosaick).
    reference : int
    motion : str
        One of :data:`hbis_torch.capture.burst.MOTIONS`.
    roi : (u0, v0, width, height) or None
        Cut the frames first (the pattern follows the cut; odd sizes lose their last row or column).
    bit_depth : int or None
        Refused: a raw file's levels come from its metadata.

    Returns
    -------
    stack : hbis_torch.stack_io.Stack
        Burst stack of the uint16 mosaics with ``cfa`` and ``raw`` keys.
    messages : list of str
    """
    from hbis_torch.capture.burst import MAX_BURST_FRAMES, MOTIONS
    from hbis_torch.checks import MAX_H

    paths = [Path(p) for p in paths]
    if bit_depth is not None:
        raise HbisInputError("--bit-depth does not apply to raw frames: their black and white levels are read "
                             "from each file")
    if not 2 <= len(paths) <= MAX_BURST_FRAMES:
        raise HbisInputError(f"a burst needs 2 to {MAX_BURST_FRAMES} frames, got {len(paths)}")
    if isinstance(scale, bool) or not isinstance(scale, (int, np.integer)) or not 1 <= scale <= MAX_H:
        raise HbisInputError(f"--scale must be an integer from 1 to {MAX_H}, got {scale!r}")
    if reference != SHARPEST and (isinstance(reference, bool) or not isinstance(reference, (int, np.integer))
                                  or not 0 <= reference < len(paths)):
        raise HbisInputError(f"--reference {reference!r} is neither a frame index (0..{len(paths) - 1}) "
                             f"nor '{SHARPEST}'")
    if motion not in MOTIONS:
        raise HbisInputError(f"--motion must be one of {', '.join(MOTIONS)}, got {motion!r}")
    missing = [str(p) for p in paths if not p.is_file()]
    if missing:
        raise HbisInputError(f"{missing[0]}: no such file")
    frames = [read_raw(p) for p in paths]
    raw, _, messages = check_raw_frames(frames, 0 if reference == SHARPEST else reference)
    height, width = frames[0].mosaic.shape
    u0, v0, w, h = (0, 0, width, height) if roi is None else (int(r) for r in roi)
    if w < 1 or h < 1 or u0 < 0 or v0 < 0 or u0 + w > width or v0 + h > height:
        raise HbisInputError(f"--roi {[u0, v0, w, h]} lies outside the {width} x {height} raw frames")
    w, h = w - w % 2, h - h % 2
    if min(w, h) < 48:
        raise HbisInputError(f"raw frames of {w} x {h} px are too small to register (at least 48 x 48: 24 x 24 "
                             "cells of 2 x 2)")
    mosaics = np.stack([f.mosaic[v0:v0 + h, u0:u0 + w] for f in frames])
    if reference == SHARPEST:  # the exposure gains, balance and camera record are the reference's
        reference, said = choose_reference(centre_cells(mosaics), SHARPEST)
        if reference:
            raw, _, messages = check_raw_frames(frames, reference)
        messages += said
    cfa = shifted_cfa(frames[0].cfa, v0, u0)
    black = np.asarray(raw["black"])
    raw["black"] = np.stack([np.roll(b, (-(v0 % 2), -(u0 % 2)), axis=(0, 1)) for b in black]).tolist()
    del frames
    stack, more = raw_burst_stack(mosaics, cfa, raw, scale, reference, motion, (u0, v0, w, h),
                                  [p.name for p in paths])
    return stack, messages + more


def raw_burst_stack(mosaics: np.ndarray, cfa: str, raw: dict, scale: int, reference: int = 0, motion: str = "auto",
                    roi=None, names: list | None = None) -> tuple:
    """Register raw mosaics on their 2 x 2-cell luminance and build the burst stack (the second
    half of :func:`assemble_raw_burst`, for mosaics already in memory).

    Parameters
    ----------
    mosaics : np.ndarray, shape (F, H, W), uint16
        H and W even, the pattern ``cfa`` at (0, 0).
    cfa : str
    raw : dict
        The ``raw`` block (:func:`check_raw_frames`).
    scale, reference, motion
        As :func:`assemble_raw_burst`'s.
    roi : (u0, v0, width, height), optional
        Recorded in the stack (default the whole frame).
    names : list of str, optional

    Returns
    -------
    stack : hbis_torch.stack_io.Stack
    messages : list of str
    """
    import torch

    from hbis_torch.capture.burst import register_burst
    from hbis_torch.capture.stuck_pixels import without_stuck_pixels
    from hbis_torch.registration.pyramid import from_level
    from hbis_torch.stack_io import BURST_MIN_CONFIDENCE, Stack, make_burst_meta, validate_stack

    F, H, W = mosaics.shape
    raw = dict(raw)
    values, clipped = normalised(mosaics, raw)
    grey, raw["grey_scale"] = registration_grey(values, cfa, raw["white_balance"], reference, clipped)
    found = register_burst(torch.from_numpy(grey), reference, motion, names)
    # a blurred reference is named, beside the frames that register (assemble_burst's rule)
    _, said = choose_reference(torch.from_numpy(grey), reference, found.confidence >= BURST_MIN_CONFIDENCE)
    motions = from_level(found.motions, 1)  # a 2 x 2 cell is a pixel of the pyramid's first level
    # hot and dead pixels, against their neighbours of the same colour (two pixels away)
    mosaics, stuck_at, stuck = without_stuck_pixels(mosaics, values, reference, motions,
                                                    found.confidence >= BURST_MIN_CONFIDENCE, spacing=2)
    extra = {"stuck_pixels": stuck_at.tolist()} if len(stuck_at) else {}
    if getattr(found, "local", None) is not None:  # [handheld]'s local shifts, from cells to pixels
        from hbis_torch.registration.local import TILE_PX

        extra["local_motion"] = {"tile_px": 2 * TILE_PX, "offsets": (2 * np.asarray(found.local)).round(5).tolist()}
    meta = make_burst_meta(scale, roi or (0, 0, W, H), motions, found.confidence, found.models, found.gain_offset,
                           reference_index=reference, bit_depth=16, cfa=cfa, raw=raw, **extra)
    mosaics = np.ascontiguousarray(mosaics, dtype=np.uint16)
    validate_stack(mosaics, meta, "assembled raw burst")
    return Stack(mosaics, meta), said + list(found.messages) + stuck
