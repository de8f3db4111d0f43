"""The reconstruction layer: super-resolution of HBIS stacks, every method in one place.

Where each part lives
---------------------
:mod:`hbis_torch.reconstruct.registry`
    :data:`METHODS` (``"classical"``, ``"learned"``: one explicit dict) and :func:`reconstruct`,
    the dispatcher that ``hbis reconstruct`` and the system pipeline call.
:mod:`hbis_torch.reconstruct.positions`
    The one sample-position policy of every method: the optics, corrected by registration where
    the data is trusted (:func:`~hbis_torch.reconstruct.positions.stack_sample_positions`,
    :data:`~hbis_torch.reconstruct.positions.REGISTRATIONS`); what each method does with the
    frames the registration could not trust is written down there.
:mod:`hbis_torch.reconstruct.classical`
    The classical baseline: scattered-sample interpolation and Wiener deblurring
    (:func:`classical_sr`; the stack-level entry ``classical.method.reconstruct_classical``).
:mod:`hbis_torch.reconstruct.learned`
    The learned network (trained and exported by :mod:`hbis_torch.training`) run in onnxruntime
    (:func:`learned_sr`; the stack-level entry ``learned.method.reconstruct_learned``).
:mod:`hbis_torch.reconstruct.adaptive_h`
    Which h a scene needs (:func:`recommend_h`).
"""

from hbis_torch.reconstruct.adaptive_h import HChoice, recommend_h
from hbis_torch.reconstruct.classical import classical_sr
from hbis_torch.reconstruct.learned import learned_sr
from hbis_torch.reconstruct.positions import REGISTRATIONS, optical_sample_positions, stack_sample_positions
from hbis_torch.reconstruct.registry import METHODS, reconstruct

__all__ = [
    "HChoice",
    "METHODS",
    "REGISTRATIONS",
    "classical_sr",
    "learned_sr",
    "optical_sample_positions",
    "reconstruct",
    "recommend_h",
    "stack_sample_positions",
]
