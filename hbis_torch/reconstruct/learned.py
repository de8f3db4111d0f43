"""Learned multi-frame super-resolution: the network runs in onnxruntime, not torch.

(torch is used only where the rest of the package uses it: tracing the sample positions.)

The network (:mod:`hbis_torch.reconstruct.net`) sees the h^2 frames in *registered order* and, per pixel,
how far each sample sits from its nominal sub-pixel phase. :func:`prepare_inputs` builds both
from the frames and their sample positions (as given by the optics or by registration);
:class:`LearnedSR` runs an exported model on them, in tiles so that a full 960 x 1280 frame fits
in memory, and :func:`learned_sr` does the whole thing for a :class:`~hbis_torch.stack_io.Stack`.

Where the default model is found
--------------------------------
``models/hbis_sr_h{h}.onnx`` at the repository root, located relative to this file
(``<repo>/hbis_torch/sr/learned.py`` -> ``<repo>/models``), which is where it is with a source
checkout or ``pip install -e .``. The environment variable ``HBIS_MODELS_DIR`` overrides the
folder; ``model=`` (``hbis reconstruct --model``) names any other file.
"""

from __future__ import annotations

import json
import os
import warnings
from pathlib import Path

import numpy as np

from hbis_torch.errors import HbisInputError

MODEL_FORMAT = "hbis-sr-onnx/1"
NORMALISATION = (
    "frames: float32 in [0, 1] (stack.to_float), registered order; offsets: float32, output "
    "pixels, sample position minus nominal phase, (x, y) per frame; image: float32, clip to [0, 1]; "
    "dark stacks (99.9th percentile < 0.5) are scaled by up to 64x before and unscaled after"
)
# Least halo (LR pixels) around each tile: more than the network's receptive field radius (13
# for the shipped models: head + 2 per block + tail + the bilinear base), so that tiling does
# not change the result; deeper models get a wider one.
TILE_HALO = 16


def models_dir() -> Path:
    """Folder of the shipped models: ``$HBIS_MODELS_DIR`` or ``<repo>/models``."""
    env = os.environ.get("HBIS_MODELS_DIR")
    if env:
        return Path(env)
    return Path(__file__).resolve().parents[2] / "models"


def default_model_path(h: int) -> Path:
    """The shipped model for factor ``h``; HbisInputError if there is none."""
    path = models_dir() / f"hbis_sr_h{int(h)}.onnx"
    if not path.is_file():
        shipped = sorted(p.name for p in models_dir().glob("hbis_sr_h*.onnx"))
        raise HbisInputError(
            f"no learned model for h = {h} at {path} (shipped: {', '.join(shipped) or 'none'}); "
            "pass --model to use another"
        )
    return path


def _check_frames_positions(frames, positions) -> tuple[np.ndarray, np.ndarray]:
    frames = np.asarray(frames)
    positions = np.asarray(positions)
    if frames.ndim != 3:
        raise HbisInputError(f"frames must have shape (F, H, W), got {frames.shape}")
    if positions.shape != frames.shape + (2,):
        raise HbisInputError(
            f"positions must have shape (F, H, W, 2) = {frames.shape + (2,)}, got {positions.shape}"
        )
    frames = frames.astype(np.float32, copy=False)
    if not np.isfinite(frames).all():
        raise HbisInputError("frames contain NaN or infinite values")
    # (the positions are checked by their sums in prepare_inputs: one pass fewer over them)
    return frames, positions.astype(np.float64, copy=False)


def _shift_segments(shift: int, size: int) -> list[tuple[slice, slice]]:
    """(destination, source) slices of one axis moved by ``shift`` whole pixels, edges repeated.

    Destination index i takes source index ``clip(i - shift, 0, size - 1)``; a source slice of
    length 1 is broadcast over its destination slice. Empty pieces are left out.
    """
    m = min(abs(int(shift)), size)
    if shift > 0:
        pieces = [(slice(0, m), slice(0, 1)), (slice(m, size), slice(0, size - m))]
    elif shift < 0:
        pieces = [(slice(0, size - m), slice(m, size)), (slice(size - m, size), slice(size - 1, size))]
    else:
        pieces = [(slice(0, size), slice(0, size))]
    return [(dst, src) for dst, src in pieces if dst.stop > dst.start]


def prepare_inputs(frames, positions, h: int) -> tuple[np.ndarray, np.ndarray]:
    """Put the frames in registered order and compute the per-pixel residual offsets.

    Frame k's mean displacement from the reference grid, in output pixels, is rounded to an
    integer ``s_k = h * n_k + phase_k`` (``phase_k`` in 0 .. h-1 per axis). The frame goes to
    channel ``phase_y * h + phase_x`` and is moved by the whole LR pixels ``n_k`` (edge pixels
    repeated), so that its pixel (x, y) sits near output pixel (h x + phase_x, h y + phase_y)
    minus the constant ``(h - 1) / 2`` of the output grid convention. The offset channels hold
    what is left, exactly: ``h * (position - (x, y)) - phase`` for the sample that landed there.

    Parameters
    ----------
    frames : array, shape (F, H, W)
        Frames in [0, 1] (any order), F = h^2.
    positions : array, shape (F, H, W, 2)
        Sample positions in ROI-local reference-frame LR pixel coordinates (x, y).
    h : int
        Resolution improvement factor.

    Returns
    -------
    frames_reg : ndarray, shape (h^2, H, W), float32
    offsets : ndarray, shape (2 h^2, H, W), float32
        Channels (2c, 2c+1) are (x, y) of registered channel c, in output pixels.

    Raises
    ------
    HbisInputError
        Wrong shapes, non-finite values, F != h^2, or frames that do not sample each of the
        h x h sub-pixel phases once.
    """
    frames, positions = _check_frames_positions(frames, positions)
    count, rows, cols = frames.shape
    if count != h * h:
        raise HbisInputError(
            f"the stack has {count} frames but the model needs h^2 = {h * h} (h = {h})"
        )
    # mean(position - pixel) = mean(position) - centre of the frame
    centre = np.array([(cols - 1) / 2, (rows - 1) / 2])
    # (einsum: numpy's mean over two strided axes is several times slower)
    position_sum = np.einsum("fnc->fc", positions.reshape(count, -1, 2))
    if not np.isfinite(position_sum).all():  # NaN and infinities reach the sums
        if np.isfinite(positions).all():
            raise HbisInputError("sample positions are too large (their sum overflows)")
        raise HbisInputError("sample positions contain NaN or infinite values")
    mean_shift = h * (position_sum / (rows * cols) - centre)  # (F, 2), output pixels
    steps = np.rint(mean_shift).astype(np.int64)
    phases = np.mod(steps, h)
    whole = (steps - phases) // h  # (F, 2) whole LR pixels
    channel = phases[:, 1] * h + phases[:, 0]
    if len(set(channel.tolist())) != count:
        raise HbisInputError(
            "the frames do not sample each of the h x h sub-pixel phases once "
            f"(rounded shifts in output pixels: {steps.tolist()}); the scan does not fit h = {h}"
        )
    grids = (np.arange(cols, dtype=np.float64), np.arange(rows, dtype=np.float64)[:, None])
    frames_reg = np.empty((count, rows, cols), np.float32)
    offsets = np.empty((2 * count, rows, cols), np.float32)
    scratch = np.empty((rows, cols), np.float64)  # reused: no new temporaries per frame
    for k in range(count):
        c = channel[k]
        # Output-grid block (x, y) takes the frame's pixel (x - n_x, y - n_y), clamped at the
        # edges: slices (edge rows and columns broadcast), no index arrays, no copies.
        for dst_y, src_y in _shift_segments(whole[k, 1], rows):
            for dst_x, src_x in _shift_segments(whole[k, 0], cols):
                frames_reg[c, dst_y, dst_x] = frames[k, src_y, src_x]
                for axis, grid in ((0, grids[0][dst_x]), (1, grids[1][dst_y])):
                    # h * (position - pixel) - phase, in this order (as float64): the residual.
                    # Only edge-repeated pixels can be far off; bound them so no input runs away.
                    t = scratch[:dst_y.stop - dst_y.start, :dst_x.stop - dst_x.start]
                    np.subtract(positions[k, src_y, src_x, axis], grid, out=t)
                    np.multiply(t, h, out=t)
                    np.subtract(t, phases[k, axis], out=t)
                    np.clip(t, -h, h, out=offsets[2 * c + axis, dst_y, dst_x], casting="same_kind")
    return frames_reg, offsets


# Dark stacks are brightened before the network (and its output darkened by the same factor):
# the training exposures put the highlights above half scale, and a stack whose brightest
# pixels sit far below that is outside what the network has seen. Normal stacks are untouched.
DARK_TARGET = 0.5
MAX_GAIN = 64.0


def exposure_gain(frames: np.ndarray) -> float:
    """1 for stacks whose 99.9th percentile reaches DARK_TARGET, else up to MAX_GAIN to get there.

    The usual, bright stack is recognised by one count (enough values at or above the target put
    the percentile there, whatever the interpolation), which is several times cheaper than the
    percentile itself; only the others compute it. Same answer either way.
    """
    frames = np.asarray(frames)
    # If fewer than rank values lie below `sure`, the sorted value at rank - 1 and every value
    # above it are >= sure, so the percentile (interpolated between sorted values at
    # floor(0.999 (n - 1)) >= rank and the next) is too. `sure` sits a little above the target so
    # that the interpolation's rounding cannot take it below.
    sure = np.float32(DARK_TARGET * (1 + 1e-6))
    rank = int(np.floor(0.999 * (frames.size - 1))) - 1
    if rank > 0 and np.count_nonzero(frames < sure) < rank:
        return 1.0
    high = float(np.percentile(frames, 99.9))
    if high >= DARK_TARGET:
        return 1.0
    return float(min(MAX_GAIN, DARK_TARGET / max(high, DARK_TARGET / MAX_GAIN)))


def run_tiled(infer, frames_reg: np.ndarray, offsets: np.ndarray, h: int, tile: int = 256,
              halo: int = TILE_HALO) -> np.ndarray:
    """Run ``infer`` over overlapping tiles and stitch the centres.

    Parameters
    ----------
    infer : callable
        (1, h^2, h_t, w_t), (1, 2h^2, h_t, w_t) float32 arrays -> (1, 1, h h_t, h w_t).
    frames_reg, offsets : ndarray, shapes (h^2, H, W) and (2h^2, H, W)
    h, tile, halo : int
        Factor, tile side and halo in LR pixels; a halo wider than the network's receptive field
        radius makes the result independent of the tiling.

    Returns
    -------
    ndarray, shape (hH, hW), float32
    """
    _, rows, cols = frames_reg.shape
    if rows <= tile and cols <= tile:  # one tile: no halo, no stitching, no copies
        return infer(np.ascontiguousarray(frames_reg[None]), np.ascontiguousarray(offsets[None]))[0, 0]
    out = np.empty((h * rows, h * cols), np.float32)
    for y0 in range(0, rows, tile):
        for x0 in range(0, cols, tile):
            y1, x1 = min(y0 + tile, rows), min(x0 + tile, cols)
            ya, xa = max(y0 - halo, 0), max(x0 - halo, 0)
            yb, xb = min(y1 + halo, rows), min(x1 + halo, cols)
            image = infer(np.ascontiguousarray(frames_reg[None, :, ya:yb, xa:xb]),
                          np.ascontiguousarray(offsets[None, :, ya:yb, xa:xb]))[0, 0]
            out[h * y0:h * y1, h * x0:h * x1] = image[h * (y0 - ya):h * (y1 - ya), h * (x0 - xa):h * (x1 - xa)]
    return out


def session_options(threads: int | None = None):
    """onnxruntime options for the CPU: all graph optimisations, one intra-op pool.

    ``threads`` defaults to the CPUs this process may use; inter-op parallelism is off because
    the graph is a single chain of convolutions.
    """
    import onnxruntime as ort

    options = ort.SessionOptions()
    options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    options.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    options.intra_op_num_threads = default_threads(threads)
    options.inter_op_num_threads = 1
    return options


def default_threads(threads: int | None = None) -> int:
    """``threads``, or the CPUs this process may use."""
    return int(threads or len(os.sched_getaffinity(0)))


PROVIDERS = ("auto", "openvino", "cpu")
OPENVINO = "OpenVINOExecutionProvider"


def execution_providers(provider: str = "auto", threads: int | None = None) -> list:
    """The onnxruntime execution providers for ``provider``, in order of preference.

    ``"openvino"``: the OpenVINO execution provider on the CPU (package ``onnxruntime-openvino``,
    which the project installs in place of ``onnxruntime`` on x86-64 Linux and Windows). It
    compiles the whole graph with the ReLUs and residual additions fused into the convolutions
    and ran the shipped models 1.4-1.6x faster than eager torch here, where onnxruntime's own CPU
    kernels were 1.1-1.3x faster (docs/learned.md). Precision is pinned to FP32, so that a CPU
    with bf16 or fp16 units does not lower it. ``"cpu"``: onnxruntime's own kernels. ``"auto"``:
    OpenVINO where this onnxruntime has it, else the CPU kernels.
    """
    import onnxruntime as ort

    if provider not in PROVIDERS:
        raise HbisInputError(f"unknown execution provider {provider!r} (choose from {', '.join(PROVIDERS)})")
    has_openvino = "openvino" in available_providers()
    if provider == "openvino" and not has_openvino:
        raise HbisInputError(
            f"this onnxruntime ({ort.__version__}) has no OpenVINO execution provider; install "
            "onnxruntime-openvino in place of onnxruntime (x86-64 Linux or Windows), or use the 'cpu' provider"
        )
    if provider == "cpu" or not has_openvino:
        return ["CPUExecutionProvider"]
    openvino = {"device_type": "CPU", "precision": "FP32", "num_of_threads": str(default_threads(threads))}
    return [(OPENVINO, openvino), "CPUExecutionProvider"]


def available_providers() -> list[str]:
    """The :data:`PROVIDERS` this onnxruntime has, by name: ``"cpu"``, and ``"openvino"`` where
    installed."""
    import onnxruntime as ort

    return ["cpu"] + (["openvino"] if OPENVINO in ort.get_available_providers() else [])


def onnxruntime_distributions() -> list[str]:
    """The installed distributions that provide the ``onnxruntime`` module."""
    from importlib.metadata import PackageNotFoundError, version

    found = []
    for name in ("onnxruntime", "onnxruntime-openvino"):
        try:
            version(name)
            found.append(name)
        except PackageNotFoundError:
            pass
    return found


def _open_session(path: Path, provider: str, threads: int | None):
    """(session, short provider name); with ``"auto"``, falls back to the CPU kernels if
    OpenVINO cannot take the model."""
    import onnxruntime as ort

    providers = execution_providers(provider, threads)
    try:
        session = ort.InferenceSession(str(path), session_options(threads), providers=providers)
    except Exception as exc:  # onnxruntime raises its own types for corrupt files
        if provider == "auto" and len(providers) > 1:
            return _open_session(path, "cpu", threads)
        raise HbisInputError(f"cannot load ONNX model {path}: {str(exc).splitlines()[0]}") from None
    return session, "openvino" if session.get_providers()[0] == OPENVINO else "cpu"


class LearnedSR:
    """An exported SR model in an onnxruntime session.

    Parameters
    ----------
    model : path, optional
        The ``.onnx`` file; by default the shipped model for ``h``.
    h : int, optional
        Needed only when ``model`` is not given.
    threads : int, optional
        Intra-op threads (default: all CPUs available to the process).
    tile : int
        Tile size in LR pixels (the halo of :data:`TILE_HALO` pixels comes on top).
    provider : {"auto", "openvino", "cpu"}
        Which onnxruntime execution provider runs the model (:func:`execution_providers`).

    Attributes
    ----------
    h, frame_count : int
    provider : str
        ``"openvino"`` or ``"cpu"``: the execution provider that took the model.
    metadata : dict
        The model's ``metadata_props`` (h, frames, normalisation, training commit, ...).
    """

    def __init__(self, model=None, h: int | None = None, threads: int | None = None, tile: int = 256,
                 provider: str = "auto"):
        if model is None:
            if h is None:
                raise HbisInputError("give a model file or the factor h of a shipped model")
            model = default_model_path(h)
        path = Path(model)
        if not path.is_file():
            raise HbisInputError(f"model file not found: {path}")
        if len(onnxruntime_distributions()) > 1:
            warnings.warn("both onnxruntime and onnxruntime-openvino are installed; they write the same "
                          "onnxruntime module over each other. Keep one: pip uninstall -y onnxruntime "
                          "onnxruntime-openvino, then pip install onnxruntime-openvino (x86-64 Linux or "
                          "Windows) or onnxruntime", RuntimeWarning, stacklevel=2)
        self.session, self.provider = _open_session(path, provider, threads)
        self.metadata = dict(self.session.get_modelmeta().custom_metadata_map)
        if self.metadata.get("format") != MODEL_FORMAT:
            raise HbisInputError(f"{path} is not an hbis SR model (metadata format != {MODEL_FORMAT})")
        self.h = int(self.metadata["h"])
        self.frame_count = int(self.metadata["frames"])
        if h is not None and int(h) != self.h:
            raise HbisInputError(f"model {path.name} is for h = {self.h}, the stack has h = {h}")
        self.path = path
        self.tile = int(tile)
        # Receptive field radius: head + 2 per residual block + tail (+ 1), or the linear base's.
        config = json.loads(self.metadata.get("model_config", "{}"))
        radius = max(2 * int(config.get("blocks", 5)) + 3, int(config.get("skip", 0)) // 2) + 1
        self.halo = max(TILE_HALO, radius)

    def infer(self, frames_reg: np.ndarray, offsets: np.ndarray) -> np.ndarray:
        """One network pass: (1, h^2, H, W), (1, 2h^2, H, W) float32 -> (1, 1, hH, hW)."""
        return self.session.run(["image"], {"frames": frames_reg, "offsets": offsets})[0]

    def run_network(self, frames_reg: np.ndarray, offsets: np.ndarray) -> np.ndarray:
        """Raw network output for registered inputs, tiled; (h^2, H, W), (2h^2, H, W) -> (hH, hW)."""
        return run_tiled(self.infer, frames_reg, offsets, self.h, self.tile, self.halo)

    def __call__(self, frames, positions) -> np.ndarray:
        """Super-resolve frames (F, H, W) in [0, 1] with positions (F, H, W, 2) -> (hH, hW) in [0, 1]."""
        frames = np.asarray(frames)
        if frames.ndim == 3 and frames.shape[0] != self.frame_count:
            raise HbisInputError(
                f"the stack has {frames.shape[0]} frames but model {self.path.name} needs "
                f"{self.frame_count} (h = {self.h})"
            )
        if frames.ndim == 3 and min(frames.shape[1:]) < 4:
            raise HbisInputError(f"frames of {frames.shape[1]} x {frames.shape[2]} are too small (min 4 x 4)")
        return super_resolve(self.run_network, frames, positions, self.h, self.path.name)


def super_resolve(run_network, frames, positions, h: int, name: str = "the network") -> np.ndarray:
    """Frames and sample positions -> image, around any runner of the network.

    :func:`prepare_inputs`, the dark-stack gain (:func:`exposure_gain`), ``run_network``, then
    a check that the output is finite and the clip to [0, 1]. :class:`LearnedSR` passes its
    onnxruntime session; the benchmark passes eager torch, so that both pay for the same glue.

    Parameters
    ----------
    run_network : callable
        (h^2, H, W), (2h^2, H, W) float32 -> (hH, hW) float32, the raw network output, a new
        array (it is clipped in place).
    frames : array, shape (F, H, W)
    positions : array, shape (F, H, W, 2)
    h : int
    name : str
        How the error message names the model.

    Returns
    -------
    ndarray, shape (hH, hW), float32 in [0, 1]
    """
    frames_reg, offsets = prepare_inputs(frames, positions, h)
    gain = exposure_gain(frames_reg)
    if gain == 1.0:  # the usual case: no copies
        image = run_network(frames_reg, offsets)
    else:
        image = run_network(frames_reg * np.float32(gain), offsets) / np.float32(gain)
    # A model is a function of float32 inputs in [0, 1]; anything non-finite here is a bug
    # in the model file, not in the stack.
    if not np.isfinite(image).all():
        raise HbisInputError(f"model {name} produced non-finite values")
    return np.clip(image, 0.0, 1.0, out=image)  # the image is ours: clip in place


def stack_positions(stack, registration: str = "optics", messages: list | None = None):
    """Sample positions (F, H, W, 2) float64 of a stack, as the classical method finds them.

    ``"optics"``: the tracer, through :func:`hbis_torch.simulate.sample_positions` (exact at
    nodes 8 pixels apart, cubic splines between: < 1e-6 pixel from
    :func:`~hbis_torch.reconstruct.classical.optical_sample_positions`, and much faster).
    ``"data"`` / ``"auto"``: the tracer corrected by registering the frames
    (:func:`~hbis_torch.registration.register_stack`), for the frames the registration trusts;
    the network needs every frame, so untrusted frames keep their optical positions.
    """
    import torch

    from hbis_torch.registration import apply_homography, homographies_from_positions, register_stack
    from hbis_torch.simulate import sample_positions
    from hbis_torch.reconstruct.classical import REGISTRATIONS

    if registration not in REGISTRATIONS:
        raise HbisInputError(f"registration must be one of {REGISTRATIONS}, got {registration!r}")
    positions = sample_positions(stack.system, stack.phases_deg, stack.reference_index, stack.roi)
    count, rows, cols = positions.shape[:3]
    if registration == "optics" or count == 1:
        return positions.numpy()
    frames = stack.to_float()
    predicted = homographies_from_positions(positions)
    reg = register_stack(frames, stack.reference_index, prediction=predicted)
    if messages is not None:
        messages.extend(reg.messages)
        if not bool(reg.ok.all()):
            messages.append(f"kept the optical positions of {int((~reg.ok).sum())} frame(s) the "
                            "registration could not trust")
    correction = reg.homographies @ torch.linalg.inv(predicted)
    corrected = apply_homography(correction, positions.reshape(count, -1, 2)).reshape(positions.shape)
    return torch.where(reg.ok[:, None, None, None], corrected, positions).numpy()


def learned_sr(stack, model=None, positions=None, threads: int | None = None,
               registration: str = "optics", messages: list | None = None,
               provider: str = "auto") -> np.ndarray:
    """Super-resolve a captured or simulated stack with an ONNX model (onnxruntime, no torch).

    Parameters
    ----------
    stack : hbis_torch.stack_io.Stack
    model : path, optional
        Defaults to the shipped model for the stack's h (:func:`default_model_path`).
    positions : array (F, H, W, 2), optional
        Sample positions in ROI-local reference LR pixels; by default :func:`stack_positions`.
    threads : int, optional
        onnxruntime intra-op threads.
    registration : {"optics", "data", "auto"}
        Where the positions come from when they are not given.
    messages : list, optional
        Receives the registration's warnings.
    provider : {"auto", "openvino", "cpu"}
        onnxruntime execution provider (:func:`execution_providers`).

    Returns
    -------
    ndarray, shape (h H, h W), float32 in [0, 1]
    """
    runner = LearnedSR(model=model, h=None if model is not None else stack.h, threads=threads,
                       provider=provider)
    if runner.h != stack.h:
        raise HbisInputError(f"model {runner.path.name} is for h = {runner.h}, the stack has h = {stack.h}")
    if positions is None:
        positions = stack_positions(stack, registration, messages)
    positions = np.asarray(positions.detach().cpu() if hasattr(positions, "detach") else positions)
    frames = stack.to_float()
    frames = np.asarray(frames.detach().cpu() if hasattr(frames, "detach") else frames)
    return runner(frames, positions)


def reconstruct_learned(stack, registration: str = "auto", *, model=None, messages: list | None = None,
                        threads: int | None = None, provider: str = "auto") -> np.ndarray:
    """The ``"learned"`` entry of :data:`hbis_torch.reconstruct.classical.METHODS` (``hbis reconstruct``)."""
    return learned_sr(stack, model=model, threads=threads, registration=registration, messages=messages,
                      provider=provider)


def _register_method() -> None:
    from hbis_torch.reconstruct.classical import METHODS

    METHODS.setdefault("learned", reconstruct_learned)


_register_method()


def read_model_metadata(path) -> dict:
    """The ``metadata_props`` of an ONNX file as a dict (no session is created)."""
    import onnx

    model = onnx.load(str(path), load_external_data=False)
    return {p.key: p.value for p in model.metadata_props}


def metadata_json(path) -> str:
    """The model's metadata as indented JSON (for ``python -m`` style inspection)."""
    return json.dumps(read_model_metadata(path), indent=2)
