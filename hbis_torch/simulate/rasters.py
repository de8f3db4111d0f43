"""Rasters for image scenes: photographs, image files, random words and textures.

Each function returns a float32 gray image (rows, cols) in [0, 1], the raster an
:class:`~hbis_torch.simulate.scenes.ImageScene` interpolates.
"""

from __future__ import annotations

import math
from functools import lru_cache
from pathlib import Path

import numpy as np

from hbis_torch.errors import HbisInputError
from hbis_torch.simulate.scenes import Size, check_size

PHOTOS = (
    "camera", "astronaut", "brick", "grass", "gravel", "coffee", "chelsea", "moon", "page",
    "text", "coins", "rocket", "immunohistochemistry", "hubble_deep_field", "clock", "cell",
)
"""Photographs from skimage.data that ship with scikit-image (no download needed)."""
HELD_OUT_PHOTOS = ("camera", "astronaut", "coffee", "chelsea", "rocket")
"""The photographs kept for held-out tests: no training pool uses them (the others may be)."""


def to_gray(array) -> np.ndarray:
    """Any image array (gray, RGB, RGBA; bool, integer or float) as float32 gray in [0, 1]."""
    a = np.asarray(array)
    if a.dtype == bool:
        a = a.astype(np.float32)
    elif np.issubdtype(a.dtype, np.integer):
        a = a.astype(np.float32) / float(np.iinfo(a.dtype).max)
    else:
        a = a.astype(np.float32)
        top = float(np.nanmax(a)) if a.size else 1.0
        if top > 1.0:
            a = a / top
    if a.ndim == 3 and a.shape[-1] in (3, 4):
        a = a[..., :3] @ np.array([0.2125, 0.7154, 0.0721], dtype=np.float32)
    if a.ndim != 2:
        raise HbisInputError(f"expected a grayscale or RGB image, got shape {np.asarray(array).shape}")
    if not np.isfinite(a).all():
        raise HbisInputError("the image contains NaN or infinite values")
    return np.clip(a, 0.0, 1.0)


@lru_cache(maxsize=None)
def photo(name: str) -> np.ndarray:
    """A photograph from skimage.data as float32 gray in [0, 1] (cached)."""
    import skimage.data

    if name not in PHOTOS:
        raise HbisInputError(f"unknown photograph {name!r}; choose from {', '.join(PHOTOS)}")
    return to_gray(getattr(skimage.data, name)())


#: A scene image's default limit of float32 work, MiB (``HBIS_MAX_STACK_MB`` overrides it): one
#: picture, not a burst of them, so the stacks' larger default does not apply.
SCENE_MAX_MB = 1024


def _check_declared(path, shape, itemsize: int, limit: int) -> None:
    """Refuse an image whose header declares more than ``limit`` bytes of float32 work, before decoding.

    Gray conversion works in float32 on every channel, hence four bytes a sample at least.
    """
    need = math.prod(int(n) for n in shape) * max(itemsize, 4)
    if need > limit:
        raise HbisInputError(f"{path}: the image declares {' x '.join(map(str, shape))} samples, "
                             f"{need / 2**20:.0f} MiB to convert, over the limit of {limit / 2**20:.0f} MiB "
                             "(raise it with the environment variable HBIS_MAX_STACK_MB)")


def read_image_file(path) -> np.ndarray:
    """An image file (PNG, JPEG, TIFF, ...) as float32 gray in [0, 1]."""
    from hbis_torch.tiff_io import max_decoded_bytes, quiet_tifffile

    path = Path(path)
    limit = max_decoded_bytes(SCENE_MAX_MB)
    try:
        if path.suffix.lower() in (".tif", ".tiff"):
            import tifffile

            with quiet_tifffile(), tifffile.TiffFile(path) as tif:
                page = tif.pages.first
                _check_declared(path, page.shape, page.dtype.itemsize if page.dtype else 8, limit)
                array = page.asarray()  # the first page only (of a stack, its first frame)
        else:
            from PIL import Image

            with quiet_tifffile(), Image.open(path) as image:  # quiet: PIL's bomb warning too
                _check_declared(path, (image.height, image.width, len(image.getbands())), 4, limit)
                if image.mode.startswith("I;16"):
                    array = np.asarray(image).astype(np.uint16)  # 16-bit: scaled by 65535
                else:
                    array = np.asarray(image)
    except FileNotFoundError:
        raise HbisInputError(f"{path}: no such image file") from None
    except HbisInputError:
        raise
    except Exception as exc:  # noqa: BLE001 - the readers raise many types for bad files
        raise HbisInputError(f"{path}: cannot read the image ({type(exc).__name__}: {exc})") from None
    return to_gray(array)


def cover_size(image_shape, footprint_mm: Size) -> Size:
    """Size (mm) at which an image of ``image_shape`` (rows, cols) just covers ``footprint_mm``,
    keeping its aspect ratio."""
    rows, cols = image_shape
    fw, fh = check_size(footprint_mm)
    pixel = max(fw / cols, fh / rows)
    return (cols * pixel, rows * pixel)


WORDS = (
    "fovea", "prism", "risley", "pixel", "camera", "optics", "scan", "sensor", "lens", "field",
    "view", "image", "light", "wedge", "phase", "super", "resolution", "eye", "compound", "array",
    "HBIS", "zoom", "focus", "signal", "noise", "Quartz", "jumps", "OVER", "lazy", "dog",
    "Xylophone", "wizard", "BOX", "vexing", "jig", "47", "2024", "0.95", "f/1.4", "3.75um",
)


@lru_cache(maxsize=64)
def _font(size_px: int):
    from matplotlib import font_manager
    from PIL import ImageFont

    return ImageFont.truetype(font_manager.findfont("DejaVu Sans"), size_px)


def words_image(shape, letter_heights_px, count: int, rng: np.random.Generator) -> np.ndarray:
    """Random words at several sizes, as a float32 raster (rows, cols) in [0, 1].

    ``letter_heights_px`` is the (min, max) capital-letter height in raster pixels; sizes are
    drawn log-uniformly. The background is a random light or dark grey, text of random contrast.
    """
    from PIL import Image, ImageDraw

    rows, cols = (int(s) for s in shape)
    dark_text = rng.random() < 0.7
    background = rng.uniform(0.6, 0.95) if dark_text else rng.uniform(0.05, 0.4)
    canvas = Image.new("F", (cols, rows), float(background))
    draw = ImageDraw.Draw(canvas)
    lo, hi = (max(float(v), 1.0) for v in letter_heights_px)
    for _ in range(count):
        cap = math.exp(rng.uniform(math.log(lo), math.log(max(hi, lo))))
        font = _font(max(2, int(round(cap / 0.73))))
        word = WORDS[rng.integers(len(WORDS))]
        if rng.random() < 0.3:
            word = "".join(chr(c) for c in rng.integers(65, 91, size=rng.integers(2, 7)))
        ink = rng.uniform(0.0, background - 0.2) if dark_text else rng.uniform(background + 0.2, 1.0)
        left, top, right, bottom = font.getbbox(word)
        x = rng.uniform(-0.1 * (right - left), max(cols - 0.9 * (right - left), 1.0))
        y = rng.uniform(-top, max(rows - bottom, 1.0))
        draw.text((x, y), word, fill=float(ink), font=font)
    return np.clip(np.asarray(canvas, dtype=np.float32), 0.0, 1.0)


def texture_image(shape, correlation_px: float, rng: np.random.Generator, beta: float = 1.0) -> np.ndarray:
    """Random texture: Gaussian noise with a power-law spectrum (exponent ``beta``) above a
    correlation length, stretched to [0, 1], as a float32 raster."""
    rows, cols = (int(s) for s in shape)
    noise = rng.standard_normal((rows, cols))
    fy = np.fft.fftfreq(rows)[:, None]
    fx = np.fft.rfftfreq(cols)[None, :]
    f = np.hypot(fx, fy)
    f0 = 1.0 / max(correlation_px * 8.0, 2.0)
    amplitude = (f0**2 + f**2) ** (-beta / 2) * np.exp(-((f * correlation_px) ** 2))
    field_ = np.fft.irfft2(np.fft.rfft2(noise) * amplitude, s=(rows, cols))
    lo, hi = np.percentile(field_, [1, 99])
    contrast = rng.uniform(0.4, 1.0)
    out = 0.5 + contrast * ((field_ - lo) / max(hi - lo, 1e-12) - 0.5)
    return np.clip(out, 0.0, 1.0).astype(np.float32)
