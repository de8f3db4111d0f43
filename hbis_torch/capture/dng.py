"""One Bayer mosaic -> a DNG file (pidng, the optional extra ``[raw]``), as a camera writes one: for
the tests' raw frames, for handing simulated raw frames to other tools, and for the joint path's
``.dng`` output. :func:`hbis_torch.capture.raw.read_raw` reads such a file back through LibRaw.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from hbis_torch.errors import HbisInputError


def write_mosaic_dng(path, mosaic: np.ndarray, cfa: str, black=0, white: int = 65535, *, bits: int = 16,
                     white_balance=None, colour_matrix=None, orientation: int = 1, camera: str | None = None,
                     exposure_s: float | None = None, iso: int | None = None, noise_profile=None) -> Path:
    """Write one Bayer mosaic as a DNG (pidng), as a camera would: for tests, and for handing
    simulated raw frames to other tools.

    Parameters
    ----------
    path : str or Path
    mosaic : np.ndarray, shape (H, W), uint16
    cfa : str
        "RGGB", "BGGR", "GRBG" or "GBRG".
    black : float or sequence of 4
        Black level (one, or one per pattern position).
    white : int
    bits : int
        BitsPerSample (8, 10, 12, 14 or 16; the container).
    white_balance : sequence of 3, optional
        As-shot multipliers (R, G, B), written as AsShotNeutral (their inverses).
    colour_matrix : np.ndarray, shape (3, 3), optional
        DNG ColorMatrix1 (XYZ D65 -> camera).
    orientation : int
        The TIFF orientation (1 as recorded, 3, 6, 8).
    camera : str, optional
    exposure_s : float, optional
    iso : int, optional
    noise_profile : sequence of 2 or 6 floats, optional

    Returns
    -------
    Path
    """
    try:
        from pidng.core import RAW2DNG, DNGTags, Tag
        from pidng.defs import CalibrationIlluminant, DNGVersion, PhotometricInterpretation
    except ImportError:
        raise HbisInputError("writing a DNG needs pidng: pip install 'hbis-torch[raw]'") from None
    from fractions import Fraction

    path = Path(path)
    H, W = mosaic.shape
    codes = {"R": 0, "G": 1, "B": 2}
    t = DNGTags()
    t.set(Tag.ImageWidth, W)
    t.set(Tag.ImageLength, H)
    t.set(Tag.TileWidth, W)
    t.set(Tag.TileLength, H)
    t.set(Tag.Orientation, int(orientation))
    t.set(Tag.PhotometricInterpretation, PhotometricInterpretation.Color_Filter_Array)
    t.set(Tag.SamplesPerPixel, 1)
    t.set(Tag.BitsPerSample, int(bits))
    t.set(Tag.CFARepeatPatternDim, [2, 2])
    t.set(Tag.CFAPattern, [codes[c] for c in cfa])
    levels = np.broadcast_to(np.asarray(black, dtype=np.float64).ravel(), (4,)) if np.size(black) in (1, 4) else None
    if levels is None:
        raise HbisInputError("black must be one level or four (one per pattern position)")
    t.set(Tag.BlackLevelRepeatDim, [2, 2])
    t.set(Tag.BlackLevel, [int(round(v)) for v in levels])
    t.set(Tag.WhiteLevel, int(white))
    if colour_matrix is not None:
        t.set(Tag.ColorMatrix1, [[int(round(v * 10000)), 10000] for v in np.asarray(colour_matrix).ravel()])
        t.set(Tag.CalibrationIlluminant1, CalibrationIlluminant.D65)
    if white_balance is not None:
        neutral = [Fraction(1 / float(v)).limit_denominator(100000) for v in white_balance]
        t.set(Tag.AsShotNeutral, [[f.numerator, f.denominator] for f in neutral])
    if camera:
        t.set(Tag.Make, camera.split(" ")[0])
        t.set(Tag.Model, camera)
        t.set(Tag.UniqueCameraModel, camera)
    if exposure_s:
        f = Fraction(float(exposure_s)).limit_denominator(1000000)
        t.set(Tag.ExposureTime, [[f.numerator, f.denominator]])
    if iso:
        t.set(Tag.PhotographicSensitivity, int(iso))
    if noise_profile is not None:
        t.set(Tag.NoiseProfile, [float(v) for v in np.asarray(noise_profile).ravel()])
    t.set(Tag.DNGVersion, DNGVersion.V1_4)
    t.set(Tag.DNGBackwardVersion, DNGVersion.V1_2)
    converter = RAW2DNG()
    converter.options(t, path="", compress=False)
    buffer = converter.convert(np.ascontiguousarray(mosaic, dtype=np.uint16))
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(bytes(buffer))
    return path
