"""The learned method on a whole stack: :func:`learned_sr`, and :func:`reconstruct_learned`,
the ``"learned"`` entry of :data:`hbis_torch.reconstruct.registry.METHODS`."""

from __future__ import annotations

import functools

import numpy as np

from hbis_torch.errors import HbisInputError
from hbis_torch.reconstruct.classical import classical_sr, optics_cutoff, reconstruct_classical, stack_fill_factor
from hbis_torch.reconstruct.classical.method import reconstruct_classical_raw_bayer
from hbis_torch.reconstruct.learned.domain import unhelpful_model
from hbis_torch.reconstruct.learned.inputs import check_ensemble, estimate_noise_params, noise_params_from_meta
from hbis_torch.reconstruct.learned.runtime import (NO_MODEL_REMEDY, LearnedSR, available_tier, classical_returned,
                                                    model_to_run, tier_of)


def classical_and_noise(stack, registration: str = "optics", positions=None, messages: list | None = None,
                        lens_sigma: float | None = None) -> tuple[np.ndarray, tuple[float, float]]:
    """The classical image of a stack and its frames' noise parameters: the network's two inputs.

    The noise parameters (a, b) (variance ``a x + b`` of a frame value x in [0, 1]) are the
    stack's sensor model's (:func:`noise_params_from_meta`) where it has one, else measured on
    the classical step's lattice (:func:`~hbis_torch.reconstruct.classical.lattice_noise_params`:
    within a few per cent of the truth at h = 4 and 7 on photographs, where a single frame's
    estimate can be several times too high; docs/learned.md).

    Parameters
    ----------
    stack : hbis_torch.stack_io.Stack
    registration : {"optics", "data", "auto"}
        Where the positions come from when they are not given
        (:func:`~hbis_torch.reconstruct.classical.reconstruct_classical`).
    positions : array (F, H, W, 2), optional
        Sample positions in ROI-local reference LR pixels.
    messages : list, optional
        Receives the registration's warnings.
    lens_sigma : float, optional
        A Gaussian lens blur (LR px) the classical step undoes (``--psf-sigma``); None or 0: none.

    Returns
    -------
    image : ndarray, shape (h H, h W), float32 in [0, 1]
    (a, b) : (float, float)

    Raises
    ------
    HbisInputError
        A stack without a sensor model whose lattice is under 3 x 3 nodes (before any work).
    """
    params = noise_params_from_meta(stack.meta)
    rows, cols = (stack.h * n for n in stack.frames.shape[1:3])
    if params is None and min(rows, cols) < 3:  # the lattice's noise operator needs 3 x 3 nodes
        raise HbisInputError(f"the stack's lattice ({rows} x {cols} nodes) is too small to measure its noise on; "
                             "record the sensor (full_well_e, read_noise_e) in the stack's metadata")
    measured = None if params is not None else []
    if positions is None:
        image = reconstruct_classical(stack, registration, messages=messages, noise_params_out=measured,
                                      lens_sigma=lens_sigma)
    else:
        image = classical_sr(stack.to_float(), positions, stack.h, cutoff=optics_cutoff(stack.system),
                             fill_factor=stack_fill_factor(stack), noise_params_out=measured,
                             lens_sigma=lens_sigma).numpy()
    return image, params if params is not None else measured[0]


def learned_sr(stack, model=None, positions=None, threads: int | None = None,
               registration: str = "optics", messages: list | None = None,
               provider: str = "auto", extrapolate: bool = False, ensemble: int | None = None,
               precision: str | None = None, lens_sigma: float | None = None) -> np.ndarray:
    """Super-resolve a stack: the classical image, refined by an ONNX model in onnxruntime.

    The learned method takes every stack the classical method takes (any reference frame, any
    scan, frames left out by the registration): the network sees only the classical image and
    the frames' noise level (:mod:`hbis_torch.reconstruct.learned.network`).

    Parameters
    ----------
    stack : hbis_torch.stack_io.Stack
    model : path or {"fast", "best"}, optional
        A model file, or the shipped model of that tier for the stack's h
        (:data:`~hbis_torch.reconstruct.learned.runtime.TIERS`); defaults to the shipped fast
        model (:func:`default_model_path`). Where none
        is shipped (h other than 2, 3, 4 and 7), the classical image is returned, with a line in
        ``messages`` saying so; "best" where only a fast model is (h = 3) runs that one, and says so.
    positions : array (F, H, W, 2), optional
        Sample positions in ROI-local reference LR pixels; by default the classical method's
        (:func:`~hbis_torch.reconstruct.classical.reconstruct_classical` with ``registration``).
    threads : int, optional
        onnxruntime intra-op threads.
    registration : {"optics", "data", "auto"}
        Where the positions come from when they are not given. The default here is ``"optics"``
        (right for the simulated stacks its direct callers pass);
        :func:`hbis_torch.reconstruct.reconstruct` and ``hbis reconstruct`` default to ``"auto"``
        (:mod:`hbis_torch.reconstruct.positions`).
    messages : list, optional
        Receives the registration's warnings, and the line saying so when the stack lies outside
        the model's training domain (:mod:`hbis_torch.reconstruct.learned.domain`).
    provider : {"auto", "openvino", "cpu"}
        onnxruntime execution provider (:func:`execution_providers`).
    extrapolate : bool
        Run the network on a stack outside its training domain too (by default such a stack gets
        the classical image).
    ensemble : {1, 2, 4, 8} or None
        Average the network over this many of the square's symmetries (geometric self-ensemble,
        :func:`~hbis_torch.reconstruct.learned.inputs.self_ensemble`): as many times the network's
        cost (``training/eval_matrix.py --ensemble N`` measures the gain). None: the
        tier's default (:func:`~hbis_torch.reconstruct.learned.inputs.default_ensemble`: the fast
        models 2 at h = 3 and 7, where the classical step takes most of the time, else 1; the
        best models 2, and 8 at h = 7; a model file of no tier as the fast ones).
    precision : {"int8", "bf16", "fp32"} or None
        Which file of the model runs (:func:`~hbis_torch.reconstruct.learned.runtime.with_precision`;
        None: the file named, float32 for the shipped models; ``"int8"``: its int8 file;
        ``"bf16"``: the float32 file in OpenVINO in bfloat16, on CPUs with bf16 units).
    lens_sigma : float, optional
        A Gaussian lens blur (LR px) the classical step undoes (:func:`classical_and_noise`).

    Returns
    -------
    ndarray, shape (h H, h W), float32 in [0, 1]
    """
    # before any work; the session opens after the classical step
    model = available_tier(model, stack.h, messages)
    path, metadata, missing = model_to_run(model, stack.h, precision, provider)
    ensemble = check_ensemble(ensemble, stack.h, tier_of(model))
    image, noise_params = classical_and_noise(stack, registration, positions, messages, lens_sigma)
    if missing is not None:  # no shipped network for this h: as outside the training domain
        return classical_returned(image, missing, messages, remedy=NO_MODEL_REMEDY)
    unhelpful = unhelpful_model(metadata)
    if unhelpful is not None and not extrapolate:  # no session to open
        return classical_returned(image, unhelpful, messages)
    runner = _runner(str(path.resolve()), path.stat().st_mtime_ns, threads, provider, precision)
    return runner(image, noise_params, optics_cutoff(stack.system), messages=messages, extrapolate=extrapolate,
                  ensemble=ensemble)


@functools.lru_cache(maxsize=4)
def _runner(path: str, mtime_ns: int, threads: int | None, provider: str, precision: str | None = None) -> LearnedSR:
    """One session per model file (and its modification time), threads, provider and precision,
    kept for the next call: a loop over stacks does not compile the model again (30 ms with
    OpenVINO). ``path`` is the file :func:`model_to_run` chose for ``precision``."""
    return LearnedSR(model=path, threads=threads, provider=provider, precision=precision)


def reconstruct_learned(stack, registration: str = "auto", *, model=None, messages: list | None = None,
                        threads: int | None = None, provider: str = "auto", extrapolate: bool = False,
                        ensemble: int | None = None, precision: str | None = None, adapt: bool = True,
                        lens_sigma: float | None = None) -> np.ndarray:
    """The ``"learned"`` entry of :data:`hbis_torch.reconstruct.registry.METHODS` (``hbis reconstruct``).

    Unlike :func:`learned_sr`, the registration defaults to ``"auto"``, as for every method of
    :func:`hbis_torch.reconstruct.reconstruct`. ``adapt`` is the burst path's
    (:func:`~hbis_torch.reconstruct.learned.burst.learned_burst`); a scan's network is never adapted.
    """
    return learned_sr(stack, model=model, threads=threads, registration=registration, messages=messages,
                      provider=provider, extrapolate=extrapolate, ensemble=ensemble, precision=precision,
                      lens_sigma=lens_sigma)


def reconstruct_learned_raw_bayer(stack, registration: str = "auto", *, messages: list | None = None, model=None,
                                  threads: int | None = None, provider: str = "auto", extrapolate: bool = False,
                                  ensemble: int | None = None, precision: str | None = None,
                                  adapt: bool = True, lens_sigma: float | None = None) -> np.ndarray:
    """The learned method on raw Bayer frames: each plane of the classical joint demosaicking
    refined by the network, with the noise of the sensor model or of one colour's sub-lattice: the
    ``raw_bayer`` path of the ``"learned"`` entry of :data:`hbis_torch.reconstruct.registry.METHODS`.
    Keywords as for :func:`reconstruct_learned`; returns (h H, h W, 3) float32.
    """
    model = available_tier(model, stack.h, messages)
    path, _, missing = model_to_run(model, stack.h, precision, provider)
    ensemble = check_ensemble(ensemble, stack.h, tier_of(model))
    planes = reconstruct_classical_raw_bayer(stack, registration, messages=messages, lens_sigma=lens_sigma)
    if missing is not None:  # as learned_sr: the classical image, said so
        return classical_returned(planes, missing, messages, remedy=NO_MODEL_REMEDY)
    runner = _runner(str(path.resolve()), path.stat().st_mtime_ns, threads, provider, precision)
    noise = noise_params_from_meta(stack.meta)
    if noise is None:  # one colour's pixels: a plain image of one sensor's noise, no mosaic in it
        noise = estimate_noise_params(stack.to_float().numpy()[:, 0::2, 0::2])
    cutoff = optics_cutoff(stack.system)
    notes: list[str] = []
    out = np.stack([runner(np.ascontiguousarray(planes[..., c]), noise, cutoff, messages=notes,
                           extrapolate=extrapolate, ensemble=ensemble) for c in range(3)], axis=-1)
    if messages is not None:
        messages.extend(dict.fromkeys(notes))  # the same line for each plane: once
    return out
