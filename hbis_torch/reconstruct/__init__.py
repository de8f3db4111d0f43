"""Super-resolution of HBIS stacks: the classical baseline (scattered-sample interpolation and
Wiener deblurring, :mod:`.classical`), the learned network run in onnxruntime (:mod:`.learned`)
and the choice of h for a scene (:mod:`.adaptive_h`)."""

from hbis_torch.reconstruct import learned  # noqa: F401  (registers METHODS["learned"], so reconstruct() knows it)
from hbis_torch.reconstruct.adaptive_h import HChoice, recommend_h
from hbis_torch.reconstruct.classical import METHODS, classical_sr, optical_sample_positions, reconstruct

__all__ = ["HChoice", "METHODS", "classical_sr", "optical_sample_positions", "reconstruct", "recommend_h"]
