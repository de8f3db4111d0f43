"""The learned method's burst path (the ``burst`` function of its registry entry): the classical
burst image refined by the network for the burst's scale."""

from __future__ import annotations

import numpy as np
from torch import Tensor

from hbis_torch.reconstruct.classical.burst import burst_sr
from hbis_torch.reconstruct.learned.domain import unhelpful_model
from hbis_torch.reconstruct.learned.inputs import check_ensemble, estimate_noise_params, noise_params_from_meta
from hbis_torch.reconstruct.learned.method import _runner
from hbis_torch.reconstruct.learned.runtime import (NO_MODEL_REMEDY, available_tier, classical_returned, model_to_run,
                                                    tier_of)


def learned_burst(stack, frames: Tensor, positions: Tensor, weights: Tensor, *, messages: list | None = None,
                  model=None, threads: int | None = None, provider: str = "auto", extrapolate: bool = False,
                  ensemble: int | None = None, precision: str | None = None) -> np.ndarray:
    """The learned method's burst path: the classical burst image, refined by the network for the
    burst's scale, told the noise measured on the frames (a burst's samples lie on no regular
    lattice, where the scans' noise is measured); where no model is shipped for it, the classical image,
    with a message (:func:`~hbis_torch.reconstruct.learned.runtime.classical_returned`).

    Returns (S H, S W) float32 in [0, 1]."""
    model = available_tier(model, stack.h, messages)
    path, metadata, missing = model_to_run(model, stack.h, precision)
    ensemble = check_ensemble(ensemble, stack.h, tier_of(model))
    image = burst_sr(frames, positions, stack.h, weights).numpy()
    if missing is not None:
        return classical_returned(image, missing, messages, remedy=NO_MODEL_REMEDY)
    unhelpful = unhelpful_model(metadata)
    if unhelpful is not None and not extrapolate:
        return classical_returned(image, unhelpful, messages)
    noise = noise_params_from_meta(stack.meta) or estimate_noise_params(frames.numpy())
    runner = _runner(str(path.resolve()), path.stat().st_mtime_ns, threads, provider)
    return runner(image, noise, None, messages=messages, extrapolate=extrapolate, ensemble=ensemble)
