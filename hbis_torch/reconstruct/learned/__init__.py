"""Learned multi-frame super-resolution: the network runs in onnxruntime, not torch.

(torch is used only where the rest of the package uses it: tracing the sample positions, and
the network's definition for training and export.)

The network (:mod:`hbis_torch.reconstruct.learned.net`) sees the h^2 frames in *registered order* and, per pixel,
how far each sample sits from its nominal sub-pixel phase. :func:`prepare_inputs` builds both
from the frames and their sample positions (as given by the optics or by registration);
:class:`LearnedSR` runs an exported model on them, in tiles so that a full 960 x 1280 frame fits
in memory, and :func:`learned_sr` does the whole thing for a :class:`~hbis_torch.stack_io.Stack`.

Where the default model is found
--------------------------------
``hbis_torch/models/hbis_sr_h{h}.onnx``, package data found through importlib.resources, so a
wheel, an sdist and a checkout find it the same way. The environment variable ``HBIS_MODELS_DIR`` overrides the
folder; ``model=`` (``hbis reconstruct --model``) names any other file.

Modules
-------
:mod:`.net`
    The network in torch (:class:`HbisSRNet`), for training and export.
:mod:`.inputs`
    Numpy glue around any runner of the network: :func:`prepare_inputs`,
    :func:`exposure_gain`, :func:`run_tiled`, :func:`super_resolve`.
:mod:`.runtime`
    onnxruntime: model discovery (:func:`models_dir`, :func:`default_model_path`), session
    options and execution providers, :class:`LearnedSR`, model metadata. onnxruntime and onnx
    are imported lazily, inside the functions that use them.
:mod:`.method`
    A whole stack: :func:`learned_sr` and :func:`reconstruct_learned` (the ``"learned"`` entry
    of :data:`hbis_torch.reconstruct.METHODS`); positions from
    :func:`hbis_torch.reconstruct.positions.stack_sample_positions`.
"""

from __future__ import annotations

from hbis_torch.reconstruct.learned.inputs import (
    DARK_TARGET,
    MAX_GAIN,
    TILE_HALO,
    exposure_gain,
    prepare_inputs,
    run_tiled,
    super_resolve,
)
from hbis_torch.reconstruct.learned.method import learned_sr, reconstruct_learned
from hbis_torch.reconstruct.learned.net import (
    HbisSRNet,
    ResidualBlock,
    bilinear_kernel,
    count_parameters,
    depth_to_space,
    space_to_depth,
)
from hbis_torch.reconstruct.learned.runtime import (
    MODEL_FORMAT,
    NORMALISATION,
    OPENVINO,
    PROVIDERS,
    LearnedSR,
    available_providers,
    default_model_path,
    default_threads,
    execution_providers,
    metadata_json,
    models_dir,
    onnxruntime_distributions,
    read_model_metadata,
    session_options,
)

__all__ = [
    "DARK_TARGET",
    "HbisSRNet",
    "LearnedSR",
    "MAX_GAIN",
    "MODEL_FORMAT",
    "NORMALISATION",
    "OPENVINO",
    "PROVIDERS",
    "ResidualBlock",
    "TILE_HALO",
    "available_providers",
    "bilinear_kernel",
    "count_parameters",
    "default_model_path",
    "default_threads",
    "depth_to_space",
    "execution_providers",
    "exposure_gain",
    "learned_sr",
    "metadata_json",
    "models_dir",
    "onnxruntime_distributions",
    "prepare_inputs",
    "read_model_metadata",
    "reconstruct_learned",
    "run_tiled",
    "session_options",
    "space_to_depth",
    "super_resolve",
]
