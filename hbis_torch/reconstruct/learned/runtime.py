"""The learned method's runtime: exported models in onnxruntime, or in OpenVINO where installed.

Where the models are (:func:`models_dir`, :func:`default_model_path`; ``HBIS_MODELS_DIR``
overrides the package's own ``hbis_torch/models``), which execution provider runs them (:func:`execution_providers`),
the session (:class:`LearnedSR`) and the models' metadata (:func:`read_model_metadata`).
onnxruntime and openvino are imported only inside the functions that need them (the onnx package
not at all).
"""

from __future__ import annotations

import functools
import json
import os
import threading
import warnings
from pathlib import Path

import numpy as np

from hbis_torch.errors import HbisInputError
from hbis_torch.notices import act
from hbis_torch.reconstruct.learned.architecture import Architecture
from hbis_torch.reconstruct.learned.domain import domain_from_metadata, outside_domain, unhelpful_model
from hbis_torch.reconstruct.learned.inputs import check_ensemble, run_tiled, super_resolve, tile_ensemble

MODEL_FORMAT = "hbis-sr-onnx/2"
NORMALISATION = (
    "base: float32, the classical image (reconstruct_classical, in [0, 1]) space-to-depth by h, "
    "channel dy*h+dx = image[h*y+dy, h*x+dx]; noise: float32, 10 * sqrt(a*level + b), the frames' "
    "noise level at each LR pixel's mean level (variance a*x + b of a frame value x in [0, 1]); "
    "image: float32, clip to [0, 1]"
)


def models_dir() -> Path:
    """Folder of the shipped models: ``$HBIS_MODELS_DIR``, or the package data ``hbis_torch/models``.

    The models are package data, so a wheel, an sdist and a checkout find them the same way.
    """
    env = os.environ.get("HBIS_MODELS_DIR")
    if env:
        return Path(env)
    from importlib.resources import files

    return Path(str(files("hbis_torch") / "models"))


# The shipped models come in two tiers (docs/learned.md, "Two tiers"): "fast", the default, and
# "best", a larger network for users who trade time for held-out quality.
TIERS = {"fast": "hbis_sr_h{h}.onnx", "best": "hbis_sr_h{h}_best.onnx"}


def tier_of(model) -> str | None:
    """The tier a ``model`` argument names: None -> "fast"; "fast" or "best" -> itself; a file -> None."""
    if model is None:
        return "fast"
    return str(model) if isinstance(model, (str, Path)) and str(model) in TIERS else None


def shipped_model_path(h: int, tier: str = "fast") -> Path:
    """Where the shipped model of factor ``h`` and ``tier`` (:data:`TIERS`) is, whether or not it exists."""
    return models_dir() / TIERS[tier].format(h=int(h))


def default_model_path(h: int, tier: str = "fast") -> Path:
    """The shipped model for factor ``h`` of ``tier`` ("fast" or "best"); HbisInputError if there is none."""
    missing = missing_model(h, tier)
    if missing is not None:
        raise HbisInputError(f"{missing}; pass --model to use another")
    return shipped_model_path(h, tier)


# What the line says where no model is shipped for a stack's h and the learned method returns the
# classical image
NO_MODEL_REMEDY = "--model runs a model of your own"


def model_to_run(model, h: int, precision: str | None = None,
                 provider: str = "auto") -> tuple[Path | None, dict | None, str | None]:
    """:func:`check_model`'s (path, metadata, None), the file at ``precision``
    (:func:`with_precision`) for ``provider`` (:func:`check_precision`); or (None, None, the line
    saying so) where no model is named (or a tier is) and none is shipped for ``h`` (the learned
    method then returns the classical image)."""
    check_precision(precision, provider)
    tier = tier_of(model)
    missing = missing_model(h, tier) if tier is not None else None
    if missing is not None:
        return None, None, missing
    return (*with_precision(*check_model(model, h), precision), None)


def available_tier(model, h: int, messages: list | None = None):
    """``model`` as given, or ``"fast"`` where it names the best tier and only a fast model is
    shipped for ``h`` (h = 3): the user asked for the most quality there is, and the fast network
    gives more than the classical image. The switch is said in ``messages``."""
    if tier_of(model) == "best" and missing_model(h, "best") is not None and missing_model(h, "fast") is None:
        if messages is not None:
            messages.append(f"no best model for h = {h}: the fast model runs")
        return "fast"
    return model


def missing_model(h: int, tier: str = "fast") -> str | None:
    """None if a model for factor ``h`` of ``tier`` is shipped, else the line that says there is none."""
    path = shipped_model_path(h, tier)
    if path.is_file():
        return None
    shipped = sorted(p.name for p in models_dir().glob("hbis_sr_h*.onnx") if not p.name.endswith(".int8.onnx"))
    which = "" if tier == "fast" else f"{tier} "  # the fast tier's line as before the tiers
    return f"no {which}learned model for h = {h} at {path} (shipped: {', '.join(shipped) or 'none'})"


PRECISIONS = ("int8", "bf16", "fp32")
# What runs without --precision: None, the file named (the shipped float32 ones). The lower
# precisions are faster but lose more than 0.05 dB in some held-out cells, the cleanest ones
# (export/check_int8.py, docs/learned.md, section int8), so neither is the default:
# - int8, the NAME.int8.onnx files: the network 1.2-1.4 times as fast on AVX2 cores, 2 times on
#   cores with AVX-512 VNNI (3 in OpenVINO); up to 0.75 / 3.68 / 0.85 / 1.22 dB lost at h = 2 /
#   3 / 4 / 7 (fast tier);
# - bf16, the float32 file run by OpenVINO in bfloat16 on cores with bf16 units (AMX or AVX-512
#   BF16): 4.13 times as fast with AMX (benchmarks/results/bench_fast.md); up to 0.33 dB lost,
#   in the cells above 50 dB (benchmarks/results/check_bf16*.md).
DEFAULT_PRECISION = None


def check_precision(precision: str | None, provider: str = "auto") -> None:
    """HbisInputError, before any work, for an unknown ``precision`` or one that ``provider``
    cannot run: bf16 runs only in OpenVINO (the ``openvino`` package), onnxruntime's CPU kernels
    have no bf16 convolutions."""
    if precision not in (None, *PRECISIONS):
        raise HbisInputError(f"unknown precision {precision!r} (choose from {', '.join(PRECISIONS)})")
    if precision != "bf16":
        return
    if provider == "cpu":
        raise HbisInputError("--precision bf16 runs in OpenVINO, and --provider cpu (onnxruntime's kernels) has "
                             "no bf16: use --provider auto or openvino")
    if not openvino_installed():
        raise HbisInputError("--precision bf16 runs in OpenVINO, which is not installed: "
                             "pip install 'hbis-torch[openvino]'")


def int8_path(model) -> Path:
    """Where the int8 file of a float32 model lives: ``NAME.int8.onnx`` beside ``NAME.onnx``
    (``export/quantize_int8.py`` writes it, :mod:`hbis_torch.training.quantize`)."""
    model = Path(model)
    return model.with_name(model.name.removesuffix(".onnx") + ".int8.onnx")


def with_precision(path: Path, metadata: dict, precision: str | None = None) -> tuple[Path, dict]:
    """The model file to run at ``precision``, and its metadata.

    Parameters
    ----------
    path : Path
        A checked model file (:func:`check_model`), float32 or int8.
    metadata : dict
        Its metadata.
    precision : {"int8", "bf16", "fp32"} or None
        None (the default): the file itself (:data:`DEFAULT_PRECISION`). ``"int8"``: the int8
        file beside a float32 model (:func:`int8_path`), which must exist. ``"fp32"`` and
        ``"bf16"`` (which OpenVINO runs in bfloat16): the float32 file.

    Raises
    ------
    HbisInputError
        An unknown precision, ``"int8"`` where there is no int8 file, ``"fp32"`` or ``"bf16"``
        for an int8 file.
    """
    if precision not in (None, *PRECISIONS):
        raise HbisInputError(f"unknown precision {precision!r} (choose from {', '.join(PRECISIONS)})")
    own = metadata.get("precision", "fp32")
    precision = precision or DEFAULT_PRECISION or own
    if precision == own:
        return path, metadata
    if own != "fp32":
        raise HbisInputError(f"{path.name} is an {own} model; --precision {precision} needs its float32 file")
    if precision == "bf16":
        return path, metadata
    int8 = int8_path(path)
    if not int8.is_file():
        raise HbisInputError(f"no int8 file for {path.name} ({int8} is missing; python export/quantize_int8.py "
                             f"{path} makes it), or use --precision fp32")
    return check_model(int8, int(metadata["h"]))


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
# What "auto" runs a model on: onnxruntime's own kernels. In fp32 OpenVINO ran the shipped h = 4
# model no faster (0.420 s against 0.415 s on a 480 x 640 input, benchmarks/bench_fast.py) and
# compiles the graph first, 1 to 6 s a process, so that a 32^2 reconstruct started in 1.49 times
# an `import torch` through it and 1.26 times through onnxruntime. The int8 files ran faster in
# OpenVINO in that run (0.239 s against onnxruntime's 0.341 s), by less than its compile takes
# on one stack. "openvino" still takes OpenVINO, for either file.
AUTO_PROVIDER = "cpu"
OPENVINO = "OpenVINOExecutionProvider"


def openvino_installed() -> bool:
    """Whether the ``openvino`` package (the optional extra ``hbis-torch[openvino]``) is installed."""
    from importlib.util import find_spec

    return find_spec("openvino") is not None


def execution_providers(provider: str = "auto", threads: int | None = None) -> list:
    """The onnxruntime execution providers for ``provider``, in order of preference.

    The project depends on plain ``onnxruntime``, so that it installs beside any other package
    that needs it. ``"openvino"`` runs the model in OpenVINO on the CPU: through the ``openvino``
    package's own ONNX reader where that package is installed (``pip install hbis-torch[openvino]``;
    it does not touch the ``onnxruntime`` module, :class:`_OpenVINOSession`), else through
    onnxruntime's OpenVINO execution provider where the installed onnxruntime is Intel's
    ``onnxruntime-openvino`` build (what this function returns then). OpenVINO compiles the whole
    graph with the ReLUs and residual additions fused into the convolutions; against
    onnxruntime's own CPU kernels it ran the h = 4 model at about the same speed here
    (``benchmarks/bench_providers.py``, benchmarks/results/bench_providers.txt). Precision is
    pinned to FP32, so that a CPU with bf16 or fp16 units does not lower it. ``"cpu"``:
    onnxruntime's own kernels. ``"auto"``: OpenVINO where installed, else the CPU kernels (what a
    caller gets here; :class:`LearnedSR` turns ``"auto"`` into :data:`AUTO_PROVIDER` first).
    """
    import onnxruntime as ort

    if provider not in PROVIDERS:
        raise HbisInputError(f"unknown execution provider {provider!r} (choose from {', '.join(PROVIDERS)})")
    has_openvino = OPENVINO in ort.get_available_providers()
    if provider == "openvino" and not has_openvino:
        raise HbisInputError(
            "OpenVINO is not installed: pip install 'hbis-torch[openvino]' (or the openvino package), "
            "or use the 'cpu' provider"
        )
    if provider == "cpu" or not has_openvino:
        return ["CPUExecutionProvider"]
    openvino = {"device_type": "CPU", "precision": "FP32", "num_of_threads": str(default_threads(threads))}
    return [(OPENVINO, openvino), "CPUExecutionProvider"]


def available_providers() -> list[str]:
    """The :data:`PROVIDERS` installed here, by name: ``"cpu"``, and ``"openvino"`` where the
    ``openvino`` package or onnxruntime's OpenVINO execution provider is installed."""
    import onnxruntime as ort

    has_openvino = openvino_installed() or OPENVINO in ort.get_available_providers()
    return ["cpu"] + (["openvino"] if has_openvino else [])


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


class _OpenVINOSession:
    """An ONNX model compiled by the ``openvino`` package for the CPU, with the part of
    onnxruntime's ``InferenceSession`` interface that :class:`LearnedSR` uses (``run``).

    The ONNX file is read by OpenVINO's own reader; height and width stay dynamic, so a new input
    size does not recompile. FP32 inference precision (``bf16``: bfloat16 where the CPU has bf16
    units, :attr:`bf16` says whether it does), ``threads`` inference threads, the latency hint
    (one request at a time). An infer request is not thread-safe: each thread that runs the model
    (``hbis reconstruct --out-dir --jobs N``) gets its own.
    """

    def __init__(self, path: Path, threads: int | None, bf16: bool = False):
        import openvino as ov

        core = ov.Core()
        # Without bf16 units OpenVINO would emulate bfloat16 or refuse it: float32 is as fast there.
        self.bf16 = bf16 and cpu_has_bf16(core)
        config = {"INFERENCE_PRECISION_HINT": "bf16" if self.bf16 else "f32",
                  "INFERENCE_NUM_THREADS": default_threads(threads), "PERFORMANCE_HINT": "LATENCY"}
        self.compiled = core.compile_model(str(path), "CPU", config)
        self._local = threading.local()

    def run(self, names, feeds: dict) -> list:
        request = getattr(self._local, "request", None)
        if request is None:
            request = self._local.request = self.compiled.create_infer_request()
        results = request.infer(feeds)
        return [np.asarray(results[self.compiled.output(name)]) for name in names]


def cpu_has_bf16(core) -> bool:
    """Whether OpenVINO (an ``openvino.Core``) finds bf16 units on this CPU (AMX or AVX-512 BF16)."""
    return "BF16" in core.get_property("CPU", "OPTIMIZATION_CAPABILITIES")


def bf16_available() -> bool:
    """Whether ``--precision bf16`` runs in bfloat16 here: the ``openvino`` package is installed
    and finds bf16 units on this CPU (else it is refused, or runs in float32)."""
    if not openvino_installed():
        return False
    import openvino as ov

    return cpu_has_bf16(ov.Core())


def _open_session(path: Path, provider: str, threads: int | None, bf16: bool = False):
    """(session, short provider name); with ``"auto"``, falls back to the CPU kernels if
    OpenVINO cannot take the model (``bf16`` asks OpenVINO for bfloat16, :class:`_OpenVINOSession`)."""
    import onnxruntime as ort

    if provider in ("auto", "openvino") and openvino_installed():
        try:
            return _OpenVINOSession(path, threads, bf16), "openvino"
        except Exception as exc:  # OpenVINO raises its own types for models it cannot compile
            if provider == "openvino":
                raise HbisInputError(f"OpenVINO cannot load ONNX model {path}: {str(exc).splitlines()[0]}") from None
            return _open_session(path, "cpu", threads)
    providers = execution_providers(provider, threads)
    try:
        session = ort.InferenceSession(str(path), session_options(threads), providers=providers)
    except Exception as exc:  # onnxruntime raises its own types for corrupt files
        if provider == "auto" and len(providers) > 1:
            return _open_session(path, "cpu", threads)
        raise HbisInputError(f"cannot load ONNX model {path}: {str(exc).splitlines()[0]}") from None
    return session, "openvino" if session.get_providers()[0] == OPENVINO else "cpu"


def check_model(model=None, h: int | None = None) -> tuple[Path, dict]:
    """A model file and its metadata, checked without starting a session (cheap: callers check
    before the classical step and open the session after it).

    Parameters
    ----------
    model : path or {"fast", "best"}, optional
        The ``.onnx`` file, or the shipped model of that tier for ``h`` (:data:`TIERS`); by
        default the shipped fast model for ``h``.
    h : int, optional
        The stack's factor: the model must be for it.

    Returns
    -------
    path : Path
    metadata : dict
        Its ``metadata_props``.

    Raises
    ------
    HbisInputError
        No such file, not an ONNX file, not an hbis SR model, or a model for another h.
    """
    tier = tier_of(model)
    if tier is not None:
        if h is None:
            raise HbisInputError("give a model file or the factor h of a shipped model")
        model = default_model_path(h, tier)
    path = Path(model)
    if not path.is_file():
        raise HbisInputError(f"model file not found: {path}")
    try:
        metadata = read_model_metadata(path)
    except Exception as exc:  # onnxruntime raises its own types for corrupt files
        reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise HbisInputError(f"cannot load ONNX model {path}: {reason}") from None
    if metadata.get("format") != MODEL_FORMAT:
        raise HbisInputError(f"{path} is not an hbis SR model (metadata format != {MODEL_FORMAT})")
    if h is not None and int(h) != int(metadata["h"]):
        raise HbisInputError(f"model {path.name} is for h = {metadata['h']}, the stack has h = {h}")
    return path, metadata


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
        Tile size in LR pixels (the halo, :attr:`halo` pixels, comes on top).
    provider : {"auto", "openvino", "cpu"}
        What runs the model: OpenVINO or onnxruntime's CPU kernels (:func:`execution_providers`).
        ``"auto"`` (the default) runs onnxruntime's CPU kernels (:data:`AUTO_PROVIDER` says why).
    precision : {"int8", "bf16", "fp32"} or None
        Which file of the model runs, and how (:func:`with_precision`; None: the one named;
        ``"bf16"``: the float32 file in OpenVINO in bfloat16, :func:`check_precision`).

    Attributes
    ----------
    h : int
    tier : {"fast", "best"} or None
        The shipped tier ``model`` named (None: a file); sets the default self-ensemble.
    provider : str
        ``"openvino"`` or ``"cpu"``: what took the model.
    precision : str
        ``"int8"``, ``"bf16"`` or ``"fp32"``: what runs (``"fp32"`` where bf16 was asked of a CPU
        without bf16 units; :attr:`note` then says so).
    note : str or None
        The line :meth:`__call__` adds to its messages: bf16 asked of a CPU without it.
    metadata : dict
        The model's ``metadata_props`` (h, frames, normalisation, training commit, ...).
    architecture : Architecture
        The network's, from ``metadata`` (:mod:`~hbis_torch.reconstruct.learned.architecture`).
    halo : int
        Context each tile gets on every side, LR pixels: the network's receptive field radius
        plus one (:attr:`Architecture.halo`), so that the tiles give the whole image's output.
    """

    def __init__(self, model=None, h: int | None = None, threads: int | None = None, tile: int = 256,
                 provider: str = "auto", precision: str | None = None):
        check_precision(precision, provider)
        path, self.metadata = with_precision(*check_model(model, h), precision)
        self.tier = tier_of(model)
        self.precision = self.metadata.get("precision", "fp32")
        bf16 = precision == "bf16"
        if bf16:
            provider = "openvino"
        elif provider == "auto":
            provider = AUTO_PROVIDER
        if len(onnxruntime_distributions()) > 1:
            warnings.warn("both onnxruntime and onnxruntime-openvino are installed; they write the same "
                          "onnxruntime module over each other. Keep one: pip uninstall -y onnxruntime "
                          "onnxruntime-openvino, then pip install onnxruntime (and, for OpenVINO, "
                          "pip install 'hbis-torch[openvino]')", RuntimeWarning, stacklevel=2)
        self.session, self.provider = _open_session(path, provider, threads, bf16)
        self.note = None
        if bf16 and self.session.bf16:
            self.precision = "bf16"
        elif bf16:
            self.note = "this CPU has no bf16 units (AMX or AVX-512 BF16): the network ran in float32"
        self.h = int(self.metadata["h"])
        self.path = path
        self.domain = domain_from_metadata(self.metadata)
        self.unhelpful = unhelpful_model(self.metadata)
        self.tile = int(tile)
        self.architecture = Architecture.from_metadata(self.metadata)
        self.halo = self.architecture.halo

    def infer(self, base: np.ndarray, noise: np.ndarray) -> np.ndarray:
        """One network pass: (1, h^2, H, W), (1, 1, H, W) float32 -> (1, 1, hH, hW)."""
        return self.session.run(["image"], {"base": base, "noise": noise})[0]

    def run_network(self, base: np.ndarray, noise: np.ndarray, ensemble: int = 1) -> np.ndarray:
        """Raw network output, tiled; base (h^2, H, W) or (h, h, H, W), noise (1, H, W) -> (hH, hW).

        ``ensemble`` (1, 2, 4 or 8) averages each tile over as many symmetries
        (:func:`~hbis_torch.reconstruct.learned.inputs.tile_ensemble`). A progress bar counts
        the tiles (:mod:`hbis_torch.progress`)."""
        from hbis_torch.progress import progress

        rows, cols = base.shape[-2:]
        tiles = 1 if rows <= self.tile and cols <= self.tile else -(-rows // self.tile) * -(-cols // self.tile)
        with progress(total=tiles, desc=f"learned SR ({self.provider})", unit="tile") as bar:
            average = tile_ensemble(self.infer, self.h, ensemble)

            def infer(b, n):
                image = average(b, n)
                bar.update()
                return image

            return run_tiled(infer, base, noise, self.h, self.tile, self.halo)

    def __call__(self, image, noise_params: tuple[float, float], cutoff: float | None = None, *,
                 messages: list | None = None, extrapolate: bool = False, ensemble: int | None = None) -> np.ndarray:
        """Refine a classical image (hH, hW) in [0, 1] of frames of noise variance ``a x + b``.

        A stack outside the model's training domain, or any stack for a model that did not beat
        the classical image on its validation set (:mod:`hbis_torch.reconstruct.learned.domain`),
        gets the classical image back, and ``messages`` a line saying why, unless
        ``extrapolate``.

        Parameters
        ----------
        image : array, shape (hH, hW)
            The classical reconstruction (:func:`hbis_torch.reconstruct.classical.reconstruct_classical`).
        noise_params : (float, float)
            (a, b) (:func:`noise_params_from_meta`, :func:`estimate_noise_params`).
        cutoff : float, optional
            The lens's diffraction cutoff in cycles per LR pixel
            (:func:`hbis_torch.reconstruct.classical.optics_cutoff`); the correction is limited
            to it (:func:`~hbis_torch.reconstruct.learned.inputs.band_limit`).
        messages : list, optional
            Receives the line saying why the classical image is returned.
        extrapolate : bool
            Run the network anyway.
        ensemble : {1, 2, 4, 8} or None
            Average the network over this many of the square's symmetries, at as many times its
            cost (:func:`~hbis_torch.reconstruct.learned.inputs.self_ensemble`); None: the
            default of :attr:`tier` (:func:`~hbis_torch.reconstruct.learned.inputs.default_ensemble`).

        Returns
        -------
        ndarray, shape (hH, hW), float32 in [0, 1]
        """
        ensemble = check_ensemble(ensemble, self.h, self.tier)
        reason = self.unhelpful or outside_domain(self.domain, noise_params, cutoff)
        if reason is not None and not extrapolate:
            return classical_returned(image, reason, messages)
        if self.note is not None and messages is not None:
            messages.append(self.note)
        return super_resolve(lambda base, noise: self.run_network(base, noise, ensemble), image, self.h,
                             noise_params, self.path.name, cutoff, views=True)


def classical_returned(image, reason: str, messages: list | None = None,
                       remedy: str = "--extrapolate runs the network anyway") -> np.ndarray:
    """The classical image (hH, hW), float32 in [0, 1], where the network is not run, and the line
    saying ``reason`` (and ``remedy``) appended to ``messages``. A float32 image already in
    [0, 1] is returned as it is, not copied (a full frame's is 240 MB at h = 7)."""
    if messages is not None:
        messages.append(act(f"{reason}: the learned method returns the classical image ({remedy})"))
    image = np.asarray(image, dtype=np.float32)
    return image if image.size == 0 or (image.min() >= 0 and image.max() <= 1) else np.clip(image, 0.0, 1.0)


def read_model_metadata(path) -> dict:
    """The ``metadata_props`` of an ONNX file as a dict, read by onnxruntime (a session of the CPU
    kernels, graph optimisations off: about 50 ms for the best h = 4 model on loaded cores, where
    importing the onnx package took 0.5 s of a command's start-up on the same cores). A file is
    read once while it is unchanged: the checks before the classical step and the session after
    it ask for the same file."""
    path = Path(path).resolve()
    stat = path.stat()
    return dict(_metadata_items(str(path), stat.st_mtime_ns, stat.st_size))


@functools.lru_cache(maxsize=16)
def _metadata_items(path: str, mtime_ns: int, size: int) -> tuple:
    import onnxruntime as ort

    options = ort.SessionOptions()
    options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_DISABLE_ALL
    options.log_severity_level = 3  # errors only: a corrupt file is reported by the exception
    session = ort.InferenceSession(path, options, providers=["CPUExecutionProvider"])
    return tuple(session.get_modelmeta().custom_metadata_map.items())


def metadata_json(path) -> str:
    """The model's metadata as indented JSON (for ``python -m`` style inspection)."""
    return json.dumps(read_model_metadata(path), indent=2)
