"""The classical method's burst path (the ``burst`` function of its registry entry):
:func:`hbis_torch.reconstruct.burst.reconstruct_burst` hands it the brightness-corrected frames,
their positions on the reference grid and their robustness weights."""

from __future__ import annotations

import math

import numpy as np
from torch import Tensor

from hbis_torch.reconstruct.classical.sr import _peak_weight, classical_sr, lattice_image, lattice_noise

# The scale whose lattice a burst's samples fill, where their noise is measured for finer scales.
NOISE_SCALE = 2


def burst_sample_noise(frames: Tensor, positions: Tensor, weights: Tensor, kernel_sigma: float = 0.45) -> float:
    """The noise standard deviation of one sample of a burst, measured on its lattice at scale
    :data:`NOISE_SCALE` (:func:`~hbis_torch.reconstruct.classical.lattice_noise`, times the
    square root of the samples a node gets there).

    Parameters
    ----------
    frames : Tensor, shape (F, H, W), float32
    positions : Tensor, shape (F, H, W, 2), float64
    weights : Tensor, shape (F, H, W), float64
    kernel_sigma : float
        The splat Gaussian (HR px).
    """
    image, den, _, typical = lattice_image(frames, positions, NOISE_SCALE, kernel_sigma, weights,
                                           mixed_offsets=True)
    samples_per_node = typical / max(_peak_weight(kernel_sigma), 1e-12)
    return lattice_noise(image, kernel_sigma, den > 0.5 * typical) * math.sqrt(max(samples_per_node, 1.0))


def burst_sr(frames: Tensor, positions: Tensor, scale: int, weights: Tensor, deblur: bool = True, **kw) -> Tensor:
    """The classical image of a burst's samples: splat with the robustness weights, then the
    Wiener deblurring of the pixel area (a burst records no optics: no optical cutoff).

    Samples of many frames at different offsets share the lattice's nodes (``mixed_offsets``).
    The Wiener filter's noise is measured on the lattice, as a scan's, but at scales above
    :data:`NOISE_SCALE` never taken below :func:`burst_sample_noise` averaged over the samples a
    node gets. A scan puts a sample on every node; a burst's random shifts leave nodes empty
    where a node gets about one sample or fewer (S = 3 and 4). The empty nodes are filled
    smoothly, and the lattice's own estimate fell to a third of the noise there (Emily at
    S = 4). The floor raised classical - single frame on the shared real sequences, by
    ``hbis validate``, from +3.34 / +2.38 to +3.51 / +2.87 dB at S = 3 / 4, and on held-out
    simulated bursts against the truth by +0.19 / +0.19 dB (docs/real-bursts.md).

    Parameters
    ----------
    frames : Tensor, shape (F, H, W), float32
    positions : Tensor, shape (F, H, W, 2), float64
    scale : int
    weights : Tensor, shape (F, H, W), float64
    deblur : bool
    **kw
        :func:`~hbis_torch.reconstruct.classical.classical_sr`'s other options (``fit_holes``
        on by default: a burst's random shifts leave holes that the samples around them fill).

    Returns
    -------
    Tensor, shape (S H, S W), float32 in [0, 1]
    """
    if deblur and scale > NOISE_SCALE and kw.get("noise") is None and "noise_floor" not in kw:
        kw["noise_floor"] = burst_sample_noise(frames, positions, weights, kw.get("kernel_sigma", 0.45))
    kw.setdefault("fit_holes", True)
    return classical_sr(frames, positions, scale, deblur, weights=weights, cutoff=None, mixed_offsets=True, **kw)


def classical_burst(stack, frames: Tensor, positions: Tensor, weights: Tensor, *, messages: list | None = None,
                    deblur: bool = True, **kw) -> np.ndarray:
    """The classical method's burst path: :func:`burst_sr` at the stack's scale.

    Returns (S H, S W) float32 in [0, 1]."""
    return burst_sr(frames, positions, stack.h, weights, deblur, **kw).numpy()


# Takes the positions as :class:`~hbis_torch.reconstruct.positions.BurstPositions` and the weights
# in float32 (:func:`~hbis_torch.reconstruct.burst.reconstruct_burst` reads this): the lattice
# reads both a band at a time.
classical_burst.streams = True
# Takes ``shared`` (classical_sr's): a colour burst's channels, the same samples, share what
# depends on their places and weights alone.
classical_burst.shares_samples = True
# The lattice fill's blend with the single frame only for bursts asked at S = 2 (or filling no
# scale's lattice): above it, a scale the samples fill on average deblurs better than the blend
# (hbis_torch.reconstruct.burst_fill.RUN_FILL's notes).
classical_burst.fill_blend_to = 2
