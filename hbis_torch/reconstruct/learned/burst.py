"""The learned method's burst path (the ``burst`` function of its registry entry): the classical
burst image refined by the network for the burst's scale, by default first adapted to the
burst's own frames (:mod:`hbis_torch.reconstruct.learned.adapt`)."""

from __future__ import annotations

import functools
import time
import weakref

import numpy as np
from torch import Tensor

from hbis_torch.reconstruct.classical.burst import burst_sr
from hbis_torch.reconstruct.learned.domain import domain_from_metadata, outside_domain, unhelpful_model
from hbis_torch.reconstruct.learned.inputs import check_ensemble, estimate_noise_params, noise_params_from_meta
from hbis_torch.reconstruct.learned.method import _runner
from hbis_torch.reconstruct.learned.runtime import (NO_MODEL_REMEDY, available_tier, classical_returned,
                                                    model_to_run, tier_of)

# The last adaptation, kept for the next call on the same samples: a colour burst's channels
# share the motion (one positions tensor), and the network adapted on the first serves all three.
_last: dict = {}


def learned_burst(stack, frames: Tensor, positions: Tensor, weights: Tensor, *, messages: list | None = None,
                  model=None, threads: int | None = None, provider: str = "auto", extrapolate: bool = False,
                  ensemble: int | None = None, precision: str | None = None, adapt: bool = True,
                  lens_sigma: float | None = None, lens_doubt: float = 0.0, shared: dict | None = None) -> np.ndarray:
    """The learned method's burst path: the classical burst image, refined by the network for the
    burst's scale, told the noise measured on the frames (a burst's samples lie on no regular
    lattice, where the scans' noise is measured); where no model is shipped for it, the classical image,
    with a message (:func:`~hbis_torch.reconstruct.learned.runtime.classical_returned`).

    With ``adapt`` (the default) the network's last convolution is first fine-tuned to predict
    the burst's own left-out frames (:func:`~hbis_torch.reconstruct.learned.adapt.adapt_refiner`),
    in at most :data:`~hbis_torch.reconstruct.learned.adapt.BUDGET_X_CLASSICAL` times the time
    this call's classical step took (at least :data:`~hbis_torch.reconstruct.learned.adapt.BUDGET_MIN_S`),
    and the network runs in PyTorch, float32. A burst whose noise lies outside the model's training range is then
    refined too where the adapted network predicts the left-out frames better than the classical
    image does (else it gets the classical image, said so). A model without its PyTorch weights
    beside it (``NAME.pt``), or a burst with fewer than two usable frames besides the reference,
    is refined without adaptation, said so.

    ``lens_sigma`` (LR px) is the lens blur the classical image undoes, as the classical method's
    (:func:`~hbis_torch.reconstruct.burst.reconstruct_burst` measures it where none is given); the
    adaptation's folds undo the same, and its forward model may blur by it
    (:func:`~hbis_torch.reconstruct.learned.adapt.forward_blur`), as it does where ``lens_doubt``
    (the lens estimate's :attr:`~hbis_torch.reconstruct.lens_blur.LensEstimate.doubt`) says the
    classical image kept some of the edges' blur. ``shared`` is the classical image's
    (:func:`~hbis_torch.reconstruct.classical.sr.classical_sr`'s: a colour burst's channels).

    Returns (S H, S W) float32 in [0, 1]."""
    model = available_tier(model, stack.h, messages)
    path, metadata, missing = model_to_run(model, stack.h, precision, provider)
    ensemble = check_ensemble(ensemble, stack.h, tier_of(model))
    started = time.perf_counter()
    classical = functools.partial(burst_sr, lens_sigma=lens_sigma or 0.0)
    image = classical(frames, positions, stack.h, weights, shared=shared).numpy()  # (not the folds': other samples)
    classical_s = time.perf_counter() - started
    if missing is not None:
        return classical_returned(image, missing, messages, remedy=NO_MODEL_REMEDY)
    unhelpful = unhelpful_model(metadata)
    if unhelpful is not None and not extrapolate:
        return classical_returned(image, unhelpful, messages)
    noise = noise_params_from_meta(stack.meta) or estimate_noise_params(frames.numpy())
    outside = None if extrapolate else outside_domain(domain_from_metadata(metadata), noise, None)
    if adapt:
        refined = _adapted(path, stack, frames, positions, weights, image, noise, ensemble, outside, messages,
                           precision, classical_s, classical, lens_doubt)
        if refined is not None:
            return refined
    if outside is not None:
        return classical_returned(image, outside, messages)
    runner = _runner(str(path.resolve()), path.stat().st_mtime_ns, threads, provider, precision)
    return runner(image, noise, None, messages=messages, extrapolate=True, ensemble=ensemble)


def _adapted(path, stack, frames, positions, weights, image, noise, ensemble, outside, messages, precision,
             classical_s, classical, lens_doubt: float = 0.0):
    """The image refined by the network adapted to the burst, or None where it cannot be adapted
    (the line saying why goes to ``messages``). The adaptation gets :data:`~hbis_torch.reconstruct.
    learned.adapt.BUDGET_X_CLASSICAL` times ``classical_s`` (the classical step's seconds), at
    least :data:`~hbis_torch.reconstruct.learned.adapt.BUDGET_MIN_S`."""
    from hbis_torch.progress import progress
    from hbis_torch.reconstruct.learned.adapt import (BLUR_PX, BUDGET_MIN_S, BUDGET_X_CLASSICAL, STEPS, adapt_refiner,
                                                      forward_blur, load_refiner, pytorch_weights, refine)

    notes = messages if messages is not None else []
    weights_file = pytorch_weights(path)
    if weights_file is None:
        notes.append(f"no PyTorch weights beside {path.name} (NAME.pt): the network is not adapted to the burst")
        return None
    lens_sigma = classical.keywords["lens_sigma"]
    key = (str(weights_file), stack.h, stack.reference_index, lens_sigma, lens_doubt)
    cached = _last.get("positions")
    if cached is not None and cached() is positions and _last.get("key") == key:
        adaptation = _last["adaptation"]
    else:
        budget = max(BUDGET_X_CLASSICAL * classical_s, BUDGET_MIN_S)
        with progress(total=STEPS, desc="adapting the network to the burst", unit="step") as bar:
            adaptation = adapt_refiner(load_refiner(weights_file), frames, positions, weights, stack.h, noise,
                                       stack.reference_index, classical, on_step=bar.update, budget_s=budget,
                                       lens_sigma=lens_sigma, lens_doubt=lens_doubt)
        _last.clear()
        _last.update(positions=weakref.ref(positions), key=key, adaptation=adaptation)
        if adaptation is None:
            notes.append("fewer than two usable frames besides the reference: the network is not adapted to the burst")
        else:
            stopped = f", its time of {budget:.1f} s spent" if adaptation.out_of_time else ""
            notes.append(f"the network was adapted to the burst's own frames ({adaptation.steps_taken} of {STEPS} "
                         f"steps in {adaptation.seconds:.1f} s{stopped}; the weights of step {adaptation.step} "
                         f"kept): mean squared error of the left-out frames' "
                         f"prediction {adaptation.error_before:.3g} unadapted, {adaptation.error_after:.3g} adapted, "
                         f"{adaptation.error_classical:.3g} from the classical image")
            blur = forward_blur(lens_sigma, lens_doubt)
            if lens_doubt > 0 and blur > BLUR_PX:
                notes.append(f"the adaptation's forward model blurred by {blur:.2f} LR px, towards the lens the "
                             f"classical image undid, not {BLUR_PX} LR px: the edges were too soft for all of their "
                             "blur to be undone, and through less the network would learn to blur the image further")
    if adaptation is None:
        return None
    if outside is not None and adaptation.error_after >= adaptation.error_classical:
        return classical_returned(image, outside + ", and the adapted network did not predict the left-out frames "
                                  "better", messages)
    if precision in ("int8", "bf16"):
        notes.append(f"the adapted network runs in float32 (PyTorch), not in {precision}; --no-adapt runs that")
    return refine(adaptation.net, image, stack.h, noise, ensemble)
# The lattice fill's blend with the single frame as for the classical method (only for bursts asked
# at S = 2, or filling no scale's lattice): the network refines the classical image, and on the
# training simulator (photographs at 640 x 480, S = 3 with 8 frames and S = 4 with 16, two seeds)
# the blend above S = 2 left the refined image behind the unblended classical one.
learned_burst.fill_blend_to = 2
# Takes ``shared`` for its classical image (a colour burst's channels: classical_burst's notes).
learned_burst.shares_samples = True
# Takes the positions as a BurstPositions and the weights in float32, as classical_burst does: its
# classical image reads them a band at a time and the adaptation reads its window's alone. Given
# whole, a 16-frame 12 MP burst's positions and float64 weights were 4.5 GB, and the learned method
# peaked at 10 GB where the classical one peaks at 4 (benchmarks/results/bench_burst_budget_*.json).
# The same bits either way (tests/test_burst.py).
learned_burst.streams = True
# Takes ``lens_doubt``, the lens estimate's doubt, where the lens is estimated (reconstruct_burst
# hands it): the adaptation's forward model reads it (adapt.forward_blur).
learned_burst.reads_lens_doubt = True
