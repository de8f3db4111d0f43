"""TIFF files read and written with care: what the headers declare is checked before anything is
decoded, tifffile stays quiet, and a written file holds one ImageDescription and its pixel size.

Reading (:func:`read_tiff`) refuses, in one :class:`StackFormatError` line naming the file, more
pages than the caller allows, a sample format that cannot be read, pages of different shapes or
dtypes, data lying beyond the end of the file (a truncated file), and more than
``HBIS_MAX_STACK_MB`` MiB once decoded (:func:`max_decoded_bytes`; default 4096, an environment
variable the user can raise). The hbis-stack/1 format on top of it is :mod:`hbis_torch.stack_io`.
"""

from __future__ import annotations

import logging
import math
import os
import warnings
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from hbis_torch.checks import MAX_H
from hbis_torch.errors import HbisInputError, StackFormatError

#: Default of HBIS_MAX_STACK_MB: the most a file (or a burst's frames together) may take once
#: decoded, MiB. h = 16 on the whole 960 x 1280 sensor in uint16 is 600 MiB; 16 frames of 12 MP in
#: 16-bit RGB are 1099 MiB, of 24 MP 2197 MiB (the 1024 of before refused them). Whether the machine
#: can hold the job is hbis_torch.budget's estimate, checked next; this bounds what a header alone
#: may ask for (a 20000 x 20000 page, 16 of them, stays refused).
DEFAULT_MAX_STACK_MB = 4096


def max_decoded_bytes(default_mb: float = DEFAULT_MAX_STACK_MB) -> int:
    """The most bytes one file may take once decoded: ``HBIS_MAX_STACK_MB`` MiB (default
    ``default_mb``, :data:`DEFAULT_MAX_STACK_MB` unless the caller bounds its files lower)."""
    text = os.environ.get("HBIS_MAX_STACK_MB", "").strip()
    if not text:
        return int(default_mb * 2**20)
    try:
        mb = float(text)
    except ValueError:
        mb = float("nan")
    if not (math.isfinite(mb) and 0 < mb <= 2**30):
        raise HbisInputError(f"HBIS_MAX_STACK_MB must be a positive number of MiB, got {text[:40]!r}")
    return int(mb * 2**20)


@contextmanager
def quiet_tifffile():
    """Keep tifffile's own log lines and warnings off stderr: the caller reports in one line."""
    log = logging.getLogger("tifffile")
    level = log.level
    log.setLevel(logging.CRITICAL + 1)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            yield
    finally:
        log.setLevel(level)


def declared_pages(tif, path: Path, max_pages: int) -> list:
    """The pages of an open TiffFile, checked from their headers alone (nothing is decoded).

    Refuses more than ``max_pages`` pages, a page whose sample format cannot be read, pages of
    different shapes or dtypes, data lying beyond the end of the file (a truncated file), and
    more than :func:`max_decoded_bytes` once decoded.
    """
    count = len(tif.pages)  # follows the IFD chain (loops detected) without parsing the pages
    if count > max_pages:
        what = "expected one image" if max_pages == 1 else f"a stack holds h x h frames, h <= {MAX_H}"
        raise StackFormatError(f"{path}: {count} pages, more than {max_pages} ({what})")
    pages = list(tif.pages)
    if not pages:
        raise StackFormatError(f"{path}: the TIFF holds no pages")
    size, limit, total, sizes = tif.filehandle.size, max_decoded_bytes(), 0, []
    for i, page in enumerate(pages):
        shape, dtype = tuple(int(n) for n in page.shape), page.dtype
        if dtype is None:
            raise StackFormatError(f"{path}: page {i} has a sample format that cannot be read")
        if not shape or min(shape) < 1:
            raise StackFormatError(f"{path}: page {i} is empty (shape {shape})")
        sizes.append(math.prod(shape) * dtype.itemsize)
        total += sizes[-1]
    if total > limit:
        raise StackFormatError(
            f"{path}: the pages declare {total / 2**20:.0f} MiB once decoded ({len(pages)} x "
            f"{tuple(pages[0].shape)} {pages[0].dtype}), over the limit of {limit / 2**20:.0f} MiB "
            "(raise it with the environment variable HBIS_MAX_STACK_MB)"
        )
    for i, (page, nbytes) in enumerate(zip(pages, sizes)):
        counts = [int(c) for c in page.databytecounts]
        ends = [int(o) + c for o, c in zip(page.dataoffsets, counts) if c]
        packed = page.compression == 1 and page.bitspersample == page.dtype.itemsize * 8
        if not ends or max(ends) > size or (packed and sum(counts) < nbytes):
            raise StackFormatError(f"{path}: the file is truncated or damaged: page {i}'s data "
                                   f"is missing or runs past the end of the file ({size} bytes)")
    shapes = sorted({tuple(p.shape) for p in pages})
    if len(shapes) != 1:
        raise StackFormatError(f"{path}: the pages have different shapes {shapes}")
    dtypes = sorted({str(p.dtype) for p in pages})
    if len(dtypes) != 1:
        raise StackFormatError(f"{path}: the pages have different dtypes ({', '.join(dtypes)})")
    return pages


def read_tiff(path: Path, max_pages: int) -> tuple[np.ndarray, str | None]:
    """All pages of a TIFF, checked first (:func:`declared_pages`): (array (P, rows, cols) or
    (P, rows, cols, 3), page 0's ImageDescription)."""
    import tifffile

    try:
        with quiet_tifffile(), tifffile.TiffFile(path) as tif:
            pages = declared_pages(tif, path, max_pages)
            description = pages[0].description
            # decoded into one array (the pages' shapes and dtypes are checked alike): no stacking copy
            arrays = np.empty((len(pages),) + tuple(pages[0].shape), pages[0].dtype)
            for page, out in zip(pages, arrays):
                page.asarray(out=out)
    except StackFormatError:
        raise
    except FileNotFoundError:
        raise StackFormatError(f"{path}: no such file") from None
    except IsADirectoryError:
        raise StackFormatError(f"{path}: is a directory, not a TIFF file") from None
    except MemoryError:
        raise StackFormatError(f"{path}: not enough memory to decode the file") from None
    except Exception as exc:  # noqa: BLE001 - tifffile raises many types for corrupt files
        detail = str(exc).splitlines()[0][:200] if str(exc) else ""
        raise StackFormatError(f"{path}: not a readable TIFF file ({type(exc).__name__}: {detail})") from None
    if not (arrays[0].ndim == 2 or (arrays[0].ndim == 3 and arrays[0].shape[-1] == 3)):
        raise StackFormatError(
            f"{path}: pages must be grayscale (rows, cols) or RGB (rows, cols, 3), got shape {arrays[0].shape}"
        )
    return arrays, description


def write_tiff(tmp: Path, array: np.ndarray, description: str, pixel_size_um: float | None = None) -> None:
    """One ImageDescription (``description``, the file's JSON) and, with ``pixel_size_um``, the
    pixel size as XResolution/YResolution in pixels per centimetre (ResolutionUnit 3), the TIFF
    unit that ImageJ/Fiji, napari's tifffile-based readers and GDAL read as the image's scale."""
    import tifffile

    resolution = {}
    if pixel_size_um is not None and math.isfinite(pixel_size_um) and pixel_size_um > 0:
        per_cm = 1e4 / float(pixel_size_um)
        resolution = {"resolution": (per_cm, per_cm), "resolutionunit": tifffile.RESUNIT.CENTIMETER}
    tifffile.imwrite(
        tmp,
        array,
        description=description,
        metadata=None,
        photometric="rgb" if array.ndim == 4 or (array.ndim == 3 and array.shape[-1] == 3) else "minisblack",
        bigtiff=array.nbytes > 2**31,
        **resolution,
    )


def read_pixel_size_um(path) -> float | None:
    """The pixel size a TIFF records in its resolution tags, in um (None where it has none)."""
    import tifffile

    with tifffile.TiffFile(path) as tif:
        tags = tif.pages[0].tags
        unit, res = tags.get("ResolutionUnit"), tags.get("XResolution")
        if unit is None or res is None or int(unit.value) != 3:
            return None
        per_cm = res.value[0] / res.value[1]
    return 1e4 / per_cm if per_cm > 0 else None
