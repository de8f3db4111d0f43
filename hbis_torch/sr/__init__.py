"""Super-resolution of HBIS stacks: the classical baseline (scattered-sample interpolation and
Wiener deblurring) and the choice of h for a scene."""

from .classical import classical_sr, optical_sample_positions, reconstruct

__all__ = ["classical_sr", "optical_sample_positions", "reconstruct"]
