"""The held-out raw matrix's bursts: colour photographs, [handheld]'s motions, a Bayer mosaic and
raw shot and read noise, against the truth.

A cell is a photograph x a Bayer pattern x a light level x S (:func:`make_raw_burst`): the
photograph (linear camera RGB, by assumption) is resized onto the output grid (anti-aliased), each
frame pixel averages it over its footprint through the frame's motion
(:func:`hbis_torch.training.heldout_burst.motions_for`, the condition "12 frames, shifts to 1.5
px" by default), keeps the colour of its pattern position, and records electrons (Poisson at the
light level's full well, plus Gaussian read noise), quantised to 12 bits over a black level of 256
in a 16-bit container (white level 4095). training/eval_raw.py scores the reconstructions.
"""

from __future__ import annotations

import dataclasses
import sys

import numpy as np

from hbis_torch.sensor.cfa import mosaic
from hbis_torch.training.heldout_burst import BurstCondition, _pixel_average, motions_for

BLACK, WHITE = 256, 4095
#: Light levels: (name, electrons at the white level, read noise in electrons).
LIGHT_LEVELS = (("bright", 20_000.0, 2.0), ("indoor", 2_000.0, 4.0), ("dim", 300.0, 6.0))
RAW_PHOTOS = ("astronaut", "coffee", "chelsea", "rocket")
PATTERNS = ("RGGB", "BGGR", "GRBG", "GBRG")


@dataclasses.dataclass
class RawBurst:
    """One cell's frames and truth.

    Attributes
    ----------
    mosaics : np.ndarray, shape (F, size, size), uint16
    truth : np.ndarray, shape (S size, S size, 3), float32 in [0, 1]
        Camera RGB on the reference's output grid.
    motions : np.ndarray, shape (F, 3, 3)
        The true motions, frame px -> reference px.
    noise : np.ndarray, shape (3, 2)
        The true variance ``S x + O`` of a normalised sample, per colour.
    raw : dict
        A stack's ``raw`` block for these frames (levels, no colour matrix).
    """

    mosaics: np.ndarray
    truth: np.ndarray
    motions: np.ndarray
    noise: np.ndarray
    raw: dict


def truth_rgb(photo_name: str, scale: int, size: int) -> np.ndarray:
    """A colour photograph's centre resized (anti-aliased) onto the output grid, (S size, S size, 3)
    float64 in [0, 1]."""
    import skimage.data
    from skimage.transform import resize

    image = getattr(skimage.data, photo_name)()[..., :3].astype(np.float64) / 255.0
    side = min(min(image.shape[:2]), int(round(1.5 * scale * size)))
    y0, x0 = (image.shape[0] - side) // 2, (image.shape[1] - side) // 2
    return resize(image[y0:y0 + side, x0:x0 + side], (scale * size, scale * size, 3), anti_aliasing=True)


def make_raw_burst(photo_name: str, cfa: str, light: str, scale: int, size: int, seed: int,
                   condition: BurstCondition | None = None, motion: str | None = None) -> RawBurst:
    """The raw frames and truth of one cell (module docstring).

    Parameters
    ----------
    photo_name : str
        One of :data:`RAW_PHOTOS`.
    cfa : str
    light : str
        A name of :data:`LIGHT_LEVELS`.
    scale : int
    size : int
        Side of the frames, px (even).
    seed : int
    condition : BurstCondition, optional
        The motion (frames, shifts, rotation, zoom); default 12 frames, shifts to 1.5 px.
    motion : str, optional
        Instead of the condition's motion, [handheld]'s renderer's
        (:func:`hbis_torch.training.handheld_render.draw_motion`): ``"translation"``,
        ``"similarity"`` or ``"homography"`` (its homographies only; the condition still gives
        the number of frames).
    """
    cond = condition or BurstCondition("raw", frames=12)
    full_well, read = {name: (fw, rn) for name, fw, rn in LIGHT_LEVELS}[light]
    rng = np.random.default_rng(seed)
    truth = truth_rgb(photo_name, scale, size)
    if motion is None:
        motions = motions_for(cond, size, rng)
    else:
        from hbis_torch.training.handheld_render import draw_motion

        if motion not in ("translation", "similarity", "homography"):
            raise ValueError(f"motion must be translation, similarity or homography, got {motion!r}")
        motions = draw_motion(motion, cond.frames, size, size, rng)[0]
    span = WHITE - BLACK
    frames = []
    for motion in motions:
        rgb = np.stack([_pixel_average(truth[..., c], motion, scale, size) for c in range(3)], -1)
        signal = mosaic(rgb, cfa)
        electrons = rng.poisson(np.clip(signal, 0, None) * full_well) + rng.normal(0, read, signal.shape)
        level = np.clip(np.round(BLACK + electrons / full_well * span), 0, WHITE)
        frames.append(level.astype(np.uint16))
    # variance of a normalised sample: x / full_well (shot) + (read / full_well)^2 + quantisation
    noise = np.tile([1.0 / full_well, (read / full_well) ** 2 + 1 / (12 * span ** 2)], (3, 1))
    F = len(frames)
    raw = {"black": np.full((F, 2, 2), float(BLACK)).tolist(), "white": [float(WHITE)] * F, "gain": [1.0] * F,
           "white_balance": [1.0, 1.0, 1.0], "colour_matrix": np.eye(3).tolist(), "orientation": 0,
           "camera": "simulated", "exposure_s": None, "iso": None, "noise_profile": None, "clip_level": 0.99}
    return RawBurst(np.stack(frames), truth.astype(np.float32), motions, noise, raw)


def provenance() -> dict:
    """Where a result came from: the command line, the checkout's commit and whether its tracked
    files were changed, the date (UTC) and the machine (for training/eval_raw.py and
    benchmarks/bench_raw_burst.py; the project-wide helper may replace it)."""
    import os
    import platform
    import subprocess
    from datetime import datetime, timezone
    from pathlib import Path

    root = Path(__file__).resolve().parents[2]

    def git(*args):
        try:
            return subprocess.run(["git", "-C", str(root), *args], capture_output=True, text=True,
                                  timeout=30).stdout.strip()
        except (OSError, subprocess.SubprocessError):
            return ""
    return {"command": " ".join(["python", *sys.argv]), "commit": git("rev-parse", "HEAD"),
            "dirty": bool(git("status", "--porcelain", "--untracked-files=no")),
            "date": datetime.now(timezone.utc).isoformat(timespec="seconds"),
            "machine": f"{platform.node()} {platform.machine()}, {os.cpu_count()} CPUs (shared)"}
