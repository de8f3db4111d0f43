"""The registration of a stack: the :class:`Registration` result and :func:`register_stack`
(:func:`register_models`: several models of one stack, from one preparation).

``register_stack`` checks its input, normalises the frames photometrically, picks the points to
compare, starts every frame from the prediction or phase correlation, fits it
(:mod:`.lucas_kanade`), chooses the motion model (:mod:`.model_choice`) and assesses the result
(:mod:`.assess`). Frames are (F, H, W) of any real dtype; homographies (F, 3, 3) float64 map
frame px -> reference px; per-frame results are (F,); precision and thresholds are in px.
"""

from __future__ import annotations

import contextvars
import dataclasses
import functools
import math
import operator
from dataclasses import dataclass, field

import torch
from torch import Tensor

from hbis_torch.errors import HbisInputError
from hbis_torch.registration.assess import (
    MIN_CORRELATION,
    _assess,
    _check_order,
    _precision_px,
)
from hbis_torch.registration.bspline import _reference_splines, gaussian_kernel
from hbis_torch.registration.homography import ALL_MODELS, MODELS, apply_homography
from hbis_torch.registration.lucas_kanade import (
    _Fit,
    _LucasKanade,
    _merge,
    _strongest_points,
)
from hbis_torch.registration.model_choice import _choose_model
from hbis_torch.registration.phase_correlation import (
    _translation,
    phase_correlation_shifts,
)
from hbis_torch.sensor.noise import mean_and_spread, noise_sigma


@dataclass
class Registration:
    """Result of :func:`register_stack`.

    Attributes
    ----------
    homographies : Tensor, shape (F, 3, 3), float64
        Frame-k pixel coordinates -> reference pixel coordinates (identity for the reference).
    model : str
        The motion model used (``translation``, ``similarity`` or ``homography``).
    confidence : Tensor, shape (F,), float64 in [0, 1]
        How far to trust each frame's motion (1 for the reference).
    ok : Tensor, shape (F,), bool
        False for frames whose motion should not be used.
    messages : list of str
        One line per problem found, naming the frame.
    precision_px : Tensor, shape (F,), float64
        Expected standard error of the motion (px, RMS over the frame) from the fit's curvature.
    residual : Tensor, shape (F,), float64
        Robust scale of the aligned difference, in units of the frame's standard deviation.
    out_of_order : Tensor, shape (F,), bool
        Frames found nearer another frame's predicted position than their own (needs a
        prediction; all False without one).
    converged : Tensor, shape (F,), bool
        Whether each frame's fit converged (True for the reference).
    """

    homographies: Tensor
    model: str
    confidence: Tensor
    ok: Tensor
    messages: list[str] = field(default_factory=list)
    precision_px: Tensor | None = None
    residual: Tensor | None = None
    out_of_order: Tensor | None = None
    converged: Tensor | None = None

    def displacement(self, u: float, v: float) -> Tensor:
        """(F, 2): where frame pixel (u, v) lands in the reference, minus (u, v), in px."""
        point = torch.tensor([[u, v]], dtype=torch.float64)
        return apply_homography(self.homographies, point)[:, 0] - point


def _check_frames(frames) -> Tensor:
    if not isinstance(frames, Tensor):
        try:
            frames = torch.as_tensor(frames)
        except (TypeError, ValueError, RuntimeError) as exc:
            raise HbisInputError(f"frames must be a (F, H, W) array of numbers: {exc}") from None
    if frames.ndim != 3:
        raise HbisInputError(f"frames must have shape (F, H, W), got {tuple(frames.shape)}")
    F, H, W = frames.shape
    if F < 1 or H < 16 or W < 16:
        raise HbisInputError(f"frames must be at least one 16 x 16 frame, got shape {(F, H, W)}")
    if frames.dtype == torch.bool or frames.is_complex():
        raise HbisInputError(f"frames must be real numbers, got dtype {frames.dtype}")
    # A finite sum means finite values (one reduction); only an inf sum needs the full check.
    if frames.is_floating_point() and not (torch.isfinite(frames.sum()) or torch.isfinite(frames).all()):
        raise HbisInputError("frames contain non-finite values (NaN or inf)")
    return frames


def _check_prediction(prediction, F: int) -> Tensor | None:
    if prediction is None:
        return None
    prediction = torch.as_tensor(prediction, dtype=torch.float64)
    if prediction.shape != (F, 3, 3):
        raise HbisInputError(
            f"prediction must have shape ({F}, 3, 3) (one homography per frame), "
            f"got {tuple(prediction.shape)}"
        )
    if not torch.isfinite(prediction).all():
        raise HbisInputError("prediction contains non-finite values")
    if bool((prediction[:, 2, 2].abs() < 1e-12).any()) or bool(
        (torch.linalg.det(prediction).abs() < 1e-12).any()
    ):
        raise HbisInputError("prediction contains a singular homography")
    return prediction / prediction[:, 2:3, 2:3]


def _in_inference_mode(fn):
    """Run ``fn`` under ``torch.inference_mode`` (no autograd bookkeeping: at small frames the
    registration's cost is mostly per tensor operation, and this takes about a tenth off) and
    hand back ordinary tensors, which callers may modify in place."""
    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        with torch.inference_mode():
            result = fn(*args, **kwargs)
        if isinstance(result, dict):
            return {key: _plain(value) for key, value in result.items()}
        return _plain(result)

    return wrapper


def _plain(result):
    """``result`` (a dataclass) with ordinary copies of its inference-mode tensors."""
    tensors = {name: value.clone() for name, value in vars(result).items() if isinstance(value, Tensor)}
    return dataclasses.replace(result, **tensors)


@_in_inference_mode
def register_stack(
    frames,
    reference_index: int,
    prediction=None,
    model: str = "auto",
    *,
    blur_sigma: float = 1.0,
    keep_fraction: float = 0.2,
    max_points: int = 1024,
    iterations: int = 30,
    tolerance_px: float = 1e-2,
    motion_tolerance_px: float = 0.01,
    min_confidence: float = 0.5,
    dtype=torch.float32,
    ladder: tuple[str, ...] = MODELS,
) -> Registration:
    """Estimate each frame's motion relative to the reference frame.

    Parameters
    ----------
    frames : Tensor or array, shape (F, H, W)
        The stack, any real dtype. Each frame is normalised to zero mean and unit standard
        deviation first, so gain and offset need not match.
    reference_index : int
        Index of the reference frame (its homography is the identity).
    prediction : Tensor, shape (F, 3, 3), optional
        Predicted homographies (frame -> reference pixel coordinates) from the optics, for
        example ``homographies_from_positions(optical_sample_positions(stack))``. The data
        corrects them; without a prediction the motion starts from phase correlation, and frames
        out of order cannot be told.
    model : {"auto", "translation", "similarity", "homography"}
        Motion model of the data's correction (on top of the prediction, if any).
    blur_sigma : float
        Gaussian pre-filter (px) on every frame, against noise and the aliased content that
        differs between shifted frames. The default 1.0 was chosen on bench_registration's
        stacks (4 scenes x 128, 256, 512 px, h = 4, 40 dB): mean error 0.0036 px against
        0.0066 at 0.7 and 0.0036 at 1.4; the aliased bars gain most.
    keep_fraction : float in (0, 1]
        Share of reference pixels (strongest gradients) that take part in the fit.
    max_points : int
        At most this many of them (at least 64): they hold nearly all the information on the
        motion, and the fit's cost grows with their number, not with the frame size.
    iterations, tolerance_px : int, float
        Lucas-Kanade stops when an update moves no corner of the frame by more than
        ``tolerance_px``.
    motion_tolerance_px : float
        In ``auto`` mode, a richer model must move some pixel by more than this to be kept.
    min_confidence : float
        Frames below this confidence are marked not ok.
    dtype : torch.dtype
        Precision of the resampling (float32 by default; the normal equations are always solved
        in float64). float32 agrees with float64 to well below 1e-3 px (tests check it).
    ladder : tuple of str
        The models ``auto`` climbs, simplest first: :data:`MODELS`, or
        :data:`~hbis_torch.registration.homography.ALL_MODELS` (with ``affine``, for bursts).

    Returns
    -------
    Registration
    """
    frames, ref, prediction = _check_arguments(frames, reference_index, prediction, model, blur_sigma,
                                               keep_fraction, max_points, dtype)
    F, H, W = frames.shape
    frames = frames.to(dtype)
    flat, noise, coefficients, points, samples, corr_area, margin = _prepare(frames, ref, blur_sigma, keep_fraction,
                                                                            max_points, dtype)
    init = _starting_motion(frames, ref, prediction)
    lk = _LucasKanade(coefficients, samples, points, margin)

    chosen = "translation" if model == "auto" else model
    fit, keep, mismatch = _fit_with_occlusion(lk, init, chosen, iterations, tolerance_px)
    # The model is chosen on the frames that registered sensibly (converged, and correlating
    # with the reference where compared), not on the failures flagged below.
    use = fit.converged & (fit.correlation >= MIN_CORRELATION) & ~flat
    use[ref] = False
    if model == "auto" and bool(use.any()):
        chosen, fit = _choose_model(lk, fit, chosen, keep, corr_area, use, iterations, tolerance_px,
                                    motion_tolerance_px, ladder)

    fit.mismatch_fraction = mismatch
    precision, confidence, messages = _confidence(fit, chosen, flat, noise, ref, (H, W), blur_sigma, corr_area,
                                                  iterations)
    ok = confidence >= min_confidence
    Hk, out_of_order = _final_motion(fit, init, prediction, ok, confidence, ref, (H, W), messages)
    precision[ref] = 0.0
    residual = fit.sigma.clone()
    residual[ref] = 0.0
    converged = fit.converged.clone()
    converged[ref] = True
    return Registration(Hk, chosen, confidence, ok, messages, precision, residual, out_of_order, converged)


#: Set while :func:`register_models` runs: the preparations its fits share, by their settings.
_SHARED: contextvars.ContextVar[dict | None] = contextvars.ContextVar("shared_preparation", default=None)


@_in_inference_mode
def register_models(frames, reference_index: int, predictions: dict, done=None, **options) -> dict:
    """:func:`register_stack` of one stack for each model of ``predictions`` (model -> its
    prediction, (F, 3, 3) or None), ``options`` its keywords: the same registrations, with what the
    fits share (the frames' normalisation, the reference's splines and the points compared)
    prepared once rather than once a model. ``done``, if given, is called with each model once
    it is fitted (a progress bar's update).

    Returns
    -------
    dict of str -> Registration
    """
    token, out = _SHARED.set({}), {}
    try:
        for model, prediction in predictions.items():
            out[model] = register_stack.__wrapped__(frames, reference_index, prediction, model, **options)
            if done is not None:
                done(model)
    finally:
        _SHARED.reset(token)
    return out


def _prepare(frames: Tensor, ref: int, blur_sigma: float, keep_fraction: float, max_points: int, dtype):
    """What every fit of ``frames`` (F, H, W) shares, for :func:`register_stack`: which frames are
    flat (F,), the noise (F,), the reference's spline coefficients, the points compared and the
    frames' samples there, the correlated area and the margin (:func:`_compared_points`); kept
    for the next model while :func:`register_models` runs."""
    shared, key = _SHARED.get(), (ref, blur_sigma, keep_fraction, max_points, dtype)
    if shared is not None and key in shared:
        return shared[key]
    F, H, W = frames.shape
    mean, spread, flat, reference = _normalisation(frames, ref)
    noise = noise_sigma(reference[None]).expand(F)  # the same sensor: one frame says enough
    kernel, margin = _blur_and_margin(H, W, blur_sigma, dtype)
    coefficients, points, samples, corr_area = _compared_points(frames, reference, mean, spread, kernel, margin,
                                                                blur_sigma, keep_fraction, max_points)
    prepared = flat, noise, coefficients, points, samples, corr_area, margin
    if shared is not None:
        shared[key] = prepared
    return prepared


def _check_arguments(frames, reference_index, prediction, model: str, blur_sigma: float, keep_fraction: float,
                     max_points: int, dtype) -> tuple[Tensor, int, Tensor | None]:
    """:func:`register_stack`'s arguments, checked in order (:class:`HbisInputError` on the first
    bad one): the frames as a (F, H, W) tensor, the reference's index, and the prediction
    (F, 3, 3) float64 scaled to H[2, 2] = 1, or None."""
    frames = _check_frames(frames)
    F = frames.shape[0]
    try:
        if isinstance(reference_index, bool):
            raise TypeError
        ref = operator.index(reference_index)
    except TypeError:
        raise HbisInputError(f"reference_index must be an integer, got {reference_index!r}") from None
    if not 0 <= ref < F:
        raise HbisInputError(f"reference_index must lie in [0, {F - 1}], got {ref}")
    prediction = _check_prediction(prediction, F)
    if model != "auto" and model not in ALL_MODELS:
        raise HbisInputError(f"model must be 'auto' or one of {ALL_MODELS}, got {model!r}")
    if not (math.isfinite(blur_sigma) and 0 <= blur_sigma <= 5):
        raise HbisInputError(f"blur_sigma must be a number in [0, 5] px, got {blur_sigma!r}")
    if not 0 < keep_fraction <= 1:
        raise HbisInputError(f"keep_fraction must lie in (0, 1], got {keep_fraction!r}")
    if isinstance(max_points, bool) or not isinstance(max_points, int) or max_points < 64:
        raise HbisInputError(f"max_points must be an integer >= 64, got {max_points!r}")
    if dtype not in (torch.float32, torch.float64):
        raise HbisInputError(f"dtype must be torch.float32 or torch.float64, got {dtype!r}")
    return frames, ref, prediction


def _normalisation(frames: Tensor, ref: int) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Photometric normalisation: every frame (F, H, W) to zero mean and unit standard deviation.

    Returns each frame's mean and spread (F,) (the spread at least a tiny floor), which frames
    are flat (F,) bool, and the normalised reference frame (H, W).
    """
    mean, spread = mean_and_spread(frames)
    tiny = 1e-6 * max(1.0, float(mean.abs().max()))
    flat = spread < tiny
    spread = spread.clamp_min(tiny)
    reference = (frames[ref] - mean[ref]) / spread[ref]
    return mean, spread, flat, reference


def _blur_and_margin(H: int, W: int, blur_sigma: float, dtype) -> tuple[Tensor, int]:
    """The blur's sampled kernel (2 r + 1,) and the border (px) that compared points keep clear
    of; frames (W x H px) too small for them are refused."""
    kernel = gaussian_kernel(blur_sigma, dtype)
    radius = (len(kernel) - 1) // 2
    margin = max(2 + int(math.ceil(2 * blur_sigma)), radius)
    if min(H, W) <= 2 * margin + 8:
        raise HbisInputError(f"frames of {W} x {H} px are too small to register (blur_sigma={blur_sigma})")
    return kernel, margin


def _compared_points(frames: Tensor, reference: Tensor, mean: Tensor, spread: Tensor, kernel: Tensor,
                     margin: int, blur_sigma: float, keep_fraction: float, max_points: int):
    """What the fit compares: the reference's strongest gradients, away from the border, and
    every frame (F, H, W), blurred like the reference and normalised by its ``mean`` and
    ``spread`` (F,), at those points only.

    Returns
    -------
    coefficients : Tensor, shape (3, H, W)
        The reference's B-spline coefficients, value and d/du, d/dv (:func:`_reference_splines`).
    points : Tensor, shape (N, 2), float64
        (u, v) integer pixel coordinates.
    samples : Tensor, shape (F, N)
        The blurred, normalised frames at the points.
    corr_area : float
        How many of the compared points share one area of correlated (blurred) residuals.
    """
    F, H, W = frames.shape
    radius = (len(kernel) - 1) // 2
    # The points: the reference's strongest gradients, away from the border.
    coefficients, strength = _reference_splines(reference, kernel)
    index = _strongest_points(strength, margin, keep_fraction, max_points)
    n_points = len(index)
    # Blurred residuals are correlated over about 4 pi sigma^2 pixels; what the statistics need
    # is how many of the compared points share one such area.
    corr_area = max(1.0, 4 * math.pi * blur_sigma ** 2 * n_points / ((H - 2 * margin) * (W - 2 * margin)))
    points = torch.stack((index % W, index // W), -1).double()  # (N, 2) as (u, v)
    # Every frame, blurred like the reference, at the points only (a patch each).
    patch = (torch.arange(-radius, radius + 1)[:, None] * W + torch.arange(-radius, radius + 1)[None, :]).reshape(-1)
    gathered = frames.reshape(F, -1).index_select(1, (index[:, None] + patch).reshape(-1))
    values = gathered.view(F, n_points, -1) @ torch.outer(kernel, kernel).reshape(-1)
    samples = (values - mean[:, None]) / spread[:, None]
    return coefficients, points, samples, corr_area


def _starting_motion(frames: Tensor, ref: int, prediction: Tensor | None) -> Tensor:
    """Where the fit starts, (F, 3, 3) float64: the prediction, or without one the translation
    that phase correlation finds; the identity for the reference."""
    if prediction is not None:
        init = prediction.clone()
    else:
        H, W = frames.shape[-2:]
        # A central window of at most 256 x 256 px is plenty for a start within the fit's reach.
        v0, u0 = max(0, (H - 256) // 2), max(0, (W - 256) // 2)
        window = frames[:, v0:v0 + 256, u0:u0 + 256]
        init = _translation(phase_correlation_shifts(window, window[ref]))
    init[ref] = torch.eye(3, dtype=torch.float64)
    return init


def _fit_with_occlusion(lk: _LucasKanade, init: Tensor, model: str, iterations: int,
                        tolerance_px: float) -> tuple[_Fit, Tensor | None, Tensor]:
    """Fit ``model`` from ``init`` (F, 3, 3), then again without the tiles that do not match.

    Returns the fit, the points it kept (F, N) bool (None when all), and the first fit's
    mismatch fraction (F,) (what is reported as occluded).
    """
    fit = lk.fit(init, model, iterations, tolerance_px)
    # Occlusion: leave out the tiles that do not match and fit those frames again. Only frames
    # that converged: one that did not has no tiles that match for a reason (another scene, no
    # texture), and leaving out its worst tiles would only flatter its correlation.
    keep, mismatch = None, fit.mismatch_fraction
    redo = ((mismatch > 0) & fit.converged).nonzero()[:, 0]
    if len(redo):
        keep = ~fit.mismatch_points
        again = lk.fit(fit.homographies[redo], model, iterations, tolerance_px, redo, keep[redo])
        fit = _merge(fit, again, redo)
    return fit, keep, mismatch


def _confidence(fit: _Fit, model: str, flat: Tensor, noise: Tensor, ref: int, size: tuple[int, int],
                blur_sigma: float, corr_area: float, iterations: int) -> tuple[Tensor, Tensor, list[str]]:
    """Precision (F,) px, confidence (F,) and messages of ``fit`` (:func:`_assess`), for frames
    of ``size`` (H, W) px with noise level ``noise`` (F,) (in units of the frames' spread)."""
    H, W = size
    # What noise alone leaves in the residual: two frames' noise, through the blur.
    blur_gain = 1.0 if blur_sigma < 0.5 else 1 / (2 * math.sqrt(math.pi) * blur_sigma)
    noise_residual = math.sqrt(2) * blur_gain * noise
    precision = _precision_px(fit, model, H, W, corr_area)
    confidence, messages = _assess(fit, precision, flat, noise_residual, ref, iterations)
    return precision, confidence, messages


def _final_motion(fit: _Fit, init: Tensor, prediction: Tensor | None, ok: Tensor, confidence: Tensor, ref: int,
                  size: tuple[int, int], messages: list[str]) -> tuple[Tensor, Tensor]:
    """The homographies to report (F, 3, 3) and the frames out of order (F,) bool, appending a
    message for every frame not ``ok`` and every problem the order check finds."""
    F = len(ok)
    H, W = size
    Hk = fit.homographies.clone()
    # A frame that failed keeps its starting motion (the prediction, if any), not a wild guess.
    Hk[~ok] = init[~ok]
    Hk[ref] = torch.eye(3, dtype=torch.float64)
    for k in (~ok).nonzero()[:, 0].tolist():
        start = "predicted" if prediction is not None else "phase-correlation"
        messages.append(f"frame {k}: not registered (confidence {float(confidence[k]):.2f}); "
                        f"its {start} motion is kept")
    out_of_order = torch.zeros(F, dtype=torch.bool)
    if prediction is not None and F > 2:
        out_of_order, order_messages = _check_order(Hk, prediction, H, W, ref, ok)
        messages += order_messages
    return Hk, out_of_order
