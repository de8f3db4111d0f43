"""Training data for the SR network: simulated scans, cut into patches.

A *pool* is a list of simulated stacks (hbis_torch.simulate.simulate_stack, the project's physical
forward model: exact Risley geometry, Airy PSF, pixel aperture, shot and read noise, 12-bit ADC)
of procedural scenes (words, texture, edges, bars, Siemens stars, gradients) and of procedural
*natural-image* rasters (dead leaves and 1/f^2 random fields, see :func:`natural_image`) at
random places on the sensor, so that the network sees the off-grid shifts of the sensor's
corners as well as its centre. Photographs are *not* used for training: they are the held-out
test of the benchmark.

Training examples are random crops of pool stacks under the 8 flips/transposes of the square.
Flipping a stack is a valid new scan: the crop's sample positions are flipped with it and
:func:`~hbis_torch.reconstruct.learned.prepare_inputs` finds the new registered order from them.

This is the project's one training-data pipeline (training/train_sr.py, the tests and
benchmarks/bench_simulate.py use it):

1. :func:`draw_example` makes every random choice of pool example ``seed`` (cheap: nothing is
   simulated), :func:`simulate_example` renders it, and :func:`build_pool` makes a pool of
   examples whose seeds come from one pool seed and the example's index (:func:`example_seed`),
   so example i of a pool is the same whichever process builds it;
2. :func:`save_pool` / :func:`load_pool` cache a pool as one .npz;
3. :func:`make_batch` cuts a batch of random crops (:func:`crop_example`, :func:`dihedral`) in the
   network's input layout; :func:`whole_example` gives a whole example as a batch of one.

All randomness comes from the seeds and generators passed in: the same seeds give the same pools
and batches, bit for bit.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from hbis_torch.config import FoveaSystem
from hbis_torch.errors import HbisInputError
from hbis_torch.io_utils import atomic_path
from hbis_torch.reconstruct.learned import prepare_inputs
from hbis_torch.scan import plan_scan
from hbis_torch.simulate import (
    SceneSpec,
    SensorModel,
    load_scene,
    sample_positions,
    simulate_stack,
)
from hbis_torch.simulate.rasters import texture_image
from hbis_torch.simulate.scenes import ImageScene

NATURAL_SCENES = ("dead-leaves", "natural-field")
TRAIN_SCENES = ("words", "texture", "edges", "bars", "siemens-star", "gradient", "slanted-edge") + NATURAL_SCENES
SCENE_WEIGHTS = (0.2, 0.15, 0.1, 0.05, 0.05, 0.05, 0.05, 0.2, 0.15)
NATURAL_SHARE = 0.35  # of SCENE_WEIGHTS: the natural scenes' share of the standard mix
FULL_WELL_E = (2000.0, 30000.0)  # full well range of the examples' sensors, electrons (log-uniform)
POOL_KEYS = ("frames", "positions", "truth", "roi", "scene")  # the entries of a pool example


def scene_weights(natural_share: float = NATURAL_SHARE) -> tuple[float, ...]:
    """SCENE_WEIGHTS with the natural scenes rescaled to ``natural_share`` of the mix (the
    procedural ones to the rest, in their standard proportions).

    Parameters
    ----------
    natural_share : float
        Share of the natural scenes (:data:`NATURAL_SCENES`) in the mix, in [0, 1].

    Returns
    -------
    tuple of float
        One probability per name of :data:`TRAIN_SCENES`, summing to 1. The standard share
        returns :data:`SCENE_WEIGHTS` itself, so that standard pools stay bit for bit.

    Raises
    ------
    ValueError
        ``natural_share`` outside [0, 1].
    """
    if not 0.0 <= natural_share <= 1.0:
        raise ValueError(f"natural_share must lie in [0, 1], got {natural_share!r}")
    if natural_share == NATURAL_SHARE:
        return SCENE_WEIGHTS
    n = len(NATURAL_SCENES)
    procedural = [w * (1 - natural_share) / (1 - NATURAL_SHARE) for w in SCENE_WEIGHTS[:-n]]
    natural = [w * natural_share / NATURAL_SHARE for w in SCENE_WEIGHTS[-n:]]
    return tuple(procedural + natural)
# Bumped whenever the scene mix changes, so that cached pools of another mix are not reused.
POOL_VERSION = 2


def dead_leaves(shape, rng: np.random.Generator, r_min: float = 1.0) -> np.ndarray:
    """Dead-leaves raster (rows, cols) float32 in [0, 1]: opaque discs of random grey, radii with
    density ~ r^-3 (scale invariant, the 1/f^2 power spectrum of natural images), painted front
    to back until the raster is covered.

    Parameters
    ----------
    shape : (int, int)
        (rows, cols) of the raster, in raster pixels.
    rng : numpy.random.Generator
        Source of the discs' centres, radii and greys.
    r_min : float
        Smallest disc radius, raster pixels (the largest is half the longer side).

    Returns
    -------
    ndarray, shape (rows, cols), float32
        Grey levels in [0, 1]; pixels no disc covered after 5000 discs are 0.5.
    """
    rows, cols = shape
    r_max = max(rows, cols) / 2
    out = np.full(shape, np.nan, np.float32)
    yy, xx = np.mgrid[0:rows, 0:cols]
    for _ in range(5000):
        # inverse-CDF sample of p(r) ~ r^-3 on [r_min, r_max]
        u = rng.random()
        r = 1.0 / np.sqrt(1.0 / r_min**2 - u * (1.0 / r_min**2 - 1.0 / r_max**2))
        cy, cx = rng.uniform(-r, rows + r), rng.uniform(-r, cols + r)
        y0, y1 = max(int(cy - r), 0), min(int(cy + r) + 1, rows)
        x0, x1 = max(int(cx - r), 0), min(int(cx + r) + 1, cols)
        if y0 >= y1 or x0 >= x1:
            continue
        win = out[y0:y1, x0:x1]
        disc = ((yy[y0:y1, x0:x1] - cy) ** 2 + (xx[y0:y1, x0:x1] - cx) ** 2 <= r * r) & np.isnan(win)
        win[disc] = rng.uniform(0.0, 1.0)
        if not np.isnan(out).any():
            break
    return np.nan_to_num(out, nan=0.5)


def natural_image(name: str, spec: SceneSpec, rng: np.random.Generator) -> ImageScene:
    """A procedural stand-in for a photograph: a dead-leaves raster or a 1/f^2 random field.

    The raster pixel is 1/4 to 4 sensor pixels (log-uniform) and the scene reads it by bilinear
    interpolation, as a photograph stretched over the view is read: coarse rasters give the
    smooth, interpolated content on which a linear (Wiener-like) prior is strong, fine ones give
    sharp natural detail. Contrast and mean level are random.

    Parameters
    ----------
    name : str
        ``"dead-leaves"`` (:func:`dead_leaves`) or ``"natural-field"`` (a 1/f^beta field).
    spec : SceneSpec
        The view to cover: ``size_mm`` (width, height) in mm and ``pixel_mm``, the sensor
        pixel's footprint in the object plane, mm.
    rng : numpy.random.Generator
        Source of every random choice.

    Returns
    -------
    ImageScene
        Of ``spec.size_mm``, its raster (rows, cols) float32 in [0, 1].
    """
    raster_px = float(np.exp(rng.uniform(np.log(0.25), np.log(4.0))))  # sensor pixels per raster pixel
    cols = max(8, int(np.ceil(spec.size_mm[0] / (spec.pixel_mm * raster_px))))
    rows = max(8, int(np.ceil(spec.size_mm[1] / (spec.pixel_mm * raster_px))))
    if name == "dead-leaves":
        image = dead_leaves((rows, cols), rng, r_min=float(rng.uniform(0.5, 2.0)))
    else:
        image = texture_image((rows, cols), correlation_px=float(rng.uniform(0.0, 1.0)), rng=rng,
                              beta=float(rng.uniform(0.8, 1.3)))
    contrast, gamma = rng.uniform(0.3, 1.0), float(np.exp(rng.uniform(-0.5, 0.5)))
    image = image**gamma
    image = rng.uniform(0.0, 1.0 - contrast) + contrast * image
    return ImageScene(size_mm=spec.size_mm, image=torch.from_numpy(image.astype(np.float32)), name=name)


@dataclass(frozen=True)
class ExampleDraw:
    """Every random choice of one pool example (:func:`draw_example`).

    Attributes
    ----------
    roi : (int, int, int, int)
        (u0, v0, width, height) of the simulated stack on the sensor, pixels.
    scene : str
        A name of :data:`TRAIN_SCENES`.
    scene_seed : int
        Seed of the scene's layout (:func:`natural_image` or ``load_scene``).
    full_well_e : float
        Full well of the sensor, electrons (sets the shot noise; the exposure).
    noise_seed : int
        Seed of ``simulate_stack``'s noise.
    """

    roi: tuple[int, int, int, int]
    scene: str
    scene_seed: int
    full_well_e: float
    noise_seed: int


def example_seed(seed: int, index: int) -> int:
    """Seed of example ``index`` of the pool of seed ``seed`` (as :func:`build_pool` uses it).

    Returns
    -------
    int
        In [0, 2^32), from ``numpy.random.SeedSequence([seed, index])``.
    """
    return int(np.random.SeedSequence([seed, index]).generate_state(1)[0])


def draw_example(system: FoveaSystem, size: int, seed: int, natural_share: float = NATURAL_SHARE) -> ExampleDraw:
    """The random choices of the example of seed ``seed`` (cheap: nothing is built).

    The ROI lies anywhere on the sensor, uniformly (corners included), the scene is drawn from
    the mix of :func:`scene_weights` and the full well log-uniformly from :data:`FULL_WELL_E`:
    from dim (noisy) to bright exposures; the ADC is the default 12 bits.

    Parameters
    ----------
    system : FoveaSystem
        Its camera bounds the ROI.
    size : int
        Side of the square ROI, sensor pixels.
    seed : int
        The example's seed (:func:`example_seed` in a pool).
    natural_share : float
        Share of the natural scenes in the mix (:func:`scene_weights`).

    Returns
    -------
    ExampleDraw

    Raises
    ------
    HbisInputError
        ``size`` below 1 or larger than the sensor.
    """
    cam = system.camera
    if not 1 <= size <= min(cam.cols, cam.rows):
        raise HbisInputError(f"example size {size} does not fit the {cam.cols} x {cam.rows} sensor")
    rng = np.random.default_rng(seed)
    roi = (int(rng.integers(0, cam.cols - size + 1)), int(rng.integers(0, cam.rows - size + 1)), size, size)
    name = str(rng.choice(TRAIN_SCENES, p=scene_weights(natural_share)))
    scene_seed = int(rng.integers(2**31))
    full_well = float(np.exp(rng.uniform(np.log(FULL_WELL_E[0]), np.log(FULL_WELL_E[1]))))
    return ExampleDraw(roi, name, scene_seed, full_well, int(rng.integers(2**31)))


def simulate_example(system: FoveaSystem, plan, size: int, seed: int, natural_share: float = NATURAL_SHARE) -> dict:
    """One simulated stack of a random scene of the mix (:func:`scene_weights`) at a random
    place on the sensor.

    Parameters
    ----------
    system : FoveaSystem
    plan : ScanPlan
        The scan (``plan_scan(system, h)``); h = ``plan.h``.
    size : int
        Side of the square ROI, sensor pixels.
    seed : int
        The example's seed: :func:`draw_example` makes its choices.
    natural_share : float
        Share of the natural scenes in the mix.

    Returns
    -------
    dict
        ``frames`` (F, size, size) float32 in [0, 1], ``positions`` (F, size, size, 2) float32
        ROI-local LR pixels, ``truth`` (h size, h size) float32, ``roi`` (4,) and ``scene``
        (name).
    """
    draw = draw_example(system, size, seed, natural_share)
    spec = SceneSpec.around_roi(size, size, system.object_pixel_mm)
    if draw.scene in NATURAL_SCENES:
        scene = natural_image(draw.scene, spec, np.random.default_rng(draw.scene_seed))
    else:
        scene = load_scene(draw.scene, spec, seed=draw.scene_seed)
    sensor = SensorModel(full_well_e=draw.full_well_e)
    stack, truth = simulate_stack(scene, system, plan, roi=draw.roi, sensor=sensor, seed=draw.noise_seed)
    positions = sample_positions(system, plan.phases_deg, plan.reference_index, draw.roi)
    return {
        "frames": stack.to_float().numpy(),
        "positions": positions.numpy().astype(np.float32),
        "truth": np.asarray(truth, np.float32),
        "roi": np.asarray(draw.roi),
        "scene": draw.scene,
    }


def build_pool(h: int, count: int, size: int, seed: int, indices=None, natural_share: float = NATURAL_SHARE) -> list[dict]:
    """``count`` simulated examples (or those of ``indices``) with seeds derived from ``seed``.

    Parameters
    ----------
    h : int
        Resolution improvement factor of the scans (F = h^2 frames).
    count : int
        Examples in the pool (used when ``indices`` is None).
    size : int
        Side of each example's ROI, sensor pixels.
    seed : int
        The pool's seed; example i gets :func:`example_seed` (seed, i).
    indices : iterable of int, optional
        Only these examples of the pool (a process's share of it).
    natural_share : float
        Share of the natural scenes in the mix.

    Returns
    -------
    list of dict
        :func:`simulate_example` dicts, in the order of ``indices``.
    """
    system = FoveaSystem()
    plan = plan_scan(system, h)
    indices = range(count) if indices is None else indices
    return [simulate_example(system, plan, size, example_seed(seed, i), natural_share) for i in indices]


def save_pool(path, pool: list[dict]) -> None:
    """Write a pool as one .npz (atomically), entry ``"{i}/{key}"`` for each key of example i."""
    arrays = {}
    for i, ex in enumerate(pool):
        for key, value in ex.items():
            arrays[f"{i}/{key}"] = np.asarray(value)
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            np.savez(f, **arrays)


def load_pool(path) -> list[dict]:
    """A pool written by :func:`save_pool`: its examples in order, the entries of
    :data:`POOL_KEYS` as arrays (``scene`` a 0-d str array)."""
    with np.load(path) as data:
        count = 1 + max(int(k.split("/")[0]) for k in data.files)
        return [{key: data[f"{i}/{key}"] for key in POOL_KEYS} for i in range(count)]


def dihedral(frames, positions, truth, k: int):
    """Apply the k-th (0..7) flip/transpose of the square to a square crop and its positions.

    Parameters
    ----------
    frames : ndarray, shape (F, P, P)
    positions : ndarray, shape (F, P, P, 2)
        Crop-local (x, y) sample positions, LR pixels; moved with the pixels.
    truth : ndarray, shape (hP, hP)
    k : int
        Bit 4: transpose, bit 1: flip x, bit 2: flip y (applied in that order).

    Returns
    -------
    frames, positions, truth
        The same shapes (views where possible).
    """
    size = frames.shape[-1]
    if k & 4:  # transpose: swap rows and columns, and the x and y of every position
        frames = frames.transpose(0, 2, 1)
        positions = positions.transpose(0, 2, 1, 3)[..., ::-1]
        truth = truth.T
    if k & 1:  # flip x
        frames, truth = frames[..., ::-1], truth[..., ::-1]
        positions = positions[:, :, ::-1].copy()
        positions[..., 0] = (size - 1) - positions[..., 0]
    if k & 2:  # flip y
        frames, truth = frames[:, ::-1], truth[::-1]
        positions = positions[:, ::-1].copy()
        positions[..., 1] = (size - 1) - positions[..., 1]
    return frames, positions, truth


def crop_example(example: dict, h: int, patch: int, rng: np.random.Generator, augment: bool = True,
                 noise_prob: float = 0.0, noise_max: float = 0.0):
    """A random (patch x patch) crop, transformed, as (frames_reg, offsets, truth (1, hP, hP)).

    With probability ``noise_prob`` the frames get extra Gaussian noise of a standard deviation
    drawn uniformly from [0, noise_max] (then clipped to [0, 1] as a sensor would), so that the
    network also learns to denoise stacks far noisier than the simulator's default exposure.

    Parameters
    ----------
    example : dict
        A pool example (:func:`simulate_example`).
    h : int
        Its resolution improvement factor.
    patch : int
        Side of the crop, LR pixels.
    rng : numpy.random.Generator
        Source of the crop's place, flip and noise.
    augment : bool
        Apply a random one of the 8 flips/transposes (:func:`dihedral`).
    noise_prob, noise_max : float
        Chance of extra noise, and its largest standard deviation (frames in [0, 1]).

    Returns
    -------
    frames_reg : ndarray, shape (h^2, patch, patch), float32
    offsets : ndarray, shape (2 h^2, patch, patch), float32
        As :func:`~hbis_torch.reconstruct.learned.prepare_inputs` gives them.
    truth : ndarray, shape (1, h patch, h patch), float32

    Raises
    ------
    HbisInputError
        ``patch`` below 1 or larger than the example.
    """
    frames, positions, truth = example["frames"], example["positions"], example["truth"]
    size_y, size_x = frames.shape[1:]
    if not 1 <= patch <= min(size_y, size_x):
        raise HbisInputError(f"patch {patch} does not fit the {size_x} x {size_y} example")
    y0 = int(rng.integers(0, size_y - patch + 1))
    x0 = int(rng.integers(0, size_x - patch + 1))
    f = frames[:, y0:y0 + patch, x0:x0 + patch]
    p = positions[:, y0:y0 + patch, x0:x0 + patch] - np.array([x0, y0], np.float32)
    t = truth[h * y0:h * (y0 + patch), h * x0:h * (x0 + patch)]
    if augment:
        f, p, t = dihedral(f, p, t, int(rng.integers(8)))
    if noise_prob and rng.random() < noise_prob:
        f = np.clip(f + rng.normal(0.0, rng.uniform(0.0, noise_max), f.shape), 0.0, 1.0)
    frames_reg, offsets = prepare_inputs(f, p, h)
    return frames_reg, offsets, np.ascontiguousarray(t, dtype=np.float32)[None]


def make_batch(pool: list[dict], h: int, patch: int, batch: int, rng: np.random.Generator,
               noise_prob: float = 0.0, noise_max: float = 0.0):
    """frames (B, h^2, P, P), offsets (B, 2h^2, P, P), truth (B, 1, hP, hP), float32.

    ``batch`` crops (:func:`crop_example`, augmented) of examples of ``pool`` drawn uniformly
    with ``rng``; the same generator state gives the same batch.
    """
    parts = [crop_example(pool[int(rng.integers(len(pool)))], h, patch, rng, True, noise_prob, noise_max)
             for _ in range(batch)]
    return tuple(np.stack(a) for a in zip(*parts))


def whole_example(example: dict, h: int):
    """The full example as a batch of one (no crop, no augmentation).

    Returns
    -------
    frames_reg : ndarray, shape (1, h^2, H, W), float32
    offsets : ndarray, shape (1, 2 h^2, H, W), float32
    truth : ndarray, shape (1, 1, hH, hW), float32
    """
    frames_reg, offsets = prepare_inputs(example["frames"], example["positions"], h)
    return frames_reg[None], offsets[None], example["truth"][None, None]
