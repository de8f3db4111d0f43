"""The single-frame baseline: the reference frame alone, enlarged bicubically onto the output grid
(:func:`hbis_torch.reconstruct.single_frame.single_frame`, also a burst's fallback)."""

from __future__ import annotations

from hbis_torch.reconstruct.single_frame import single_frame

__all__ = ["ALIASES", "SINGLE_FRAME", "single_frame"]

#: Names of the baseline in :func:`hbis_torch.validate.cross_validate` (the second is an alias).
SINGLE_FRAME = "single-frame"
ALIASES = {"bicubic": SINGLE_FRAME, "single": SINGLE_FRAME, "single-frame": SINGLE_FRAME}
