"""The reconstruction layer: super-resolution of HBIS stacks, every method in one place.

Where each part lives
---------------------
:mod:`hbis_torch.reconstruct.registry`
    :data:`METHODS` (``"classical"``, ``"learned"``), :func:`register` (a method is one module
    plus one :class:`Method` entry: its name, options, run function and optional raw-Bayer
    path) and :func:`reconstruct`, the dispatcher that ``hbis reconstruct`` and the system
    pipeline call.
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
:mod:`hbis_torch.reconstruct.classical.adaptive_h`
    Which h a scene needs (:func:`recommend_h`).
"""

from hbis_torch.lazy import lazy_exports

# Names handed on from the modules that define them, imported on first use (PEP 562), so that
# the registry (``hbis reconstruct --help`` reads it) comes without torch.
_HOMES = {
    "HChoice": "classical.adaptive_h",
    "recommend_h": "classical.adaptive_h",
    "classical_sr": "classical",
    "learned_sr": "learned",
    "REGISTRATIONS": "positions",
    "optical_sample_positions": "positions",
    "stack_sample_positions": "positions",
    "METHODS": "registry",
    "Method": "registry",
    "Option": "registry",
    "reconstruct": "registry",
    "register": "registry",
}

__all__ = sorted(_HOMES)


__getattr__, __dir__ = lazy_exports(__name__, _HOMES, globals())
