"""Checks at the door: the values many parts of hbis-torch take, validated by one rule each.

Each function returns the value in the form the code uses (an ``int``, a tuple, a float64
tensor) or raises :class:`~hbis_torch.errors.HbisInputError` with a one-line message.
"""

from __future__ import annotations

import argparse
import math

from typing import TYPE_CHECKING

from hbis_torch.config import Camera
from hbis_torch.errors import HbisInputError

if TYPE_CHECKING:  # numpy and torch are imported where a check needs them: the CLI's --help loads neither
    from torch import Tensor

Roi = tuple[int, int, int, int]

#: The largest resolution improvement factor hbis-torch accepts: 256 frames a stack.
MAX_H = 16
#: The largest prism phase accepted, degrees (a thousand turns and more; beyond it a float64
#: angle loses the 1e-9 degree a scan plan resolves).
MAX_PHASE_DEG = 1e6


def check_h(h, minimum: int = 1) -> int:
    """A resolution improvement factor: an integer (Python or NumPy) from ``minimum`` to 16.

    ``minimum`` is 2 where h = 1 means nothing (the network has no sub-pixel phases to combine).

    Examples
    --------
    >>> import numpy as np
    >>> from hbis_torch.checks import check_h
    >>> check_h(np.int64(4))
    4
    >>> check_h(17)
    Traceback (most recent call last):
    ...
    hbis_torch.errors.HbisInputError: h must be an integer from 1 to 16, got 17
    """
    import numpy as np

    if isinstance(h, (bool, np.bool_)) or not isinstance(h, (int, np.integer)) or not minimum <= int(h) <= MAX_H:
        raise HbisInputError(f"h must be an integer from {minimum} to {MAX_H}, got {h!r}")
    return int(h)


def check_roi(camera: Camera, roi: Roi | None) -> Roi:
    """Return a validated ``(u0, v0, width, height)`` in pixels; ``None`` gives the whole sensor.

    Examples
    --------
    >>> from hbis_torch import Camera
    >>> from hbis_torch.checks import check_roi
    >>> camera = Camera()
    >>> check_roi(camera, None)
    (0, 0, 1280, 960)
    >>> check_roi(camera, (608, 456, 64, 48))
    (608, 456, 64, 48)
    >>> check_roi(camera, (1270, 0, 64, 64))
    Traceback (most recent call last):
    ...
    hbis_torch.errors.HbisInputError: roi (1270, 0, 64, 64) lies outside the ... sensor
    """
    if roi is None:
        return (0, 0, camera.cols, camera.rows)
    try:
        u0, v0, width, height = (int(r) for r in roi)
    except (TypeError, ValueError):
        raise HbisInputError(f"roi must be four integers (u0, v0, width, height), got {roi!r}")
    if width < 1 or height < 1:
        raise HbisInputError(f"roi {roi!r} is empty: width and height must be at least 1")
    if u0 < 0 or v0 < 0 or u0 + width > camera.cols or v0 + height > camera.rows:
        raise HbisInputError(
            f"roi {roi!r} lies outside the {camera.rows} x {camera.cols} (rows x cols) sensor"
        )
    return (u0, v0, width, height)


def check_phases(phases_deg) -> Tensor:
    """Prism phases in degrees, shape (F, 2) (a single pair may be given as (2,)), as float64."""
    import torch

    phases = torch.as_tensor(phases_deg, dtype=torch.float64)
    if phases.ndim == 1 and phases.shape[0] == 2:
        phases = phases[None]
    if phases.ndim != 2 or phases.shape[1] != 2 or phases.shape[0] < 1:
        raise HbisInputError(f"phases must have shape (F, 2), got {tuple(phases.shape)}")
    if not bool(torch.isfinite(phases).all()):
        raise HbisInputError("phases contain non-finite values (NaN or infinite)")
    if bool((phases.abs() > MAX_PHASE_DEG).any()):
        raise HbisInputError(f"phases must lie within +-{MAX_PHASE_DEG:g} degrees")
    return phases


def check_phase_pair(phases_deg) -> tuple[float, float]:
    """Two finite angles in degrees, as a tuple of floats."""
    try:
        values = [float(v) for v in phases_deg]
    except (TypeError, ValueError):
        raise HbisInputError(f"phases must be two numbers in degrees, got {phases_deg!r}")
    if len(values) != 2 or not all(math.isfinite(v) for v in values):
        raise HbisInputError(f"phases must be two finite numbers in degrees, got {phases_deg!r}")
    if max(abs(v) for v in values) > MAX_PHASE_DEG:
        raise HbisInputError(f"phases must lie within +-{MAX_PHASE_DEG:g} degrees, got {phases_deg!r}")
    return values[0], values[1]


def as_float64_tensor(x, name: str) -> Tensor:
    """An array-like of real, finite numbers as a float64 tensor (NumPy arrays are not copied
    before the cast)."""
    import numpy as np
    import torch

    if isinstance(x, np.ndarray):
        x = torch.from_numpy(np.ascontiguousarray(x))
    if not isinstance(x, torch.Tensor):
        try:
            x = torch.as_tensor(x)
        except (TypeError, ValueError, RuntimeError):
            raise HbisInputError(f"{name} must be an array of numbers") from None
    if x.dtype == torch.bool or x.is_complex():
        raise HbisInputError(f"{name} must be real numbers, got {x.dtype}")
    x = x.to(torch.float64)
    if not torch.isfinite(x).all():
        raise HbisInputError(f"{name} contain non-finite values (NaN or inf)")
    return x


# --------------------------------------------------------------------------- command-line numbers

_MAX_NUMBER_CHARS = 64  # no sensible number is longer; int() of 5,000 digits is refused or slow


def bounded_int(lo: int, hi: int):
    """An argparse ``type=`` for an integer from ``lo`` to ``hi`` (inclusive).

    A bad value raises ``argparse.ArgumentTypeError``: argparse prints one line, exit code 2.
    """

    def parse(text: str) -> int:
        try:
            if len(text) > _MAX_NUMBER_CHARS:
                raise ValueError
            value = int(text, 10)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer from {lo} to {hi}, got {text[:40]!r}") from None
        if not lo <= value <= hi:
            raise argparse.ArgumentTypeError(f"must be an integer from {lo} to {hi}, got {value}")
        return value

    parse.__name__ = "integer"
    return parse


def auto_or(parse):
    """An argparse ``type=`` that reads ``auto`` as None (the method decides) and anything else with
    ``parse``."""

    def parse_or_auto(text: str):
        return None if text.strip().lower() == "auto" else parse(text)

    parse_or_auto.__name__ = getattr(parse, "__name__", "value")
    return parse_or_auto


def bounded_float(lo: float, hi: float, *, lo_open: bool = False, hi_open: bool = False):
    """An argparse ``type=`` for a finite number in [lo, hi] (``lo_open``/``hi_open``: excluded).

    NaN and infinities are refused like any number out of range.
    """
    span = f"{'(' if lo_open else '['}{lo:g}, {hi:g}{')' if hi_open else ']'}"

    def parse(text: str) -> float:
        try:
            if len(text) > _MAX_NUMBER_CHARS:
                raise ValueError
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a number in {span}, got {text[:40]!r}") from None
        if not math.isfinite(value):
            raise argparse.ArgumentTypeError(f"must be a finite number in {span}, got {text!r}")
        if value < lo or value > hi or (lo_open and value == lo) or (hi_open and value == hi):
            raise argparse.ArgumentTypeError(f"must lie in {span}, got {value:g}")
        return value

    parse.__name__ = "number"
    return parse
