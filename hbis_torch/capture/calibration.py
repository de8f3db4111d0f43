"""Dark frame, flat field and bad-pixel map: the per-pixel corrections of a real sensor.

Each calibration image is stored in the camera's own units (the raw digital numbers of the frames,
or float in [0, 1] for float frames). A dark frame is the camera's output with the lens capped
(black level plus dark current, at the exposure of the scan); a flat field is its output looking
at a uniform white target (same exposure class); a bad-pixel map is nonzero at defective pixels.
A multi-page TIFF of either is averaged page by page (several captures lower its noise). Each may
have the frames' size or the whole sensor's (then the stack's ROI is cut out of it).

The correction, in the stack's normalised units (``Stack.to_float``)::

    gain      = (flat - dark) / mean(flat - dark)        (pixel response, 1 on average)
    corrected = clip((frame - dark) / gain, 0, 1)

and every bad pixel (from the map, or with a flat-field gain below ``MIN_GAIN``) is replaced by
the mean of its good neighbours. The calibrated stack holds float32 frames in [0, 1] and records
what was applied under ``calibration``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from hbis_torch.errors import HbisInputError

MIN_GAIN = 0.1
"""A pixel whose flat-field response is below this fraction of the mean is treated as bad."""


@dataclass
class FrameCalibration:
    """Calibration images as read (float64, raw units), any of them None.

    Attributes
    ----------
    dark, flat : np.ndarray or None, shape (H, W) or (H, W, 3)
    bad : np.ndarray or None, shape (H, W), bool
    names : dict
        File name of each image given, for the stack's record.
    """

    dark: np.ndarray | None = None
    flat: np.ndarray | None = None
    bad: np.ndarray | None = None
    names: dict = field(default_factory=dict)

    def __bool__(self) -> bool:
        return any(x is not None for x in (self.dark, self.flat, self.bad))


def _read_mean(path, what: str) -> np.ndarray:
    from hbis_torch.capture.frames import read_image

    try:
        pages = read_image(path)
    except HbisInputError as exc:
        raise HbisInputError(f"{what}: {exc}") from None
    return pages.astype(np.float64).mean(axis=0)


def load_calibration(dark=None, flat=None, bad_pixels=None) -> FrameCalibration:
    """Read the calibration images given as paths (None: not given)."""
    cal = FrameCalibration()
    if dark is not None:
        cal.dark, cal.names["dark"] = _read_mean(dark, "dark frame"), Path(dark).name
    if flat is not None:
        cal.flat, cal.names["flat"] = _read_mean(flat, "flat field"), Path(flat).name
    if bad_pixels is not None:
        bad = _read_mean(bad_pixels, "bad-pixel map")
        cal.bad, cal.names["bad_pixels"] = (bad.max(axis=-1) if bad.ndim == 3 else bad) != 0, Path(bad_pixels).name
    return cal


def check_calibration_size(cal: FrameCalibration, captured_shape, roi=None) -> None:
    """Refuse calibration images that fit neither frames of ``captured_shape`` ((H, W) or (H, W, 3),
    as a burst's files declare them) nor their cut to ``roi``, before any frame is decoded."""
    height, width = captured_shape[:2]
    u0, v0, w, h = roi if roi is not None else (0, 0, width, height)
    shape = (h, w, *captured_shape[2:])
    for image, what, key in ((cal.dark, "dark frame", "dark"), (cal.flat, "flat field", "flat"),
                             (cal.bad, "bad-pixel map", "bad_pixels")):
        if image is not None:
            _fit(image, what, cal.names.get(key, ""), shape, (u0, v0, w, h), (height, width))


def _fit(image: np.ndarray, what: str, name: str, frame_shape, roi, sensor_shape) -> np.ndarray:
    """``image`` cut to the frames: as it is when it has their size, the ROI when it has the sensor's."""
    hw = image.shape[:2]
    u0, v0, width, height = roi
    if hw == tuple(frame_shape[:2]):
        out = image
    elif hw == tuple(sensor_shape):
        out = image[v0:v0 + height, u0:u0 + width]
    else:
        raise HbisInputError(f"{what} {name} is {hw[1]} x {hw[0]} pixels but the frames are {frame_shape[1]} x "
                             f"{frame_shape[0]} (sensor {sensor_shape[1]} x {sensor_shape[0]}): a calibration "
                             "of another camera or ROI")
    colour = len(frame_shape) == 3
    if out.ndim == 3 and not colour:
        raise HbisInputError(f"{what} {name} is colour but the frames are grayscale")
    if colour and out.ndim == 2 and what != "bad-pixel map":
        out = np.repeat(out[..., None], 3, axis=-1)
    return out


def fill_bad_pixels(frames: np.ndarray, bad: np.ndarray, rounds: int = 8) -> np.ndarray:
    """Replace the pixels where ``bad`` (H, W) is True by the mean of their good 3 x 3 neighbours.

    ``frames``: (F, H, W) or (F, H, W, C) float. Clusters are filled from the outside in, one ring a
    round; a pixel with no good pixel within ``rounds`` rings is set to the frame's mean.
    """
    from scipy.ndimage import uniform_filter

    colour = frames.ndim == 4
    out = np.array(np.moveaxis(frames, -1, 1) if colour else frames[:, None], dtype=np.float64)  # (F, C, H, W)
    good = ~np.asarray(bad, dtype=bool)
    for _ in range(rounds):
        if good.all():
            break
        g = good.astype(np.float64)
        total = uniform_filter(out * g, size=(1, 1, 3, 3), mode="nearest")
        count = uniform_filter(g, size=3, mode="nearest")
        fill = ~good & (count > 1e-9)
        out[..., fill] = total[..., fill] / count[fill]
        good = good | fill
    if not good.all():
        out[..., ~good] = out.mean(axis=(2, 3), keepdims=True)[..., 0]
    return np.moveaxis(out, 1, -1) if colour else out[:, 0]


def calibrate_stack(stack, cal: FrameCalibration):
    """The stack corrected for dark, flat and bad pixels: float32 frames in [0, 1].

    Parameters
    ----------
    stack : hbis_torch.stack_io.Stack
        Frames as captured (raw units).
    cal : FrameCalibration

    Returns
    -------
    Stack
        float32 frames, ``bit_depth`` and ``black_level`` dropped (they described the raw
        numbers), ``calibration`` recording the files applied and the bad-pixel count.
    """
    from hbis_torch.stack_io import Stack

    if not cal:
        return stack
    frames = stack.frames
    cam = stack.system.camera
    if frames.dtype == np.float32:
        black, scale = 0.0, 1.0
    else:
        black, scale = stack.black_level, float(2 ** stack.bit_depth - 1) - stack.black_level
    dark, gain, bad = corrections(cal, frames.shape[1:], stack.roi, (cam.rows, cam.cols), black, scale)
    corrected = (stack.to_float().numpy().astype(np.float64) - dark) / gain
    if bad.any():
        corrected = fill_bad_pixels(corrected, bad)
    corrected = np.clip(corrected, 0.0, 1.0).astype(np.float32)
    meta = {k: v for k, v in stack.meta.items() if k not in ("bit_depth", "black_level")}
    meta["calibration"] = {**cal.names, "bad_pixel_count": int(bad.sum())}
    return Stack(corrected, meta)


def calibrate_frames(frames: np.ndarray, cal: FrameCalibration, roi, captured_shape, white: float):
    """Frames cut to ``roi`` from captured ones, corrected as :func:`calibrate_stack` corrects a
    stack's, a frame at a time (a burst's frames need not all be held in float64).

    Parameters
    ----------
    frames : np.ndarray, shape (F, H, W) or (F, H, W, 3)
        Any dtype, the captured frames cut to ``roi``.
    cal : FrameCalibration
        Images of the frames' size, or of the captured frames' (then cut to ``roi``).
    roi : (u0, v0, width, height)
    captured_shape : (rows, cols)
    white : float
        The frames' value of white (their black is 0: a dark frame holds the camera's black level).

    Returns
    -------
    frames : np.ndarray, float32 in [0, 1]
    bad : np.ndarray, shape (H, W), bool
        The bad pixels (from the map, and the flat field's weak ones), filled from their neighbours.
    """
    dark, gain, bad = corrections(cal, frames.shape[1:], roi, captured_shape, 0.0, float(white))
    out = np.empty(frames.shape, np.float32)
    for k in range(len(frames)):
        corrected = (frames[k].astype(np.float64) / white - dark) / gain
        if bad.any():
            corrected = fill_bad_pixels(corrected[None], bad)[0]
        out[k] = np.clip(corrected, 0.0, 1.0)
    return out, bad


def corrections(cal: FrameCalibration, shape, roi, sensor_shape, black: float, scale: float):
    """The per-pixel corrections of frames of ``shape`` (H, W) or (H, W, 3) cut to ``roi`` from a
    sensor of ``sensor_shape``, in units where ``(raw - black) / scale`` is the frame's value:
    (dark (0.0 or an array), gain (1.0 or an array), bad (H, W) bool); a flat-field gain below
    :data:`MIN_GAIN` is a bad pixel (its gain set to 1)."""
    dark = 0.0
    if cal.dark is not None:
        dark = (_fit(cal.dark, "dark frame", cal.names.get("dark", ""), shape, roi, sensor_shape) - black) / scale
    bad = np.zeros(shape[:2], dtype=bool)
    if cal.bad is not None:
        bad |= _fit(cal.bad, "bad-pixel map", cal.names.get("bad_pixels", ""), shape, roi, sensor_shape)
    gain = 1.0
    if cal.flat is not None:
        response = (_fit(cal.flat, "flat field", cal.names.get("flat", ""), shape, roi, sensor_shape) - black) / scale
        response = response - dark
        mean = response[~bad].mean(axis=0) if (~bad).any() else 0.0
        if not np.all(np.asarray(mean) > 0):
            raise HbisInputError(f"flat field {cal.names.get('flat', '')} is no brighter than the dark frame")
        gain = response / mean
        weak = gain < MIN_GAIN
        bad |= weak.any(axis=-1) if weak.ndim == 3 else weak
        gain = np.where(gain < MIN_GAIN, 1.0, gain)
    return dark, gain, bad
