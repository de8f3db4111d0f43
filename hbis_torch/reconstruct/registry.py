"""Every reconstruction method by name, and :func:`reconstruct`, which dispatches to them.

A method is one module plus one entry here: a :class:`Method` that names its run function, the
options it takes (``hbis reconstruct`` builds its flags and ``--help`` from them) and, if it has
one, its own path for raw Bayer frames. :func:`register` adds an entry; the two built-in methods
are registered below. Colour stacks go through :mod:`hbis_torch.reconstruct.colour`, which is
handed the :class:`Method`: no method module imports this one.

Run functions are named as ``"module:function"`` and imported when a stack is reconstructed, so
importing the registry (as ``hbis reconstruct --help`` does) imports neither torch nor
onnxruntime.

Examples
--------
>>> from hbis_torch.reconstruct.registry import METHODS
>>> sorted(METHODS)
['classical', 'learned']
>>> [option.flag for option in METHODS["classical"].options]
['--no-deblur', '--psf-sigma']
"""

from __future__ import annotations

import dataclasses
import importlib
from typing import TYPE_CHECKING, Any, Callable

from hbis_torch.checks import auto_or, bounded_float
from hbis_torch.errors import HbisInputError

if TYPE_CHECKING:
    import numpy as np


@dataclasses.dataclass(frozen=True)
class Option:
    """One option of a method: a keyword of its run function and a ``hbis reconstruct`` flag.

    Parameters
    ----------
    flag : str
        The command-line flag, e.g. ``"--no-deblur"``.
    keyword : str
        The run function's keyword the flag sets, e.g. ``"deblur"``.
    help : str
        One sentence for ``--help``.
    argparse : dict
        What ``ArgumentParser.add_argument`` takes besides the flag, the destination, the help
        and the default (``action``, ``type``, ``choices``, ``metavar``).
    """

    flag: str
    keyword: str
    help: str
    argparse: dict = dataclasses.field(default_factory=dict)


@dataclasses.dataclass(frozen=True)
class Method:
    """A reconstruction method: what :func:`reconstruct` and ``hbis reconstruct`` need of it.

    Parameters
    ----------
    name : str
        The ``--method`` name.
    run : callable or str
        ``run(stack, registration=..., messages=None, **options)`` -> ndarray (h H, h W), float32
        in [0, 1], for a grey stack; or ``"module:function"`` naming it (imported on first use).
    summary : str
        One line for ``hbis reconstruct --help``.
    options : tuple of Option
        The method's own options; any other is refused.
    raw_bayer : callable or str, optional
        ``raw_bayer(stack, registration=..., messages=None, **options)`` -> ndarray
        (h H, h W, 3): the method's own path for raw Bayer frames (joint demosaicking). Without
        one, raw frames are demosaicked first and go through ``run`` as RGB.
    threads : bool
        ``run`` takes ``threads`` (``hbis reconstruct --threads``, which also sets torch's).
    burst : callable or str, optional
        ``burst(stack, frames, positions, weights, messages=None, **options)`` -> ndarray
        (S H, S W): the method on a burst stack's grey (or one colour's) frames (F, H, W), given
        each sample's position (F, H, W, 2) and robustness weight (F, H, W)
        (:mod:`hbis_torch.reconstruct.burst` works them out). Without one, a burst goes through
        ``run`` as any stack does (its positions from
        :func:`~hbis_torch.reconstruct.positions.stack_sample_positions`, without robustness).
    """

    name: str
    run: Callable[..., np.ndarray] | str
    summary: str
    options: tuple[Option, ...] = ()
    raw_bayer: Callable[..., np.ndarray] | str | None = None
    threads: bool = False
    burst: Callable[..., np.ndarray] | str | None = None

    @property
    def keywords(self) -> frozenset[str]:
        """The keywords of :attr:`options`."""
        return frozenset(option.keyword for option in self.options)

    def run_function(self) -> Callable[..., np.ndarray]:
        """:attr:`run`, imported if named as ``"module:function"``."""
        return _resolve(self.run)

    def raw_bayer_function(self) -> Callable[..., np.ndarray] | None:
        """:attr:`raw_bayer`, imported if named as ``"module:function"``; None without one."""
        return None if self.raw_bayer is None else _resolve(self.raw_bayer)

    def burst_function(self) -> Callable[..., np.ndarray] | None:
        """:attr:`burst`, imported if named as ``"module:function"``; None without one."""
        return None if self.burst is None else _resolve(self.burst)


def _resolve(target: Callable[..., Any] | str) -> Callable[..., Any]:
    if callable(target):
        return target
    module, _, name = target.partition(":")
    return getattr(importlib.import_module(module), name)


#: Reconstruction methods by name (:func:`register` adds one).
METHODS: dict[str, Method] = {}


def register(method: Method) -> Method:
    """Add ``method`` to :data:`METHODS` (a name taken already is refused) and return it.

    A flag that another method declares too must mean the same there (keyword and argparse
    settings), since ``hbis reconstruct`` has one flag for both.
    """
    if method.name in METHODS:
        raise HbisInputError(f"a reconstruction method named {method.name!r} is registered already")
    for option in method.options:
        for other in METHODS.values():
            for theirs in other.options:
                if theirs.flag == option.flag and (theirs.keyword, theirs.argparse) != (option.keyword, option.argparse):
                    raise HbisInputError(f"{option.flag} of method {method.name!r} differs from {other.name!r}'s")
    METHODS[method.name] = method
    return method


def get_method(name: str) -> Method:
    """The registered method called ``name``, or one :class:`HbisInputError` line naming those there are."""
    if name not in METHODS:
        raise HbisInputError(f"unknown reconstruction method {name!r}; available: {', '.join(METHODS)}")
    return METHODS[name]


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
        learned: ``model``, ``messages``, ``threads``, ``provider``, ``extrapolate``,
        ``ensemble``, ``precision``). A colour stack (RGB frames or raw Bayer with a ``cfa`` key) goes through
        :func:`hbis_torch.reconstruct.colour.reconstruct_colour`, which also takes ``colour``
        ("luma" or "channels"); ``colour`` on a grey stack is refused. A burst stack
        (``stack.kind == "burst"``) goes through
        :func:`hbis_torch.reconstruct.burst.reconstruct_burst` and the method's ``burst`` path.

    Returns
    -------
    np.ndarray, shape (h*H, h*W) (or (h*H, h*W, 3) for a colour stack), float32 in [0, 1]
    """
    entry = get_method(method)
    if getattr(stack, "kind", "hbis") == "burst" and isinstance(stack.meta.get("raw"), dict):  # raw Bayer burst
        # named, not imported: the classical package imports this one
        joint = _resolve("hbis_torch.reconstruct.classical.raw_burst:reconstruct_raw_burst")
        return joint(stack, entry, registration=registration, **kw)
    if getattr(stack, "kind", "hbis") == "burst" and entry.burst is not None:  # measured motion, robustness
        from hbis_torch.reconstruct.burst import reconstruct_burst

        return reconstruct_burst(stack, entry, registration=registration, **kw)
    if kw.pop("keep_blurred", False):
        raise HbisInputError("--keep-blurred is for burst stacks (hbis assemble --burst): a scan's frames are all used")
    if registration == "data" and len(stack.frames) > 1:
        ref = stack.frames[stack.reference_index]
        if ref.min() == ref.max():  # nothing to register to: every other frame would be left out
            raise HbisInputError(f"the reference frame {stack.reference_index} is uniform (every pixel "
                                 f"{ref.flat[0]}), so no frame can be registered to it: use --registration "
                                 "optics or auto")
    if getattr(stack, "colour", False):  # RGB or raw Bayer frames: every method, through one wrapper
        from hbis_torch.reconstruct.colour import reconstruct_colour  # (torch: only when a stack is run)

        return reconstruct_colour(stack, entry, registration=registration, **kw)
    if kw.pop("colour", None) is not None:
        raise HbisInputError("the colour option (--colour) applies to colour stacks (RGB or raw Bayer frames); "
                             "this stack is grey")
    return entry.run_function()(stack, registration=registration, **kw)


# The lens blur the deblurring undoes: the classical method's, and the classical image's that the
# learned method refines (one option, so that both take it alike)
PSF_SIGMA = Option("--psf-sigma", "lens_sigma", "a Gaussian lens blur (standard deviation, LR px) that the deblurring "
                   "undoes beyond the pixel's area and the optics' diffraction: a number (from a calibration such as "
                   "a slanted edge; 0: none) or 'auto', the default: bursts measure it on their own straight edges "
                   "and say what they found, scans take none. Too large a value rings and costs more than too small "
                   "a one (docs/real-bursts.md)", {"type": auto_or(bounded_float(0.0, 3.0)), "metavar": "PX|auto"})


register(Method(
    name="classical",
    run="hbis_torch.reconstruct.classical.method:reconstruct_classical",
    raw_bayer="hbis_torch.reconstruct.classical.method:reconstruct_classical_raw_bayer",
    burst="hbis_torch.reconstruct.classical.burst:classical_burst",
    summary="splat the samples at their positions and deblur with a Wiener filter (docs/classical.md)",
    options=(
        Option("--no-deblur", "deblur", "interpolation only, without the Wiener deblurring",
               {"action": "store_false"}),
        PSF_SIGMA,
    ),
))

register(Method(
    name="learned",
    run="hbis_torch.reconstruct.learned.method:reconstruct_learned",
    raw_bayer="hbis_torch.reconstruct.learned.method:reconstruct_learned_raw_bayer",
    burst="hbis_torch.reconstruct.learned.burst:learned_burst",
    summary="the classical image refined by a small network in onnxruntime (docs/learned.md)",
    threads=True,
    options=(
        Option("--model", "model", "'fast' (the default: the shipped small model for the stack's h), 'best' "
               "(the shipped larger model: more held-out dB for more time, docs/learned.md; at h = 3, which has "
               "none, the fast one) or an ONNX model file",
               {"type": str, "metavar": "fast|best|M.onnx"}),
        Option("--provider", "provider", "what runs the model; 'auto' (the default) and 'cpu': onnxruntime's "
               "CPU kernels; 'openvino': OpenVINO (pip install 'hbis-torch[openvino]'), no faster in fp32",
               {"choices": ("auto", "openvino", "cpu")}),
        Option("--extrapolate", "extrapolate", "run the network on a stack outside its training domain too "
               "(a lens blurrier, or noise far lower or higher, than any it was trained on); by default such "
               "a stack gets the classical image, with a message", {"action": "store_true"}),
        Option("--ensemble", "ensemble", "average the network over this many of the square's 8 flips and "
               "rotations (geometric self-ensemble; default: the fast models 2 at h = 3 and 7, where the classical "
               "step takes most of the time, else 1; the best models 2, and 8 at h = 7): as many times the "
               "network's time, for a small gain in PSNR",
               {"type": int, "choices": (1, 2, 4, 8)}),
        Option("--precision", "precision", "how the network runs: 'fp32' (the default for the shipped models); "
               "'int8', its int8 file NAME.int8.onnx (shipped for h = 2, 3, 4, 7, both tiers), 1.2-1.4 times as "
               "fast on AVX2 cores, 2 times with AVX-512 VNNI; 'bf16', the float32 file in OpenVINO in bfloat16 "
               "(pip install 'hbis-torch[openvino]'), about 4 times as fast on cores with AMX (4.13x measured, "
               "benchmarks/results/bench_fast.md), "
               "float32 on others. Each loses PSNR in the held-out matrix's cleanest cells: int8 up to 3.7 dB, "
               "bf16 up to 0.33 dB, in cells above 50 dB (docs/learned.md, section int8)",
               {"choices": ("int8", "bf16", "fp32")}),
        PSF_SIGMA,
        Option("--no-adapt", "adapt", "bursts: refine with the network as shipped, not first fine-tuned for a few "
               "seconds to predict the burst's own left-out frames (test-time adaptation, docs/real-bursts.md)",
               {"action": "store_false"}),
    ),
))
