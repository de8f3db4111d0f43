"""Coarse-to-fine registration: the whole frame's motion on a Gaussian pyramid.

Lucas-Kanade converges from a start within a pixel or two of the answer. A hand-held burst of
real size turns by tenths of a degree, which moves a 640 x 480 frame's corners by several
pixels while its centre barely moves, so no translation start (phase correlation) is within
reach. Halving the frames until they are small brings every motion within reach at the coarsest
level; each finer level then starts from the coarser one's answer, where it is off by about a
pixel of that level (Bouguet's pyramidal Lucas-Kanade [1]_; Baker and Matthews' fitter at each
level, :func:`~hbis_torch.registration.register_stack`). The coarsest level starts from several
phase-correlation peaks and keeps the motion most of the frame follows (:func:`dominant_motion`),
so a moving object's sharper peak does not take the burst with it.

Frames are (F, H, W) float32; homographies (F, 3, 3) float64 map frame px -> reference px, pixel
centres at integers (:mod:`.homography`).

References
----------
.. [1] J.-Y. Bouguet, "Pyramidal implementation of the Lucas Kanade feature tracker", Intel
   Corporation, Microprocessor Research Labs, 2000.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from hbis_torch.registration.homography import ALL_MODELS

#: The coarsest level's shorter side is at least this (px): small enough that a burst's motion
#: is within a pixel or two there, large enough that the fit has texture to work with.
COARSEST_SIDE = 64
#: Levels this many halvings or more below the finest are fitted as similarities at most: a few
#: thousand pixels do not pin down a perspective, while rotation and zoom they do.
SIMILARITY_LEVELS = 2
#: The coarsest level's fit starts from this many phase-correlation peaks, and keeps per frame the
#: one that explains most of the frame (:func:`dominant_motion`).
START_PEAKS = 3
#: Another peak's fit replaces the strongest peak's only where its robust residual is below this
#: share of the strongest's: fits from two peaks in the same basin differ by rounding, a fit
#: locked onto a moving object leaves a residual many times the background's.
DOMINANCE = 0.8


def levels_for(shape: tuple[int, int]) -> int:
    """How many halvings a frame of ``shape`` (H, W) takes to reach the coarsest level (0 for
    frames whose shorter side is under twice :data:`COARSEST_SIDE`)."""
    side, levels = min(shape), 0
    while side // 2 >= COARSEST_SIDE:
        side //= 2
        levels += 1
    return levels


def level_matrix(level: int) -> np.ndarray:
    """(3, 3): full-resolution px -> px of the pyramid level ``level`` (each halving averages
    2 x 2 pixels, so a centre x becomes (x + 0.5) / 2 - 0.5)."""
    s = 2.0 ** -level
    return np.array([[s, 0.0, (s - 1) / 2], [0.0, s, (s - 1) / 2], [0.0, 0.0, 1.0]])


def to_level(homographies: np.ndarray, level: int) -> np.ndarray:
    """Homographies (F, 3, 3) between full-resolution frames, expressed on level ``level``."""
    d = level_matrix(level)
    return d @ homographies @ np.linalg.inv(d)


def from_level(homographies: np.ndarray, level: int) -> np.ndarray:
    """The inverse of :func:`to_level`."""
    d = level_matrix(level)
    return np.linalg.inv(d) @ homographies @ d


def pyramid(frames: Tensor, levels: int) -> list[Tensor]:
    """[frames, frames halved, ...], ``levels + 1`` entries, (F, H / 2^l, W / 2^l) each.

    Each halving averages 2 x 2 pixels (an odd last row or column is dropped), which is the
    pixel-centre convention of :func:`level_matrix`; the fit blurs every level by its own
    Gaussian, so no further anti-aliasing is needed (with Kornia's 5-tap ``pyrdown`` the
    assemble of 16 frames of 640 x 480 took 2.06 CPU s, with this 1.68 s, on one thread)."""
    out = [frames]
    for _ in range(levels):
        out.append(torch.nn.functional.avg_pool2d(out[-1][:, None], 2)[:, 0])
    return out


def project(homographies: np.ndarray, model: str, shape: tuple[int, int]) -> np.ndarray:
    """The motion of ``model`` nearest each homography (F, 3, 3): least squares over a grid of
    the frame's (``shape`` (H, W)) points. Translation, similarity and affine are closed under
    composition, so a fit started from the projection stays in its model."""
    if model == "homography":
        return np.array(homographies, dtype=np.float64)
    H, W = shape
    v, u = np.meshgrid(np.linspace(0, H - 1, 9), np.linspace(0, W - 1, 9), indexing="ij")
    src = np.stack((u.ravel(), v.ravel(), np.ones(u.size)))  # (3, N)
    c = np.array([(W - 1) / 2, (H - 1) / 2])
    out = np.repeat(np.eye(3)[None], len(homographies), 0)
    for k, m in enumerate(homographies):
        dst = m @ src
        dst = (dst[:2] / dst[2]).T - c  # (N, 2), centred
        x, y = src[0] - c[0], src[1] - c[1]
        if model == "translation":
            out[k, :2, 2] = (dst - np.stack((x, y), -1)).mean(0)
        elif model == "similarity":  # [a -b; b a] (x, y) + t
            one, zero = np.ones_like(x), np.zeros_like(x)
            A = np.concatenate((np.stack((x, -y, one, zero), -1), np.stack((y, x, zero, one), -1)))
            a, b, tx, ty = np.linalg.lstsq(A, dst.T.ravel(), rcond=None)[0]
            out[k, :2] = [[a, -b, tx], [b, a, ty]]
        elif model == "affine":
            A = np.stack((x, y, np.ones_like(x)), -1)
            out[k, :2] = np.linalg.lstsq(A, dst, rcond=None)[0].T
        else:
            raise ValueError(f"unknown model {model!r}")
        centre = np.array([[1, 0, c[0]], [0, 1, c[1]], [0, 0, 1.0]])
        out[k] = centre @ out[k] @ np.linalg.inv(centre)
    return out


def coarse_to_fine(frames: Tensor, reference: int, model: str = "homography", start: np.ndarray | None = None,
                   keep_levels: int = 1, images: list[Tensor] | None = None) -> np.ndarray:
    """Every frame's motion to the reference, fitted on a pyramid from the coarsest level down.

    Parameters
    ----------
    frames : Tensor, shape (F, H, W), float32
    reference : int
    model : str
        The richest model fitted (one of :data:`~.homography.ALL_MODELS`); the coarsest
        levels fit at most a similarity (:data:`SIMILARITY_LEVELS`).
    start : np.ndarray, shape (F, 3, 3), optional
        Where the coarsest level starts (default: phase correlation there).
    keep_levels : int
        Stop above this many of the finest levels (1: the full resolution is left to the
        caller's own fit, which starts from the answer).
    images : list of Tensor, optional
        ``pyramid(frames, levels_for((H, W)))``, where the caller builds it (to read a level of
        it itself); built here otherwise.

    Returns
    -------
    np.ndarray, shape (F, 3, 3), float64, or None
        Frame px -> reference px at full resolution; None (and no work) where the frames are
        too small for a pyramid down to ``keep_levels`` and no ``start`` was given.
    """
    from hbis_torch.registration.stack import register_stack

    F, H, W = frames.shape
    levels = levels_for((H, W))
    motions = None if start is None else np.array(start, dtype=np.float64)
    if levels < keep_levels:
        return motions
    images = pyramid(frames, levels) if images is None else images
    for level in range(levels, keep_levels - 1, -1):
        fitted = model
        if level >= SIMILARITY_LEVELS and ALL_MODELS.index(model) > ALL_MODELS.index("similarity"):
            fitted = "similarity"
        if motions is None:
            found = dominant_motion(images[level], reference, fitted)
        else:
            prediction = project(to_level(motions, level), fitted, images[level].shape[1:])
            prediction[reference] = np.eye(3)
            found = register_stack(images[level], reference, prediction=prediction, model=fitted).homographies.numpy()
        motions = from_level(found, level)
    motions[reference] = np.eye(3)
    return motions


def dominant_motion(frames: Tensor, reference: int, model: str, peaks: int = START_PEAKS) -> np.ndarray:
    """Every frame's motion (F, 3, 3) float64 to the reference, fitted from each of the ``peaks``
    strongest phase-correlation peaks; per frame, the trusted fit with the smallest robust
    residual.

    The whole frame's motion is the one most of the frame follows. A moving object that only
    translates can give phase correlation a sharper peak than a background that also turns (the
    turn smears the background's peak), and a fit started there locks onto the object; the
    background's fit leaves a smaller robust residual scale, since most pixels agree with it
    (smaller by :data:`DOMINANCE` at least, else the strongest peak's fit is kept). A frame that no
    peak brings within the model's reach is fitted again as a translation first, then as the
    model, from each peak, from no motion and from the nearest trusted frame's motion (a hand
    moves a burst's frames by a few pixels, the background's peak can be too smeared to rank).
    """
    from hbis_torch.registration.phase_correlation import _translation, phase_correlation_peaks

    shifts = phase_correlation_peaks(frames, frames[reference], peaks).double()  # (F, peaks, 2)
    starts = torch.stack([_translation(shifts[:, j]) for j in range(peaks)], 1)  # (F, peaks, 3, 3)
    found, score = _fits_from(frames, reference, starts, (model,))
    trusted = np.isfinite(score).any(0)
    trusted[reference] = True
    first = found[0].copy()  # where nothing is trusted, the strongest peak's fit, as a single start gave
    if not trusted.all():
        stuck = np.flatnonzero(~trusted)
        index = np.concatenate(([reference], stuck))
        known = np.flatnonzero(trusted)
        nearest = known[np.abs(stuck[:, None] - known[None]).argmin(1)]  # each stuck frame's nearest trusted one
        neighbour = torch.as_tensor(_choose(found, score)[np.concatenate(([reference], nearest))])
        still = torch.eye(3, dtype=torch.float64).expand(len(index), 3, 3)
        more = torch.cat((starts[index], torch.stack((still, neighbour), 1)), 1)  # (1 + stuck, peaks + 2, 3, 3)
        again, again_score = _fits_from(frames[index], 0, more, ("translation", model))
        found = np.concatenate((found, np.repeat(found[:1], 2, 0)))
        score = np.concatenate((score, np.full((2, score.shape[1]), np.inf)))
        found[:, stuck], score[:, stuck] = again[:, 1:], again_score[:, 1:]
    out = _choose(found, score)
    untrusted = np.isinf(score).all(0)
    out[untrusted] = first[untrusted]
    out[reference] = np.eye(3)
    return out


def _choose(found: np.ndarray, score: np.ndarray) -> np.ndarray:
    """Per frame, the fit (of ``found`` (P, F, 3, 3)) whose score (P, F) is smallest, unless the
    first's is within :data:`DOMINANCE` of it; (F, 3, 3)."""
    best = np.argmin(score, 0)
    frame = np.arange(len(best))
    best[~(score[best, frame] < DOMINANCE * score[0])] = 0
    return found[best, frame]


def _fits_from(frames: Tensor, reference: int, starts: Tensor, models: tuple[str, ...]):
    """From each start (F, P, 3, 3), the fit of ``models`` one after another, each from the last.

    Returns the homographies (P, F, 3, 3) and each fit's robust residual, infinite where the
    fit is not trusted (P, F).
    """
    from hbis_torch.registration.stack import register_stack

    found, score = [], []
    for j in range(starts.shape[1]):
        motion = starts[:, j].clone()
        for model in models:
            motion[reference] = torch.eye(3, dtype=torch.float64)
            reg = register_stack(frames, reference, prediction=motion, model=model)
            motion = reg.homographies
        found.append(motion.numpy())
        score.append(torch.where(reg.ok, torch.nan_to_num(reg.residual, nan=torch.inf), torch.inf).numpy())
    return np.stack(found), np.stack(score)
