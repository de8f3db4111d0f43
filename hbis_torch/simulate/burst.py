"""Simulated bursts with known motion: frames of a freely moving camera, for tests and benchmarks.

An image on the output grid (the truth, S times the frames' resolution) is seen by a camera that
moves a little between frames: frame k's pixel (u, v) integrates the truth over the pixel's area
around the reference position ``H_k (u, v)`` (a box of S x S output pixels, then a sample at that
position, cubic spline). Optionally a patch moves on its own (a moving object) in some frames.
Noise is Gaussian, frames are quantised to 8 bits.

Conventions are the burst stack's (docs/design.md section 3): motions (F, 3, 3) float64 map frame
px -> reference px; the output grid's pixel (U, V) sits at LR position ((U + 0.5) / S - 0.5,
(V + 0.5) / S - 0.5).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class SimulatedBurst:
    """A burst and its truth.

    Attributes
    ----------
    frames : np.ndarray, shape (F, H, W), uint8
    motions : np.ndarray, shape (F, 3, 3), float64
        The true homographies, frame px -> reference px (identity for frame 0, the reference).
    truth : np.ndarray, shape (S H, S W), float32 in [0, 1]
        What the reference frame's grid refined S times shows.
    moving : np.ndarray, shape (F,), bool
        Frames in which the moving patch is displaced.
    """

    frames: np.ndarray
    motions: np.ndarray
    truth: np.ndarray
    moving: np.ndarray


def random_motions(count: int, shape, rng, max_shift: float = 1.5, max_rotation_deg: float = 0.0,
                   max_zoom: float = 0.0) -> np.ndarray:
    """(count, 3, 3) similarity motions about the frame's centre, frame 0 the identity."""
    H, W = shape
    c = np.array([[1, 0, (W - 1) / 2], [0, 1, (H - 1) / 2], [0, 0, 1.0]])
    motions = [np.eye(3)]
    for _ in range(count - 1):
        a = np.deg2rad(rng.uniform(-max_rotation_deg, max_rotation_deg))
        z = 1 + rng.uniform(-max_zoom, max_zoom)
        t = rng.uniform(-max_shift, max_shift, 2)
        m = np.array([[z * np.cos(a), -z * np.sin(a), t[0]], [z * np.sin(a), z * np.cos(a), t[1]], [0, 0, 1]])
        motions.append(c @ m @ np.linalg.inv(c))
    return np.stack(motions)


def simulate_burst(truth: np.ndarray, scale: int, motions: np.ndarray, noise: float = 0.01, seed: int = 0,
                   moving_patch: tuple | None = None, moving_frames=(), gains=None,
                   blur_px: float = 0.0) -> SimulatedBurst:
    """Render the frames of a burst of ``truth`` seen through ``motions``.

    Parameters
    ----------
    truth : np.ndarray, shape (S H, S W), float in [0, 1]
        The scene on the output grid.
    scale : int
        S.
    motions : np.ndarray, shape (F, 3, 3)
        Frame px -> reference px (frame 0 should be the identity).
    noise : float
        Standard deviation of the Gaussian noise, in [0, 1] units.
    seed : int
    moving_patch : (v0, u0, size, dv, du) or None
        A square of the truth (output px) that, in ``moving_frames``, is shown displaced by
        (dv, du) output px (a moving object).
    moving_frames : sequence of int
    gains : sequence of (g, o), optional
        Per frame, the frame shows ``g * scene + o`` (a brightness change).
    blur_px : float
        Standard deviation of a Gaussian lens blur, LR px, applied to the scene before the pixel
        area (the truth stays sharp: the lens is what the reconstruction undoes).

    Returns
    -------
    SimulatedBurst
    """
    from scipy.ndimage import gaussian_filter, map_coordinates, uniform_filter

    truth = np.asarray(truth, dtype=np.float64)
    rng = np.random.default_rng(seed)
    H, W = truth.shape[0] // scale, truth.shape[1] // scale
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    frames, moving = [], np.zeros(len(motions), dtype=bool)
    for k, m in enumerate(motions):
        scene = truth
        if moving_patch is not None and k in moving_frames:
            scene = _moved(truth, moving_patch)
            moving[k] = True
        if blur_px > 0:
            scene = gaussian_filter(scene, blur_px * scale, mode="nearest")
        area = uniform_filter(scene, scale, mode="nearest")  # the pixel's area, S x S output px
        x, y, w = (m @ np.stack((u.ravel(), v.ravel(), np.ones(u.size))))
        ur, vr = (x / w).reshape(H, W), (y / w).reshape(H, W)
        # An even box's value at index i is centred on output px i - 0.5: sample half a pixel on.
        shift = 0.5 if scale % 2 == 0 else 0.0
        U, V = scale * (ur + 0.5) - 0.5 + shift, scale * (vr + 0.5) - 0.5 + shift
        frame = map_coordinates(area, [V, U], order=3, mode="nearest")
        if gains is not None:
            frame = gains[k][0] * frame + gains[k][1]
        frame = frame + rng.normal(0, noise, frame.shape)
        frames.append(np.clip(np.round(frame * 255), 0, 255).astype(np.uint8))
    return SimulatedBurst(np.stack(frames), np.asarray(motions, dtype=np.float64),
                          truth.astype(np.float32), moving)


def _moved(truth: np.ndarray, patch: tuple) -> np.ndarray:
    v0, u0, size, dv, du = patch
    out = truth.copy()
    out[v0 + dv:v0 + dv + size, u0 + du:u0 + du + size] = truth[v0:v0 + size, u0:u0 + size]
    return out
