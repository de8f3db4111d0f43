"""The classical method's burst path (the ``burst`` function of its registry entry):
:func:`hbis_torch.reconstruct.burst.reconstruct_burst` hands it the brightness-corrected frames,
their positions on the reference grid and their robustness weights."""

from __future__ import annotations

import numpy as np
from torch import Tensor

from hbis_torch.reconstruct.classical.sr import classical_sr


def classical_burst(stack, frames: Tensor, positions: Tensor, weights: Tensor, *, messages: list | None = None,
                    deblur: bool = True, **kw) -> np.ndarray:
    """The classical method's burst path: splat with the robustness weights, then the Wiener
    deblurring of the pixel area (no optics recorded: no optical cutoff).

    Returns (S H, S W) float32 in [0, 1]."""
    return classical_sr(frames, positions, stack.h, deblur, weights=weights, cutoff=None, **kw).numpy()
