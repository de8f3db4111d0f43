"""Every reconstruction method by name, and :func:`reconstruct`, which dispatches to them.

The registry is the one place that lists the methods; it imports both methods' entry functions
and nothing registers itself on import. Importing it does not import onnxruntime or onnx (the
learned method imports them when it runs).
"""

from __future__ import annotations

import numpy as np

from hbis_torch.errors import HbisInputError
from hbis_torch.reconstruct.classical.method import reconstruct_classical
from hbis_torch.reconstruct.learned.method import reconstruct_learned

# Reconstruction methods by name: function(stack, registration=..., messages=None, **kw) ->
# (h*H, h*W) float32 array in [0, 1] ("messages": a list that receives warnings, or None).
# Another method is added with one entry here.
METHODS = {"classical": reconstruct_classical, "learned": reconstruct_learned}


def reconstruct(stack, method: str = "classical", registration: str = "auto", **kw) -> np.ndarray:
    """Super-resolve a stack onto the h-times grid of its reference frame's ROI.

    Parameters
    ----------
    stack : hbis_torch.stack_io.Stack
    method : str
        A key of :data:`METHODS` ("classical", "learned").
    registration : {"optics", "data", "auto"}
        Where the samples' positions come from: the tracer alone (exact for simulated stacks
        whose phases are the true ones); the tracer corrected by registering the frames
        (frames that cannot be registered are left out); or that correction where the data is
        trusted and the tracer elsewhere ("auto", the default for every method). The learned
        method cannot leave frames out: with "data" it keeps the optical positions of the frames
        the registration could not trust, as with "auto" (:mod:`hbis_torch.reconstruct.positions`).
    **kw
        Passed to the method (for classical: ``deblur``, ``messages`` (a list that receives the
        registration's warnings), ``fill_factor``, and :func:`classical_sr`'s keywords; for
        learned: ``model``, ``messages``, ``threads``, ``provider``). A colour stack (RGB frames
        or raw Bayer with a ``cfa`` key) goes through :func:`hbis_torch.reconstruct.colour.
        reconstruct_colour`, which also takes ``colour`` ("luma" or "channels").

    Returns
    -------
    np.ndarray, shape (h*H, h*W) (or (h*H, h*W, 3) for a colour stack), float32 in [0, 1]
    """
    if method not in METHODS:
        raise HbisInputError(f"unknown reconstruction method {method!r}; available: {', '.join(METHODS)}")
    if registration == "data" and len(stack.frames) > 1:
        ref = stack.frames[stack.reference_index]
        if ref.min() == ref.max():  # nothing to register to: every other frame would be left out
            raise HbisInputError(f"the reference frame {stack.reference_index} is uniform (every pixel "
                                 f"{ref.flat[0]}), so no frame can be registered to it: use --registration "
                                 "optics or auto")
    if getattr(stack, "colour", False):  # RGB or raw Bayer frames: every method, through one wrapper
        from hbis_torch.reconstruct.colour import reconstruct_colour

        return reconstruct_colour(stack, method, registration=registration, **kw)
    kw.pop("colour", None)
    return METHODS[method](stack, registration=registration, **kw)
