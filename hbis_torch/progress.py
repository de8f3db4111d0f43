"""Progress bars: one rule for every step that can take more than a couple of seconds.

A bar shows (tqdm, on stderr) when stderr is a terminal and nobody switched bars off: the CLI's
``-q`` does (:func:`set_progress`), and so does ``HBIS_PROGRESS=0`` in the environment.
Library code asks :func:`progress_enabled` or wraps its loop in :func:`progress`.
"""

from __future__ import annotations

import os
import sys

_enabled: bool | None = None  # None: decide from the terminal and the environment


def set_progress(enabled: bool | None) -> None:
    """Switch progress bars on or off for this process (``None``: back to the automatic rule)."""
    global _enabled
    _enabled = enabled


def progress_enabled() -> bool:
    """Whether bars show: as set by :func:`set_progress`, else when stderr is a terminal and
    ``HBIS_PROGRESS`` is not ``0``."""
    if _enabled is not None:
        return _enabled
    if os.environ.get("HBIS_PROGRESS", "") == "0":
        return False
    try:
        return sys.stderr.isatty()
    except (AttributeError, ValueError):  # replaced or closed stderr
        return False


def progress(iterable=None, *, desc: str, total: int | None = None, unit: str = "it"):
    """A tqdm bar over ``iterable`` (or a manual one with ``total``), shown only where
    :func:`progress_enabled`; it leaves no line behind."""
    from tqdm import tqdm

    return tqdm(iterable, desc=desc, total=total, unit=unit, leave=False, disable=not progress_enabled(),
                dynamic_ncols=True)
