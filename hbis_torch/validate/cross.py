"""Observation-space cross-validation: hold a frame out, super-resolve the rest, predict the
held-out frame through the forward model and score the prediction (docs/validate.md).

The idea is Nguyen, Milanfar and Golub's, who chose the regularisation of multi-frame
super-resolution by (generalised) cross-validation: N. Nguyen, P. Milanfar and G. Golub,
"Efficient generalized cross-validation with applications to parametric image restoration and
resolution enhancement", IEEE Transactions on Image Processing 10(9), 1299-1308 (2001).
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np

from hbis_torch.errors import HbisInputError
from hbis_torch.notices import act
from hbis_torch.validate.baseline import ALIASES, SINGLE_FRAME, single_frame
from hbis_torch.observation.forward import DEFAULT_BLUR_PX, predict_frame
from hbis_torch.validate.frames import holdout_frames, select_frames
from hbis_torch.validate.score import DEFAULT_BORDER_PX, FrameScore, fit_and_score, inside

#: What :func:`cross_validate` compares by default.
DEFAULT_METHODS = (SINGLE_FRAME, "classical", "learned")
#: Frames held out by default (fewer where the stack has fewer besides the reference).
DEFAULT_HOLDOUT = 3


@dataclasses.dataclass
class MethodScores:
    """One method's cross-validation.

    Attributes
    ----------
    name : str
    frames : list of FrameScore
        One per held-out frame, in the order of :attr:`Validation.held_out`.
    seconds : float
        Mean wall time of one reconstruction, s.
    messages : list of str
        What the method said (once each), e.g. that it returned the classical image.
    """

    name: str
    frames: list[FrameScore]
    seconds: float
    messages: list[str]

    @property
    def psnr(self) -> list[float]:
        """PSNR of each held-out frame's prediction, dB."""
        return [s.psnr for s in self.frames]

    @property
    def mean_psnr(self) -> float:
        """The mean of :attr:`psnr`, dB."""
        return float(np.mean(self.psnr))


@dataclasses.dataclass
class Validation:
    """The result of :func:`cross_validate`.

    Attributes
    ----------
    held_out : list of int
        The frames held out, one at a time.
    methods : dict of str to MethodScores
        In the order asked for.
    scored_on : str
        ``"grey"``, ``"luma"`` (RGB stacks: BT.601 luminance of the prediction and the frame) or
        ``"mosaic"`` (raw Bayer stacks: each pixel against its own colour of the prediction).
    h, frames, reference_index, registration, border_px, blur_px
        The stack's refinement factor, frame count and reference; the settings used.
    """

    held_out: list[int]
    methods: dict[str, MethodScores]
    scored_on: str
    h: int
    frames: int
    reference_index: int
    registration: str
    border_px: float
    blur_px: float

    def gain(self, method: str, baseline: str = SINGLE_FRAME) -> float:
        """Mean PSNR of ``method`` minus that of ``baseline``, dB."""
        return self.methods[method].mean_psnr - self.methods[baseline].mean_psnr

    def to_dict(self) -> dict:
        """Plain JSON-ready dictionary (what ``hbis validate --json`` prints)."""
        out = {k: getattr(self, k) for k in ("held_out", "scored_on", "h", "frames", "reference_index",
                                            "registration", "border_px", "blur_px")}
        out["methods"] = {name: {"mean_psnr_db": m.mean_psnr, "psnr_db": m.psnr,
                                 "gain": [s.gain for s in m.frames], "offset": [s.offset for s in m.frames],
                                 "samples": [s.samples for s in m.frames], "seconds": m.seconds,
                                 "messages": m.messages}
                          for name, m in self.methods.items()}
        return out


def resolve_methods(methods) -> list[str]:
    """Canonical names of ``methods`` (a name, or names; "bicubic" and "single" mean
    :data:`SINGLE_FRAME`); an unknown one is refused in one line, naming those there are."""
    from hbis_torch.reconstruct.registry import METHODS

    names = [methods] if isinstance(methods, str) else list(methods)
    out = []
    for name in names:
        name = ALIASES.get(name, name)
        if name != SINGLE_FRAME and name not in METHODS:
            raise HbisInputError(f"unknown method {name!r}; available: {', '.join((SINGLE_FRAME, *METHODS))} "
                                 "(bicubic = single-frame)")
        if name not in out:
            out.append(name)
    if not out:
        raise HbisInputError("no method to validate")
    return out


def _scoring_kind(stack) -> str:
    if stack.meta.get("cfa") is not None:
        return "mosaic"
    return "luma" if stack.frames.ndim == 4 else "grey"


def _observed_and_gray(stack):
    """The frames as scored (F, H, W), the grey frames to register on (F, H, W) and the
    reference frame as the single-frame baseline enlarges it ((H, W) or RGB (H, W, 3)), float in
    [0, 1]."""
    from hbis_torch.reconstruct.colour import LUMA

    frames = stack.to_float().numpy()
    ref = stack.reference_index
    kind = _scoring_kind(stack)
    if kind == "grey":
        return frames, frames, frames[ref]
    if kind == "luma":
        luma = frames @ LUMA.astype(np.float32)
        return luma, luma, frames[ref]
    from hbis_torch.sensor.cfa import demosaic

    rgb = demosaic(frames, stack.meta["cfa"])
    return frames, rgb @ LUMA.astype(np.float32), rgb[ref]


def _positions(stack, gray, registration: str, messages: list):
    """Sample positions (F, H, W, 2) of every frame and which are trusted (F,), from the layer's
    one policy (:func:`hbis_torch.reconstruct.positions.stack_sample_positions`), on the grey
    frames ``gray``. A burst's are a :class:`~hbis_torch.reconstruct.positions.BurstPositions`,
    computed where read (the held-out frames' alone: a 16-frame 12 MP burst's whole are 3 GB)."""
    import torch

    from hbis_torch.reconstruct.colour import gray_stack
    from hbis_torch.reconstruct.positions import burst_positions, stack_sample_positions

    if stack.kind == "burst":
        positions, trusted = burst_positions(stack, lazy=True)
        return positions, trusted.numpy()
    grey = stack if _scoring_kind(stack) == "grey" else gray_stack(stack, gray)
    positions, trusted = stack_sample_positions(grey, registration, frames=torch.from_numpy(
        np.ascontiguousarray(gray, dtype=np.float32)), messages=messages)
    return positions.numpy(), trusted.numpy()


def _choosable(stack, gray, trusted, messages: list | None):
    """The frames a burst may hold out: its trusted ones but those blurred
    (:func:`~hbis_torch.capture.sharpness.blurred_frames`: a shaken frame's prediction from the
    others would score its shake, not the method); a scan's trusted ones."""
    if stack.kind != "burst":
        return trusted
    import torch

    from hbis_torch.capture.sharpness import blurred_frames

    blurred, _ = blurred_frames(torch.from_numpy(np.ascontiguousarray(gray, dtype=np.float32)),
                                stack.reference_index, trusted)
    if not blurred:
        return trusted
    if messages is not None:
        messages.append(f"frame(s) {blurred} are blurred (shaken or out of focus): held out only where too few "
                        "others are")
    out = np.array(trusted, dtype=bool)
    out[blurred] = False
    return out


class _Scorer:
    """Predicts and scores held-out frames of one stack (the forward model's fixed parts)."""

    def __init__(self, stack, observed, positions, border_px: float, blur_px: float):
        from hbis_torch.reconstruct.classical.method import stack_fill_factor

        self.kind = _scoring_kind(stack)
        self.h = stack.h
        self.rows, self.cols = stack.frames.shape[1:3]
        self.observed, self.positions = observed, positions
        self.border_px, self.blur_px = border_px, blur_px
        self.fill_factor = stack_fill_factor(stack)
        self.cfa = stack.meta.get("cfa")

    def __call__(self, estimate, k: int) -> FrameScore:
        from hbis_torch.reconstruct.colour import LUMA

        estimate = np.asarray(estimate, dtype=np.float64)
        if self.kind == "luma" and estimate.ndim == 3:
            estimate = estimate @ LUMA
        positions = np.asarray(self.positions[k])
        predicted = predict_frame(estimate, positions, self.h, self.fill_factor, self.blur_px)
        if self.kind == "mosaic":
            from hbis_torch.sensor.cfa import mosaic

            predicted = mosaic(predicted, self.cfa)
        mask = inside(positions, self.rows, self.cols, self.border_px)
        return fit_and_score(predicted, self.observed[k], mask)


def cross_validate(stack, methods=DEFAULT_METHODS, holdout: int | None = None, *, registration: str = "auto",
                   border_px: float = DEFAULT_BORDER_PX, blur_px: float = DEFAULT_BLUR_PX,
                   method_options: dict | None = None, messages: list | None = None,
                   on_step=None, extra_methods: dict | None = None) -> Validation:
    """Score methods on a stack without ground truth: leave frames out one at a time, super-resolve
    the rest, predict the held-out frame and measure the PSNR of the prediction.

    Parameters
    ----------
    stack : hbis_torch.stack_io.Stack
        An HBIS scan stack or a burst, grey, RGB or raw Bayer, of at least 2 frames.
    methods : str or sequence of str
        Registered methods (:data:`hbis_torch.reconstruct.registry.METHODS`) and
        ``"single-frame"`` (alias ``"bicubic"``): the reference frame alone, enlarged bicubically.
    holdout : int, optional
        How many frames to hold out, one at a time (:func:`holdout_frames`: spread over the stack,
        never the reference). Default: 3, or every frame besides the reference where there are
        fewer.
    registration : {"optics", "data", "auto"}
        Passed to the methods; also where the held-out frames' sample positions come from.
    border_px : float
        Samples within this many LR pixels of the reference frame's edge are not scored.
    blur_px : float
        The forward model's Gaussian blur, LR pixels (:mod:`hbis_torch.observation.forward`).
    method_options : dict, optional
        Per method name, keywords for :func:`hbis_torch.reconstruct.reconstruct`.
    messages : list, optional
        Receives the registration's warnings about the whole stack, and a line naming held-out
        frames whose motion is not trusted (the methods' own lines are in each
        :attr:`MethodScores.messages`).
    on_step : callable, optional
        Called with no argument after each reconstruction (a progress bar's ``update``).
    extra_methods : dict of str to callable, optional
        Methods from outside the registry (a peer package, a variant under study), by name, scored
        after ``methods`` on the same held-out frames, forward model and samples. Each is called
        once per held-out frame with that fold's stack: :func:`select_frames` of every frame but the
        held-out one, exactly what the registered methods are given (the reference kept, its
        ``reference_index`` re-indexed in the reduced set). It returns the super-resolved image on
        the output grid of the reference frame refined ``stack.h`` times (docs/design.md section
        1: HR pixel (U, V) centred at LR ((U + 0.5) / h - 0.5, (V + 0.5) / h - 0.5)), shape
        (h H, h W), or (h H, h W, 3) for an RGB stack (a 2-D image of an RGB stack is taken as its
        luma). Messages are not collected from them. A name that is a registered method or the
        baseline is refused.

    Returns
    -------
    Validation
    """
    from hbis_torch.reconstruct.positions import check_registration
    from hbis_torch.reconstruct.registry import METHODS, reconstruct

    if isinstance(stack.meta.get("raw"), dict):  # a raw burst (docs/raw-bursts.md): its own levels per frame
        raise HbisInputError("hbis validate does not score raw bursts (hbis assemble --burst of raw files) yet: "
                             "their samples are a mosaic with levels of their own")
    names = resolve_methods(methods)
    extra = dict(extra_methods or {})
    for name, method in extra.items():
        if not isinstance(name, str) or not name or name in ALIASES or name in METHODS:
            raise HbisInputError(f"extra method {name!r}: needs a name of its own (not a registered method or "
                                 f"{SINGLE_FRAME})")
        if not callable(method):
            raise HbisInputError(f"extra method {name!r} is not callable")
    check_registration(registration)
    count = len(stack.frames)
    holdout = min(DEFAULT_HOLDOUT, count - 1) if holdout is None else int(holdout)
    holdout_frames(count, stack.reference_index, holdout)  # refuses a bad count before any work
    options = dict(method_options or {})
    observed, gray, reference = _observed_and_gray(stack)
    positions, trusted = _positions(stack, gray, registration, messages if messages is not None else [])
    held = holdout_frames(count, stack.reference_index, holdout, _choosable(stack, gray, trusted, messages))
    doubtful = [k for k in held if not trusted[k]]
    if doubtful and messages is not None:
        messages.append(act(f"held-out frame(s) {doubtful}: their motion is not trusted (too few trusted frames to "
                            "hold out instead), so their predictions, and scores, are doubtful for every method; "
                            "read the scores with care or validate a burst with more trusted frames"))
    score = _Scorer(stack, observed, positions, border_px, blur_px)
    results = {}
    for name in [*names, *extra]:
        scores, seconds, said = [], [], []
        for k in held:
            start = time.perf_counter()
            if name == SINGLE_FRAME:  # the reference is never held out: one image serves every frame
                estimate = single_frame(reference, stack.h)
            else:
                subset = select_frames(stack, [i for i in range(count) if i != k])
                if name in extra:
                    estimate = extra[name](subset)
                    grid = (stack.h * score.rows, stack.h * score.cols)
                    if np.shape(estimate)[:2] != grid:
                        raise HbisInputError(f"extra method {name!r} returned an image of shape "
                                             f"{np.shape(estimate)}, not the output grid's {grid}")
                else:
                    estimate = reconstruct(subset, method=name, registration=registration, messages=said,
                                           **options.get(name, {}))
            seconds.append(time.perf_counter() - start)
            scores.append(score(estimate, k))
            if on_step is not None:
                on_step()
        results[name] = MethodScores(name, scores, float(np.mean(seconds)), list(dict.fromkeys(said)))
    return Validation(held, results, score.kind, stack.h, count, stack.reference_index, registration,
                      float(border_px), float(blur_px))

