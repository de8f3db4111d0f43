"""Learned multi-frame super-resolution: the network runs in onnxruntime, not torch (but for a
burst's test-time adaptation, :mod:`.adapt`, which fine-tunes it in PyTorch first).

The network (:mod:`.network`, trained and exported on the build side, :mod:`hbis_torch.training`)
refines the classical reconstruction: it
sees the classical image cut into the h^2 sub-pixel phases of the LR grid and a per-pixel map of
the frames' noise level (:func:`network_inputs`), from the stack's sensor model or measured from
the frames. So it takes any stack the classical method takes (any reference frame, any scan,
frames left out), and the optics enter through the classical step's transfer function.
:class:`LearnedSR` runs an exported model in onnxruntime, in tiles so that a full 960 x 1280
frame fits in memory, and :func:`learned_sr` does the whole thing for a
:class:`~hbis_torch.stack_io.Stack`.

Where the default model is found
--------------------------------
``hbis_torch/models/hbis_sr_h{h}.onnx``, package data found through importlib.resources, so a
wheel, an sdist and a checkout find it the same way. The environment variable ``HBIS_MODELS_DIR`` overrides the
folder; ``model=`` (``hbis reconstruct --model``) names any other file.

Modules
-------
:mod:`.architecture`
    The network's architecture (:class:`Architecture`: kind, width, blocks, h), read from a
    model's metadata; it sizes the tiles' halo.
:mod:`.inputs`
    Numpy glue around any runner of the network: the noise model
    (:func:`noise_params_from_meta`, :func:`estimate_noise_params`), :func:`network_inputs`,
    :func:`run_tiled`, :func:`self_ensemble` and :func:`tile_ensemble` (:func:`default_ensemble`),
    :func:`super_resolve`.
:mod:`.runtime`
    onnxruntime: model discovery (:func:`models_dir`, :func:`default_model_path`), session
    options and execution providers, :class:`LearnedSR`, model metadata. onnxruntime and onnx
    are imported lazily, inside the functions that use them.
:mod:`.method`
    A whole stack: :func:`learned_sr` and :func:`reconstruct_learned` (the ``"learned"`` entry
    of :data:`hbis_torch.reconstruct.METHODS`): the classical image
    (:func:`hbis_torch.reconstruct.classical.reconstruct_classical`), refined.
:mod:`.domain`
    A model's training domain and validation gain, read from its metadata, and the check that a
    stack lies inside it.

Nothing here imports torch's network or the training pipeline (:mod:`hbis_torch.training`).
"""

from __future__ import annotations

from hbis_torch.reconstruct.learned.architecture import Architecture
from hbis_torch.reconstruct.learned.inputs import (
    NOISE_SCALE,
    TILE_HALO,
    default_ensemble,
    estimate_noise_params,
    network_inputs,
    noise_params_from_meta,
    run_tiled,
    self_ensemble,
    sensor_noise_params,
    super_resolve,
    tile_ensemble,
)
from hbis_torch.reconstruct.learned.method import learned_sr, reconstruct_learned
from hbis_torch.reconstruct.learned.runtime import (
    MODEL_FORMAT,
    NORMALISATION,
    OPENVINO,
    PRECISIONS,
    PROVIDERS,
    LearnedSR,
    available_providers,
    default_model_path,
    default_threads,
    execution_providers,
    int8_path,
    metadata_json,
    models_dir,
    onnxruntime_distributions,
    read_model_metadata,
    session_options,
)

__all__ = [
    "Architecture",
    "LearnedSR",
    "MODEL_FORMAT",
    "NOISE_SCALE",
    "NORMALISATION",
    "OPENVINO",
    "PRECISIONS",
    "PROVIDERS",
    "TILE_HALO",
    "available_providers",
    "default_model_path",
    "default_threads",
    "estimate_noise_params",
    "execution_providers",
    "int8_path",
    "learned_sr",
    "metadata_json",
    "models_dir",
    "network_inputs",
    "noise_params_from_meta",
    "onnxruntime_distributions",
    "read_model_metadata",
    "reconstruct_learned",
    "run_tiled",
    "sensor_noise_params",
    "session_options",
    "super_resolve",
]
