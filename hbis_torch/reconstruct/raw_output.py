"""A raw burst's result written out: a linear 16-bit TIFF (linear sRGB) or a linear DNG (camera
RGB, through pidng), and an sRGB preview PNG, turned as the reference frame was
(docs/raw-bursts.md). The image is the joint path's linear camera RGB
(:func:`hbis_torch.reconstruct.classical.raw_burst.reconstruct_raw_burst`)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from hbis_torch.errors import HbisInputError

# Rows converted at a time: at 8000 x 6000 the whole image's float temporaries took 2 GB beside
# the 0.6 GB image.
BAND_ROWS = 256


def orient(image: np.ndarray, flip: int) -> np.ndarray:
    """Turn an image (H, W, ...) as LibRaw's ``flip`` says (0 as recorded, 3: 180 deg, 5: 90 deg
    counter-clockwise, 6: 90 deg clockwise)."""
    if flip == 3:
        return image[::-1, ::-1]
    if flip == 5:
        return np.rot90(image, 1)
    if flip == 6:
        return np.rot90(image, -1)
    return image


def camera_to_srgb(image: np.ndarray, raw: dict) -> np.ndarray:
    """Linear camera RGB (H, W, 3) -> linear sRGB (H, W, 3) float32 in [0, 1]: the white
    balance (the green multiplier 1), then the colour matrix, then clipped to [0, 1]."""
    balance = np.asarray(raw["white_balance"], dtype=np.float32)
    matrix = np.asarray(raw["colour_matrix"], dtype=np.float32)
    out = (image * balance) @ matrix.T
    return np.clip(out, 0, 1).astype(np.float32)


def srgb_gamma(linear: np.ndarray) -> np.ndarray:
    """The sRGB transfer curve (IEC 61966-2-1) of linear values in [0, 1]."""
    linear = np.clip(linear, 0, 1)
    return np.where(linear <= 0.0031308, 12.92 * linear, 1.055 * np.power(linear, 1 / 2.4) - 0.055)


def srgb_outputs(image: np.ndarray, raw: dict, linear: bool = True) -> tuple[np.ndarray | None, np.ndarray]:
    """The 16-bit linear sRGB and the 8-bit sRGB preview of linear camera RGB, made a band of
    rows at a time (:data:`BAND_ROWS`).

    Parameters
    ----------
    image : np.ndarray, shape (H, W, 3), float32
        Linear camera RGB.
    raw : dict
        The stack's ``raw`` block (:func:`camera_to_srgb`).
    linear : bool
        False: no 16-bit image (None in its place).

    Returns
    -------
    linear_srgb : np.ndarray or None, shape (H, W, 3), uint16
        :func:`camera_to_srgb` times 65535, rounded.
    preview : np.ndarray, shape (H, W, 3), uint8
        :func:`srgb_gamma` of it times 255, rounded.
    """
    H, W, _ = image.shape
    out = np.empty((H, W, 3), np.uint16) if linear else None
    preview = np.empty((H, W, 3), np.uint8)
    for y in range(0, H, BAND_ROWS):
        srgb = camera_to_srgb(image[y:y + BAND_ROWS], raw)
        if out is not None:
            out[y:y + BAND_ROWS] = np.round(srgb * 65535)
        preview[y:y + BAND_ROWS] = np.round(srgb_gamma(srgb) * 255)
    return out, preview


def preview_path(path) -> Path:
    """Where the sRGB preview of an output goes: beside it, ``NAME.preview.png``."""
    path = Path(path)
    return path.with_name(path.stem + ".preview.png")


def write_raw_outputs(path, image: np.ndarray, meta: dict) -> list:
    """Write a raw burst's result: ``path`` (a linear 16-bit TIFF in linear sRGB, or with ``.dng``
    a linear DNG in the camera's RGB with its colour matrix and white balance) and the sRGB
    preview PNG beside it (:func:`preview_path`), both turned as the reference frame was.

    Parameters
    ----------
    path : str or Path
    image : np.ndarray, shape (S H, S W, 3), float32 in [0, 1]
        Linear camera RGB (:func:`hbis_torch.reconstruct.classical.raw_burst.reconstruct_raw_burst`).
    meta : dict
        The output's JSON; its ``raw`` block (the stack's) gives the colour.

    Returns
    -------
    list of Path
        The files written.
    """
    from hbis_torch.io_utils import atomic_path
    from hbis_torch.optional import import_cv2

    path = Path(path)
    raw = meta["raw"]
    flip = int(raw.get("orientation", 0))
    dng = path.suffix.lower() == ".dng"
    data, preview = srgb_outputs(image, raw, linear=not dng)
    written = []
    if dng:
        _write_dng(path, orient(image, flip), raw)
    else:
        import tifffile

        info = {**meta, "colour_space": "linear sRGB (IEC 61966-2-1 primaries, D65), white-balanced; "
                "1 = the white level", "transfer": "linear"}
        with atomic_path(path) as tmp:
            tifffile.imwrite(tmp, np.ascontiguousarray(orient(data, flip)), photometric="rgb", metadata=None,
                             description=json.dumps(info, default=float), software="hbis-torch",
                             extratags=_camera_tags(raw))
    written.append(path)
    cv2 = import_cv2("writing the sRGB preview PNG")
    preview = orient(preview, flip)
    target = preview_path(path)
    with atomic_path(target) as tmp:
        ok, encoded = cv2.imencode(".png", np.ascontiguousarray(preview[..., ::-1]))
        if not ok:
            raise RuntimeError(f"{target}: OpenCV could not encode the preview")
        Path(tmp).write_bytes(encoded.tobytes())
    written.append(target)
    return written


def _camera_tags(raw: dict) -> list:
    """TIFF Make/Model (as one text) for the linear TIFF, where the files named a camera."""
    camera = raw.get("camera")
    return [(271, "s", 0, str(camera), True)] if camera else []


def _write_dng(path: Path, image: np.ndarray, raw: dict) -> None:
    """A linear DNG (PhotometricInterpretation LinearRaw, 16 bits, 3 samples) of camera RGB,
    with the colour matrix (sRGB from camera, inverted into DNG's XYZ-to-camera ColorMatrix1),
    the as-shot white balance and the noise profile, through pidng."""
    try:
        from pidng.core import RAW2DNG, DNGTags, Tag
        from pidng.defs import CalibrationIlluminant, DNGVersion, PhotometricInterpretation
    except ImportError:
        raise HbisInputError("writing a DNG needs pidng: pip install 'hbis-torch[raw]'") from None
    from hbis_torch.io_utils import atomic_path

    H, W, _ = image.shape
    data = np.empty((H, W, 3), np.uint16)
    for y in range(0, H, BAND_ROWS):  # the turned image is a view: its rows are the bands
        data[y:y + BAND_ROWS] = np.round(image[y:y + BAND_ROWS] * 65535)
    # ColorMatrix1 maps XYZ (D65) to camera RGB: inverse of (sRGB <- XYZ)^-1 ... composed with the balance.
    srgb_from_xyz = np.array([[3.2404542, -1.5371385, -0.4985314], [-0.9692660, 1.8760108, 0.0415560],
                              [0.0556434, -0.2040259, 1.0572252]])
    srgb_from_cam = np.asarray(raw["colour_matrix"], dtype=np.float64) @ np.diag(raw["white_balance"])
    cam_from_xyz = np.linalg.inv(srgb_from_cam) @ srgb_from_xyz
    cam_from_xyz /= cam_from_xyz[1].sum() if abs(cam_from_xyz[1].sum()) > 1e-9 else 1.0
    t = DNGTags()
    t.set(Tag.ImageWidth, W)
    t.set(Tag.ImageLength, H)
    t.set(Tag.TileWidth, W)
    t.set(Tag.TileLength, H)
    t.set(Tag.Orientation, 1)
    t.set(Tag.PhotometricInterpretation, PhotometricInterpretation.Linear_Raw)
    t.set(Tag.SamplesPerPixel, 3)
    t.set(Tag.BitsPerSample, [16, 16, 16])
    t.set(Tag.BlackLevel, [0, 0, 0])
    t.set(Tag.WhiteLevel, 65535)
    t.set(Tag.ColorMatrix1, [[int(round(v * 10000)), 10000] for v in cam_from_xyz.ravel()])
    t.set(Tag.CalibrationIlluminant1, CalibrationIlluminant.D65)
    t.set(Tag.AsShotNeutral, [[int(round(10000 / v)), 10000] for v in raw["white_balance"]])
    t.set(Tag.Make, str(raw.get("camera") or "unknown"))
    t.set(Tag.Model, str(raw.get("camera") or "unknown"))
    t.set(Tag.UniqueCameraModel, str(raw.get("camera") or "hbis-torch raw burst"))
    t.set(Tag.DNGVersion, DNGVersion.V1_4)
    t.set(Tag.DNGBackwardVersion, DNGVersion.V1_2)
    converter = RAW2DNG()
    with atomic_path(path) as tmp:
        converter.options(t, path="", compress=False)
        buffer = converter.convert(data)
        Path(tmp).write_bytes(bytes(buffer))


def check_raw_outputs(stack_path, out, overwrite: bool = False) -> None:
    """Before any work: where ``stack_path`` is a raw burst stack, refuse in one line a preview
    (:func:`preview_path` of ``out``) that exists already (unless ``overwrite``, the rule of
    ``--out``), a ``.dng`` output without pidng, and a preview without OpenCV. Other stacks:
    nothing to check. Only the file's JSON description is read (no pixels)."""
    import os

    import tifffile

    from hbis_torch.tiff_io import quiet_tifffile

    try:
        with quiet_tifffile(), tifffile.TiffFile(stack_path) as tif:  # a broken file: read_stack's one line
            meta = json.loads(tif.pages[0].description or "{}")
    except Exception:  # not readable here: read_stack says why, in its own line
        return
    if not (isinstance(meta, dict) and meta.get("kind") == "burst" and isinstance(meta.get("raw"), dict)):
        return
    preview = preview_path(out)
    if os.path.lexists(preview) and not (overwrite and os.path.isfile(preview)):
        how = "it is not a regular file" if overwrite else "pass --overwrite to replace it"
        raise HbisInputError(f"--out: the preview {preview} exists already ({how})")
    from hbis_torch.optional import import_cv2

    import_cv2("writing the sRGB preview PNG of a raw burst")
    if Path(out).suffix.lower() == ".dng":
        try:
            import pidng  # noqa: F401
        except ImportError:
            raise HbisInputError("writing a DNG needs pidng: pip install 'hbis-torch[raw]'") from None
