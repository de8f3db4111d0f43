"""Captured frames of a freely moving camera (a burst) -> one ``hbis-stack/1`` burst stack.

Each frame's motion to the reference is measured from the data (no optics, no phases):

1. *coarse*: phase correlation (inside :func:`~hbis_torch.registration.register_stack`); where
   that leaves the frame unregistered, ORB features matched to the reference and a RANSAC fit
   (OpenCV) give a second start, for motion beyond the correlation's reach;
2. *fine*: the project's Lucas-Kanade (:func:`~hbis_torch.registration.register_stack`), frame
   by frame against the reference, so that the motion model is chosen per frame: the ladder of
   :mod:`hbis_torch.registration.model_choice` (BIC over translation, similarity, affine,
   homography at the strongest gradients) proposes one, and it is kept only if it predicts the
   whole frame from the reference better than a translation does (:func:`prediction_error`):
   the simplest model that explains the frame. A frame identical to the reference gets
   ``identity``;
3. *brightness* (:mod:`hbis_torch.capture.brightness`): the frame, warped onto the reference
   grid, is matched to the reference by a robust least-squares gain and offset (saturated pixels
   and outliers left out);
4. *trust*: the registration's confidence; a frame that does not match the reference (another
   scene) or cannot be registered gets confidence 0 and is named in the messages.

Frames are (F, H, W) or (F, H, W, 3) of any stored dtype; motions are (F, 3, 3) float64
homographies frame px -> reference px; confidence (F,) in [0, 1]; gain_offset (F, 2) such that
``g * frame + o`` (values in [0, 1]) matches the reference.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field, replace

import numpy as np
import torch

from hbis_torch.capture.brightness import fit_gain_offset, gain_fit_levels, gain_fit_reference
from hbis_torch.capture.frames import bit_depth_hint
from hbis_torch.capture.sharpness import SHARPEST, choose_reference
from hbis_torch.capture.stuck_pixels import without_stuck_pixels
from hbis_torch.errors import HbisInputError
from hbis_torch.notices import act
from hbis_torch.stack_io import BURST_MIN_CONFIDENCE, Stack, make_burst_meta, validate_stack

log = logging.getLogger(__name__)

#: ``--motion`` choices: ``auto`` climbs translation -> similarity -> affine -> homography per frame.
MOTIONS = ("auto", "translation", "similarity", "affine", "homography")
MAX_BURST_FRAMES = 256
MIN_BURST_PX = 24  # the smallest side a burst's frames (or their picture inside black bands) may have
# Below this confidence another start is tried; frames left below BURST_MIN_CONFIDENCE are rejected.
RETRY_CONFIDENCE = 0.6
# A frame registered again from other starts (_register_pair) tries each while its best is below
# this, and keeps the best: a frame whose turn of 1.5 degrees was missed still fits its centre to
# 0.05 px and passes RETRY_CONFIDENCE, where the turn found fits to 0.01 px.
SETTLED_CONFIDENCE = 0.95
BURST_PRECISION_PX = 0.15
MATCH_RESIDUAL_ONE, MATCH_RESIDUAL_ZERO = 0.3, 0.6
FULL_OVERLAP = 0.5
MODEL_TOLERANCE_PX = 0.01
# A richer model than translation is kept only if it predicts the frame this much better (relative).
RICHER_GAIN = 0.01


@dataclass
class BurstMotion:
    """Each frame's measured motion to the reference (:func:`register_burst`).

    Attributes
    ----------
    motions : np.ndarray, shape (F, 3, 3), float64
        Frame px -> reference px.
    confidence : np.ndarray, shape (F,), float64 in [0, 1]
    models : list of str
        The model of each motion (``identity`` for the reference and exact copies of it).
    gain_offset : np.ndarray, shape (F, 2), float64
    messages : list of str
        One line per frame that was rejected or needed a second start, naming it.
    local : np.ndarray, shape (F, rows, cols, 2), float64, or None
        Local shifts on top of each motion (:mod:`hbis_torch.registration.local`), LR px; None
        for frames too small to tile.
    """

    motions: np.ndarray
    confidence: np.ndarray
    models: list
    gain_offset: np.ndarray
    messages: list = field(default_factory=list)
    local: np.ndarray | None = None


def luminance(frames: np.ndarray) -> torch.Tensor:
    """(F, H, W) float32 in [0, 1] from stored frames (F, H, W) or (F, H, W, 3) (BT.601 luma),
    converted a frame at a time (frames memory-mapped from disk are read once, and no float
    copy of the whole burst is made beside the result)."""
    frames = np.asarray(frames)
    top = float(np.iinfo(frames.dtype).max) if frames.dtype in (np.uint8, np.uint16) else None
    # torch's memory, written through a NumPy view: NumPy asks for transparent huge pages for
    # arrays of 4 MB and more, whose first touch took 4-11 times as long here (a 12 MP burst's
    # 768 MB: 4.1-12.8 s against 1.2-1.8 s in fresh processes).
    result = torch.empty(frames.shape[:3], dtype=torch.float32)
    out = result.numpy()
    for k, frame in enumerate(frames):
        if frame.ndim == 2:  # written in place: no float copy of the frame (on a 12 MP burst
            np.divide(frame, np.float32(top or 1.0), out=out[k], dtype=np.float32)  # 0.2 s a frame)
            continue
        x = frame.astype(np.float32)
        if top is not None:
            x /= top
        out[k] = x @ np.array([0.299, 0.587, 0.114], dtype=np.float32)
    return result


def _of_the_frame(message: str) -> str:
    """A pair registration's line about its frame 1, said of the frame named before it:
    "frame 1: its motion ..." -> "its motion ...", "frame 1 is flat" -> "it is flat"."""
    prefix = "frame 1: "
    return message[len(prefix):] if message.startswith(prefix) else message.replace("frame 1", "it", 1)


def register_burst(grey: torch.Tensor, reference: int = 0, motion: str = "auto",
                   names: list | None = None) -> BurstMotion:
    """Measure every frame's motion, model, brightness and confidence relative to the reference.

    Every frame's whole-frame motion is first found coarse to fine on a Gaussian pyramid
    (:func:`~hbis_torch.registration.pyramid.coarse_to_fine`, batched over the frames), so a
    turn of the camera that moves the corners by pixels is within the fit's reach. At full
    resolution each model of the ladder is fitted from that start (or the ``motion`` asked for
    alone), and ``auto`` keeps, per frame, the model with the lowest BIC of the whole frame's
    prediction error (:func:`model_evidence`): evidence that grows with the frame, so a
    rotation of a tenth of a degree wins on a 640 x 480 frame while a 48 px frame's aliasing does
    not buy a richer model. Where a frame is still untrusted, the fit starts again from its
    neighbour's motion (a burst drifts smoothly) and then from matched features. With ``-v`` the
    ``hbis_torch`` log says why each frame got its model.

    Parameters
    ----------
    grey : Tensor, shape (F, H, W), float32 in [0, 1]
        The frames' luminance (:func:`luminance`).
    reference : int
        Index of the reference frame.
    motion : str
        One of :data:`MOTIONS`: ``auto`` picks each frame's model from its data; any other
        fits that model to every frame.
    names : list of str, optional
        Where each frame came from, for the messages.

    Returns
    -------
    BurstMotion
    """
    from hbis_torch.progress import progress
    from hbis_torch.registration import ALL_MODELS, register_models
    from hbis_torch.registration.pyramid import coarse_to_fine, levels_for, project, pyramid

    F = grey.shape[0]
    shape = tuple(grey.shape[1:])
    names = names or [f"frame {k}" for k in range(F)]
    motions = np.repeat(np.eye(3)[None], F, 0)
    confidence, models = np.ones(F), ["identity"] * F
    standing = np.ones(F)  # what decides another start: the confidence, halved where the fit did not converge
    gain_offset = np.tile([1.0, 0.0], (F, 1))
    messages: list[str] = []
    ref = grey[reference]
    same = [k for k in range(F) if k != reference and torch.equal(grey[k], ref)]
    todo = [k for k in range(F) if k != reference and k not in same]
    if not todo:
        return BurstMotion(motions, confidence, models, gain_offset, messages)
    candidates = ALL_MODELS if motion == "auto" else (motion,)
    # The pyramid's level the brightness fit reads is kept (the same halvings, made once).
    images, gain_levels = pyramid(grey, levels_for(shape)), gain_fit_levels(shape)
    halved = images[gain_levels] if 0 < gain_levels < len(images) else None
    start = coarse_to_fine(grey, reference, candidates[-1], keep_levels=1, images=images)
    del images
    if start is None:  # frames too small for a pyramid: each frame's own ladder (_register_pair)
        candidates = ()
    bar = progress(desc="registering the burst", total=len(candidates) + 1, unit="step")
    predictions = {}
    for model in candidates:
        predictions[model] = project(start, model, shape)
        predictions[model][reference] = np.eye(3)
    # every model's fit from the same preparation of the frames (register_models)
    fits = register_models(grey, reference, predictions, lambda _: bar.update(), motion_tolerance_px=MODEL_TOLERANCE_PX,
                           min_confidence=0.0)
    if fits:
        from hbis_torch.registration.evidence import model_evidence

        evidence = model_evidence(grey, reference, {m: r.homographies.numpy() for m, r in fits.items()}, todo)
        for k in todo:
            chosen = min(candidates, key=lambda m: evidence[m][k])
            reg, conf = fits[chosen], burst_confidence(fits[chosen], shape, k)
            if len(candidates) > 1:
                log.info("frame %d (%s): %s (the whole frame's BIC against it: %s)", k, names[k], chosen,
                         ", ".join(f"{m} {evidence[m][k] - evidence[chosen][k]:+.1f}" for m in candidates
                                   if m != chosen))
            motions[k], models[k], confidence[k] = reg.homographies[k].numpy(), chosen, conf
            standing[k] = fit_standing(reg, shape, k)
    else:
        confidence[todo] = standing[todo] = 0.0
    # Frames left untrusted (every frame, for frames too small for a pyramid): the ladder on the
    # pair, from phase correlation, then the neighbour's motion, then matched features.
    for direction in (range(reference + 1, F), range(reference - 1, -1, -1)):
        neighbour = np.eye(3)
        for k in direction:
            if k in todo and standing[k] < RETRY_CONFIDENCE:
                reg, how = _register_pair(ref, grey[k], motion, neighbour)
                conf, stands = burst_confidence(reg, shape), fit_standing(reg, shape)
                if stands > standing[k] or confidence[k] == 0:
                    motions[k], models[k], confidence[k] = reg.homographies[1].numpy(), reg.model, conf
                    standing[k] = stands
                    if how:
                        log.info("frame %d (%s): %s%s", k, names[k], reg.model, how)
                if confidence[k] < BURST_MIN_CONFIDENCE:
                    why = "; ".join(_of_the_frame(m) for m in reg.messages
                                    if "not registered" not in m) or "its motion is not measurable"
                    messages.append(f"frame {k} ({names[k]}) rejected (registration confidence "
                                    f"{confidence[k]:.2f}{how}): {why}")
                    confidence[k] = 0.0
                    continue
            if k in todo and confidence[k] > 0:
                neighbour = motions[k]
    bar.update()
    reduced = gain_fit_reference(ref) if halved is None else (halved[reference], gain_levels)  # once a burst
    for k in todo:
        if confidence[k] > 0:
            gain_offset[k] = fit_gain_offset(grey[k], ref, motions[k], reduced, None if halved is None else halved[k])
    local = None
    if start is not None:  # frames large enough for a pyramid are large enough to tile
        from hbis_torch.registration.local import local_offsets

        local = local_offsets(grey, reference, motions, gain_offset, [k for k in todo if confidence[k] > 0])
    bar.close()
    return BurstMotion(motions, confidence, models, gain_offset, messages, local)


def _register_pair(ref: torch.Tensor, frame: torch.Tensor, motion: str, neighbour: np.ndarray):
    """The best registration of ``frame`` to ``ref`` from up to four starts (phase correlation,
    the neighbour's motion, matched features' shift, then with their turn), trying the next while
    the best (:func:`fit_standing`) is below :data:`SETTLED_CONFIDENCE`.

    Returns (the :class:`~hbis_torch.registration.Registration` of the pair, a note on the start
    used, "" for phase correlation).
    """
    from hbis_torch.registration import ALL_MODELS, register_stack

    pair = torch.stack((ref, frame))
    shape = tuple(ref.shape)
    best, note = register_stack(pair, 0, model=motion, ladder=ALL_MODELS, motion_tolerance_px=MODEL_TOLERANCE_PX,
                                min_confidence=0.0), ""
    if motion == "auto" and best.model != "translation":
        best = _simplest_that_predicts(pair, best)
    features = {}  # the features' whole motion, matched once

    def matched(small_turn: bool):
        if "motion" not in features:
            features["motion"] = feature_start(ref.numpy(), frame.numpy(), small_turn=True)
        whole = features["motion"]
        plain = None if whole is None else _without_small_turn(whole, shape)
        if not small_turn:
            return plain
        return None if plain is whole else whole  # a small turn, tried once the shift alone failed

    starts = (("the neighbouring frame's motion", lambda: neighbour if not np.allclose(neighbour, np.eye(3)) else None),
              ("matched features", lambda: matched(False)),
              ("matched features with their turn", lambda: matched(True)))
    for name, start in starts:
        if fit_standing(best, shape) >= SETTLED_CONFIDENCE:
            break
        guess = start()
        if guess is None:
            continue
        again = register_stack(pair, 0, prediction=np.stack((np.eye(3), guess)), model=motion, ladder=ALL_MODELS,
                               motion_tolerance_px=MODEL_TOLERANCE_PX, min_confidence=0.0)
        if fit_standing(again, shape) > fit_standing(best, shape):
            # the fit refines the start's motion: a turned start and a shift on it is a turn
            model = max(again.model, model_of(guess), key=ALL_MODELS.index)
            best, note = replace(again, model=model), f", started from {name}"
    return best, note


def model_of(motion: np.ndarray) -> str:
    """The simplest model of :data:`~hbis_torch.registration.homography.ALL_MODELS` that holds
    ``motion`` (3, 3), to rounding."""
    m = motion / motion[2, 2]
    if np.abs(m[2, :2]).max() > 1e-12:
        return "homography"
    a = m[:2, :2]
    if np.abs(a - np.eye(2)).max() <= 1e-12:
        return "translation"
    if abs(a[0, 0] - a[1, 1]) <= 1e-12 and abs(a[0, 1] + a[1, 0]) <= 1e-12:
        return "similarity"
    return "affine"


def _simplest_that_predicts(pair: torch.Tensor, richer):
    """``richer`` (the ladder's pick, a :class:`~hbis_torch.registration.Registration` of the
    pair) or, where a translation predicts the frame from the reference as well, the translation.

    The ladder's test looks at the strongest gradients only, where on small aliased frames a
    richer model also fits the aliasing; the whole frame, predicted through each motion
    (:func:`prediction_error`), tells a real rotation or zoom from that.
    """
    from hbis_torch.registration import register_stack

    plain = register_stack(pair, 0, model="translation", min_confidence=0.0)
    if not bool(torch.isfinite(plain.homographies).all()):
        return richer
    simple_error = prediction_error(pair[0], pair[1], plain.homographies[1].numpy())
    rich_error = prediction_error(pair[0], pair[1], richer.homographies[1].numpy())
    return richer if rich_error < (1 - RICHER_GAIN) * simple_error else plain


def prediction_error(reference: torch.Tensor, frame: torch.Tensor, motion: np.ndarray) -> float:
    """RMS difference between ``frame`` (H, W) and the reference (H, W) resampled at the frame's
    pixels through ``motion`` (frame px -> reference px; Kornia, bicubic), after a least-squares
    gain and offset, over the pixels 3 px or more inside both, the worst quarter of them left out
    (a moving object or an occlusion); inf where fewer than 16 remain."""
    import kornia

    from hbis_torch.registration.evidence import trimmed_line_mse

    H, W = frame.shape
    # Both blurred first: on aliased frames the aliasing, not the motion, would dominate the error.
    reference, frame = kornia.filters.gaussian_blur2d(torch.stack((reference, frame))[:, None].float(), (5, 5),
                                                      (1.0, 1.0), border_type="replicate")[:, 0]
    to_frame = torch.as_tensor(np.linalg.inv(motion), dtype=torch.float32)[None]
    image = torch.stack((reference, torch.ones_like(reference)))[:, None].float()
    out = kornia.geometry.transform.warp_perspective(image, to_frame.expand(2, 3, 3), (H, W), mode="bicubic",
                                                     align_corners=True)[:, 0]
    valid = out[1] > 0.999
    valid[:3], valid[-3:], valid[:, :3], valid[:, -3:] = False, False, False, False
    if int(valid.sum()) < 16:
        return float("inf")
    return trimmed_line_mse(out[0][valid].double(), frame[valid].double()) ** 0.5


def overlap(motion: np.ndarray, shape) -> float:
    """Share of the reference frame (H, W) that a frame moved by ``motion`` (frame px ->
    reference px) covers, on a grid of every fourth pixel."""
    H, W = shape
    v, u = np.mgrid[0:H:4, 0:W:4].astype(np.float64)
    try:
        x, y, w = np.linalg.inv(motion) @ np.stack((u.ravel(), v.ravel(), np.ones(u.size)))
    except np.linalg.LinAlgError:
        return 0.0
    with np.errstate(divide="ignore", invalid="ignore"):
        fu, fv = x / w, y / w
    return float(np.mean((fu >= -0.5) & (fu <= W - 0.5) & (fv >= -0.5) & (fv <= H - 0.5)))


def burst_confidence(reg, shape, index: int = 1) -> float:
    """Confidence in [0, 1] of frame ``index`` of a registration (frames of ``shape`` (H, W);
    by default the second frame of a registered pair), for a burst.

    The scan registration's own confidence asks for 0.05 px (the Risley scan's sub-pixel steps
    are that fine); a burst's random sub-pixel offsets gain from samples good to a tenth of a pixel
    or so. So: ``exp(-(precision / 0.15 px)^2)``, times how well the aligned frames match:
    1 up to a residual of 0.3 frame standard deviations, 0 at 0.6 (another scene leaves about 0.7,
    i.e. a correlation of 0.75; noise and aliasing on the shared sequences leave 0.05 to 0.2);
    and by how much of the reference the frame covers (:func:`overlap`): 1 from
    :data:`FULL_OVERLAP` up, 0 at none (the fit compares only the points both frames see, so a
    motion wrong by a whole frame can look precise on the few it keeps).

    The burst's registrations keep every frame's own fit (``register_stack(...,
    min_confidence=0)``), which this judges: the scan's threshold would put a frame fitted to
    0.05 to 0.1 px back at its starting motion while its fit was judged here.
    """
    precision = float(reg.precision_px[index])
    residual = float(reg.residual[index])
    finite = np.isfinite(precision) and np.isfinite(residual)
    if not finite or not bool(torch.isfinite(reg.homographies[index]).all()):
        return 0.0
    match = float(np.clip((MATCH_RESIDUAL_ZERO - residual) / (MATCH_RESIDUAL_ZERO - MATCH_RESIDUAL_ONE), 0, 1))
    covered = min(1.0, overlap(reg.homographies[index].numpy(), shape) / FULL_OVERLAP)
    return float(np.exp(-(precision / BURST_PRECISION_PX) ** 2)) * match * covered


def fit_standing(reg, shape, index: int = 1) -> float:
    """:func:`burst_confidence`, halved where the fit did not converge: what decides whether a
    frame is fitted again from another start, and which start's fit it keeps (a start a turn away
    can leave a shift that fits the frame's centre and wanders). The frame's confidence stays
    :func:`burst_confidence` itself: on a small aliased frame a fit can wander at 0.01 px and be
    good."""
    converged = reg.converged is None or bool(reg.converged[index])
    return burst_confidence(reg, shape, index) * (1.0 if converged else 0.5)


def feature_start(reference: np.ndarray, frame: np.ndarray, small_turn: bool = False) -> np.ndarray | None:
    """A homography frame px -> reference px from ORB features and RANSAC (OpenCV), for motion
    beyond phase correlation's reach; None where too few features match.

    Parameters
    ----------
    reference, frame : np.ndarray, shape (H, W), float32 in [0, 1]
    small_turn : bool
        Keep a turn below 2 degrees and a zoom below 3 % too. By default such a start is its
        shift at the frame's centre (:func:`_without_small_turn`): what features say of so small
        a turn is mostly their noise on a small frame, and the fit finds it from there; on a large
        one a turn of 1.5 degrees moves the corners by 10 px, beyond the fit's reach from a shift.
    """
    try:
        import cv2
    except ImportError:  # the optional extra: the coarse start stays phase correlation
        return None
    scale = 4 if max(reference.shape) < 256 else 1  # ORB needs some 30 px around a keypoint
    def prepare(image):
        big = cv2.resize(image, None, fx=scale, fy=scale, interpolation=cv2.INTER_CUBIC)
        return np.clip(big * 255, 0, 255).astype(np.uint8)
    orb = cv2.ORB_create(nfeatures=1000, edgeThreshold=15, patchSize=15)
    kr, dr = orb.detectAndCompute(prepare(reference), None)
    kf, df = orb.detectAndCompute(prepare(frame), None)
    if dr is None or df is None or len(kr) < 8 or len(kf) < 8:
        return None
    matches = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True).match(df, dr)
    if len(matches) < 8:
        return None
    src = np.float32([kf[m.queryIdx].pt for m in matches])
    dst = np.float32([kr[m.trainIdx].pt for m in matches])
    cv2.setRNGSeed(0)  # RANSAC draws from OpenCV's global generator: the same burst, the same start, every run
    matrix, inliers = cv2.estimateAffinePartial2D(src, dst, method=cv2.RANSAC, ransacReprojThreshold=3.0 * scale)
    if matrix is None or int(inliers.sum()) < 6:
        return None
    # OpenCV's pixel centres are at integers too; undo the enlargement: (x + 0.5) * s - 0.5.
    up = np.array([[scale, 0, (scale - 1) / 2], [0, scale, (scale - 1) / 2], [0, 0, 1.0]])
    start = np.linalg.inv(up) @ np.vstack((matrix, [0, 0, 1])) @ up
    return start if small_turn else _without_small_turn(start, reference.shape)


def _without_small_turn(motion: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """``motion`` itself where it turns by 2 degrees or more or zooms by 3 % or more, else the
    translation that moves the centre of a frame of ``shape`` (H, W) as it does."""
    zoom, angle = np.hypot(motion[0, 0], motion[1, 0]), np.degrees(np.arctan2(motion[1, 0], motion[0, 0]))
    if abs(zoom - 1) >= 0.03 or abs(angle) >= 2:
        return motion
    H, W = shape
    centre = np.array([(W - 1) / 2, (H - 1) / 2, 1.0])
    moved = motion @ centre
    out = np.eye(3)
    out[:2, 2] = moved[:2] / moved[2] - centre[:2]
    return out


def assemble_burst(frames: np.ndarray, scale: int, reference: int | str = 0, motion: str = "auto", roi=None,
                   bit_depth: int | None = None, names: list | None = None,
                   calibration=None) -> tuple[Stack, list]:
    """Build and validate a burst stack from captured frames.

    Parameters
    ----------
    frames : np.ndarray, shape (F, H, W) or (F, H, W, 3)
        uint8, uint16 or float32 (in [0, 1]), in capture order; F >= 2.
    scale : int
        Output scale S (1..16): the reconstruction refines the reference grid S times.
    reference : int or "sharpest"
        The frame whose grid the output refines, or the sharpest frame
        (:func:`~hbis_torch.capture.sharpness.choose_reference`, which also names a given
        reference that is clearly blurred).
    motion : str
        One of :data:`MOTIONS`.
    roi : (u0, v0, width, height) or None
        Cut the frames to this rectangle first. None: whole frames, less any still black bands at
        their edges (a letterbox; :mod:`hbis_torch.capture.borders`), which a message names.
    bit_depth : int or None
        Significant bits of integer frames (default: the dtype's).
    names : list of str, optional
        Where each frame came from (for messages).
    calibration : hbis_torch.capture.calibration.FrameCalibration, optional
        Dark frame, flat field and bad-pixel map, of the frames' size as captured (or as cut):
        the frames are corrected first (float32), and the bad pixels are filled and given no
        weight, as stuck pixels are.

    Returns
    -------
    stack : Stack
    messages : list of str
    """
    captured = np.shape(frames)[1:3]
    cut = [] if roi is not None else None  # (no roi: the frames are cut to their picture, if banded)
    frames, roi = check_burst_input(frames, scale, reference, motion, roi, bit_depth)
    if cut is None:
        frames, roi, cut = _inside_bands(frames, bit_depth)
    bad_at, calibrated = np.zeros((0, 2), int), []
    if calibration:
        frames, bad_at, calibrated = _calibrated(frames, calibration, roi, captured, bit_depth)
        bit_depth = None  # (it described the raw numbers)
    grey = luminance(frames)
    if bit_depth is not None and frames.dtype != np.float32:
        grey.mul_((2 ** (frames.dtype.itemsize * 8) - 1) / (2 ** bit_depth - 1))
    given = reference != SHARPEST
    reference, messages = (reference, []) if given else choose_reference(grey, reference)
    found = register_burst(grey, reference, motion, names)
    frames, stuck_at, stuck = without_stuck_pixels(frames, grey.numpy(), reference, found.motions,
                                                   found.confidence >= BURST_MIN_CONFIDENCE)
    if given:  # compared with the frames that register: another scene's sharpness says nothing of it
        _, messages = choose_reference(grey, reference, found.confidence >= BURST_MIN_CONFIDENCE)
    messages += cut + calibrated + found.messages + stuck
    hint = bit_depth_hint(frames) if bit_depth is None else None
    if hint is not None:
        messages.append(hint)
    if all(m == "identity" for m in found.models):
        messages.append(act(f"all {len(frames)} frames are identical to the reference: the burst holds no new "
                            "samples (its reconstruction is the single-frame estimate); capture it again, moving "
                            "the camera a little between frames"))
    meta = make_burst_meta(scale, roi, found.motions, found.confidence, found.models, found.gain_offset,
                           reference_index=reference, bit_depth=bit_depth)
    unusable = np.unique(np.concatenate([bad_at, stuck_at]), axis=0)
    if len(unusable):  # filled in the frames, and given no weight by the reconstruction
        meta["stuck_pixels"] = unusable.tolist()
    if calibration:
        meta["calibration"] = {**calibration.names, "bad_pixel_count": len(bad_at)}
    if found.local is not None:  # plain lists already: set here, not walked value by value by make_burst_meta
        from hbis_torch.registration.local import TILE_PX

        meta["local_motion"] = {"tile_px": TILE_PX, "offsets": found.local.round(5).tolist()}
    frames = np.ascontiguousarray(frames)
    validate_stack(frames, meta, "assembled burst")
    return Stack(frames, meta), messages


def _calibrated(frames: np.ndarray, calibration, roi, captured, bit_depth: int | None):
    """The frames corrected by ``calibration``
    (:func:`~hbis_torch.capture.calibration.calibrate_frames`), the bad pixels ((N, 2) row,
    column) and the line that says what was applied."""
    from hbis_torch.capture.calibration import calibrate_frames

    if frames.dtype == np.float32:
        white = 1.0
    else:
        white = 2 ** (frames.dtype.itemsize * 8 if bit_depth is None else int(bit_depth)) - 1
    frames, bad = calibrate_frames(frames, calibration, roi, captured, white)
    bad_at = np.argwhere(bad)
    applied = [f"{what} {calibration.names[key]}" for key, what in (("dark", "dark frame"), ("flat", "flat field"),
                                                                    ("bad_pixels", "bad-pixel map"))
               if key in calibration.names]
    line = f"calibrated with the {', the '.join(applied)}"
    if len(bad_at):
        line += f": {len(bad_at)} bad pixel(s) filled from their neighbours and given no weight"
    return frames, bad_at, [line]


def _inside_bands(frames: np.ndarray, bit_depth: int | None) -> tuple[np.ndarray, tuple, list]:
    """Whole frames cut to the picture inside still black bands at their edges
    (:func:`~hbis_torch.capture.borders.picture_inside_bands`), if the picture is large enough to
    register: (frames, roi, the message that says so, or none)."""
    from hbis_torch.capture.borders import picture_inside_bands

    height, width = frames.shape[1:3]
    if frames.dtype == np.float32:
        white = 1.0
    else:  # the bits the values use, where not given (a 10-bit camera in a 16-bit file: 1023)
        white = 2 ** (max(int(frames.max()).bit_length(), 1) if bit_depth is None else int(bit_depth)) - 1
    picture = picture_inside_bands(frames, white)
    if picture is None or min(picture[2:]) < MIN_BURST_PX:
        return frames, (0, 0, width, height), []
    u0, v0, w, h = picture
    bands = [f"{n} px at the {side}" for n, side in ((v0, "top"), (height - v0 - h, "bottom"), (u0, "left"),
                                                     (width - u0 - w, "right")) if n]
    line = act(f"the frames have still black bands ({', '.join(bands)}): the burst is cut to the picture inside "
               f"them, {w} x {h} px at ({u0}, {v0}), and the output covers it alone; --roi 0,0,{width},{height} "
               "keeps the whole frames")
    return frames[:, v0:v0 + h, u0:u0 + w], picture, [line]


def check_burst_input(frames, scale, reference, motion, roi, bit_depth) -> tuple[np.ndarray, tuple]:
    """Every check of :func:`assemble_burst`'s arguments, before any work: the frames (cut to
    ``roi``) and the roi."""
    from hbis_torch.checks import MAX_H

    frames = np.asarray(frames)
    if frames.ndim not in (3, 4) or (frames.ndim == 4 and frames.shape[-1] != 3):
        raise HbisInputError(f"burst frames must have shape (F, H, W) or (F, H, W, 3), got {frames.shape}")
    if not 2 <= len(frames) <= MAX_BURST_FRAMES:
        raise HbisInputError(f"a burst needs 2 to {MAX_BURST_FRAMES} frames, got {len(frames)}")
    if isinstance(scale, bool) or not isinstance(scale, (int, np.integer)) or not 1 <= scale <= MAX_H:
        raise HbisInputError(f"--scale must be an integer from 1 to {MAX_H}, got {scale!r}")
    if reference != SHARPEST and (isinstance(reference, bool) or not isinstance(reference, (int, np.integer))
                                  or not 0 <= reference < len(frames)):
        raise HbisInputError(f"--reference {reference!r} is neither a frame index (0..{len(frames) - 1}) "
                             f"nor '{SHARPEST}'")
    if motion not in MOTIONS:
        raise HbisInputError(f"--motion must be one of {', '.join(MOTIONS)}, got {motion!r}")
    height, width = frames.shape[1:3]
    if roi is None:
        roi = (0, 0, width, height)
    u0, v0, w, h = (int(r) for r in roi)
    if w < 1 or h < 1 or u0 < 0 or v0 < 0 or u0 + w > width or v0 + h > height:
        raise HbisInputError(f"--roi {list(roi)} lies outside the {width} x {height} frames")
    frames = frames[:, v0:v0 + h, u0:u0 + w]
    if min(h, w) < MIN_BURST_PX:
        raise HbisInputError(f"burst frames of {w} x {h} px are too small to register "
                             f"(at least {MIN_BURST_PX} x {MIN_BURST_PX})")
    if frames.dtype not in (np.uint8, np.uint16, np.float32):
        raise HbisInputError(f"frame dtype {frames.dtype} is not one of uint8, uint16, float32")
    if frames.dtype == np.float32 and (not np.isfinite(frames).all() or frames.min() < 0 or frames.max() > 1):
        raise HbisInputError("float32 frames must be finite and lie in [0, 1]")
    if bit_depth is not None:
        container = 32 if frames.dtype == np.float32 else frames.dtype.itemsize * 8
        if frames.dtype == np.float32 or not 1 <= int(bit_depth) <= container:
            raise HbisInputError(f"bit depth {bit_depth} does not fit {frames.dtype} frames")
        if int(frames.max()) > 2 ** int(bit_depth) - 1:
            raise HbisInputError(f"pixel values reach {int(frames.max())}, more than {bit_depth} bits hold")
    return frames, (u0, v0, w, h)
