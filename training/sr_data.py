"""Training data for the SR network: simulated scans, cut into patches.

A *pool* is a list of simulated stacks (hbis_torch.simulate.simulate_stack, the project's physical
forward model: exact Risley geometry, Airy PSF, pixel aperture, shot and read noise, 12-bit ADC)
of procedural scenes (words, texture, edges, bars, Siemens stars, gradients) at random places on
the sensor, so that the network sees the off-grid shifts of the sensor's corners as well as its
centre. Photographs are *not* used for training: they are the held-out test of the benchmark.

Training examples are random crops of pool stacks under the 8 flips/transposes of the square.
Flipping a stack is a valid new scan: the crop's sample positions are flipped with it and
:func:`~hbis_torch.sr.learned.prepare_inputs` finds the new registered order from them.
"""

from __future__ import annotations

import numpy as np

from hbis_torch.config import System
from hbis_torch.io_utils import atomic_path
from hbis_torch.scan import plan_scan
from hbis_torch.simulate import SceneSpec, SensorModel, load_scene, sample_positions, simulate_stack
from hbis_torch.sr.learned import prepare_inputs

TRAIN_SCENES = ("words", "texture", "edges", "bars", "siemens-star", "gradient", "slanted-edge")
SCENE_WEIGHTS = (0.3, 0.25, 0.15, 0.1, 0.1, 0.05, 0.05)


def simulate_example(system: System, plan, size: int, seed: int) -> dict:
    """One simulated stack of a random procedural scene at a random place on the sensor.

    Returns a dict with ``frames`` (F, size, size) float32 in [0, 1], ``positions``
    (F, size, size, 2) float32 ROI-local LR pixels, ``truth`` (h size, h size) float32,
    ``roi`` (4,) and ``scene`` (name).
    """
    rng = np.random.default_rng(seed)
    cam = system.camera
    roi = (int(rng.integers(0, cam.cols - size + 1)), int(rng.integers(0, cam.rows - size + 1)), size, size)
    name = str(rng.choice(TRAIN_SCENES, p=SCENE_WEIGHTS))
    pixel = system.object_pixel_mm
    side = size * pixel * 1.25  # a margin so the scene covers every frame of the scan
    spec = SceneSpec(size_mm=(side, side), pixel_mm=pixel, detail_mm=pixel / 16)
    scene = load_scene(name, spec, seed=int(rng.integers(2**31)))
    # Exposure varies from dim (noisy) to bright; the ADC is the default 12 bits.
    sensor = SensorModel(full_well_e=float(np.exp(rng.uniform(np.log(2000), np.log(30000)))))
    stack, truth = simulate_stack(scene, system, plan, roi=roi, sensor=sensor, seed=int(rng.integers(2**31)))
    positions = sample_positions(system, plan.phases_deg, plan.reference_index, roi)
    return {
        "frames": stack.to_float().numpy(),
        "positions": positions.numpy().astype(np.float32),
        "truth": np.asarray(truth, np.float32),
        "roi": np.asarray(roi),
        "scene": name,
    }


def build_pool(h: int, count: int, size: int, seed: int, indices=None) -> list[dict]:
    """``count`` simulated examples (or those of ``indices``) with seeds derived from ``seed``."""
    system = System()
    plan = plan_scan(system, h)
    indices = range(count) if indices is None else indices
    return [simulate_example(system, plan, size, int(np.random.SeedSequence([seed, i]).generate_state(1)[0]))
            for i in indices]


def save_pool(path, pool: list[dict]) -> None:
    """Write a pool as one .npz (atomically)."""
    arrays = {}
    for i, ex in enumerate(pool):
        for key, value in ex.items():
            arrays[f"{i}/{key}"] = np.asarray(value)
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            np.savez(f, **arrays)


def load_pool(path) -> list[dict]:
    with np.load(path) as data:
        count = 1 + max(int(k.split("/")[0]) for k in data.files)
        return [{key: data[f"{i}/{key}"] for key in ("frames", "positions", "truth", "roi", "scene")}
                for i in range(count)]


def dihedral(frames, positions, truth, k: int):
    """Apply the k-th (0..7) flip/transpose of the square to a square crop and its positions."""
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
    """
    frames, positions, truth = example["frames"], example["positions"], example["truth"]
    size_y, size_x = frames.shape[1:]
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
    """frames (B, h^2, P, P), offsets (B, 2h^2, P, P), truth (B, 1, hP, hP), float32."""
    parts = [crop_example(pool[int(rng.integers(len(pool)))], h, patch, rng, True, noise_prob, noise_max)
             for _ in range(batch)]
    return tuple(np.stack(a) for a in zip(*parts))


def whole_example(example: dict, h: int):
    """The full example as a batch of one (no crop, no augmentation)."""
    frames_reg, offsets = prepare_inputs(example["frames"], example["positions"], h)
    return frames_reg[None], offsets[None], example["truth"][None, None]
