"""Training data from bursts: frames of a freely moving camera, for the refiner of each scale.

A Risley scan puts its samples on a near-regular lattice; a burst (``hbis assemble --burst``)
puts them wherever the camera went, a few frames or many, with gaps, and its motion is measured,
not known. A training pool can hold burst examples beside the scans
(:func:`simulate_burst_example`; ``training/train_sr.py burst_pool_size=N``), so that one model
per scale serves both kinds of stack (docs/real-bursts.md says what that gave: the shipped
models are trained on scans alone). Each example draws, from its own seed:

* the scene: the scan pool's scenes (:data:`~hbis_torch.training.data.TRAIN_SCENES`, the
  held-out photographs never), drawn on the output grid;
* the frames: 4 to 30 (log-uniform), shifts up to 0.5 to 4 LR px, rotations up to 1 degree in
  half of the bursts, zooms up to 1 % in a quarter, a patch of the scene that moves on its own in
  a third of them, brightness changes (gain 0.9 to 1.1, offset +-0.03) in half;
* the camera: a Gaussian lens blur of 0 to 0.6 LR px (the truth stays sharp), Gaussian noise of
  0.2 % to 10 % of full scale (log-uniform), 8 bits.

The burst is then assembled as a user's is (:func:`~hbis_torch.capture.burst.assemble_burst`,
motion measured, ``--motion auto``), and its classical image made as the learned method makes
it (:func:`~hbis_torch.reconstruct.burst.burst_samples`, then the classical splat and Wiener step
with the robustness weights), so the network learns the registration's errors too. The example
is a dict of :data:`~hbis_torch.training.data.POOL_KEYS`, as a scan's, so the two kinds mix in one
pool.
"""

from __future__ import annotations

import numpy as np
import torch

from hbis_torch.config import FoveaSystem
from hbis_torch.simulate import SceneSpec, load_scene

# Bumped whenever the burst examples change, so that cached pools of another kind are not reused
# (2: the classical image made as the burst path makes it, burst_sr).
BURST_POOL_VERSION = 2
FRAMES = (4, 30)
MAX_SHIFT_PX = (0.5, 4.0)
MAX_ROTATION_DEG = 1.0  # in half of the bursts
MAX_ZOOM = 0.01  # in a quarter
MOVING_SHARE = 1 / 3  # bursts with a patch that moves on its own
BLUR_PX = (0.0, 0.6)  # Gaussian lens blur, LR px
NOISE = (0.002, 0.1)  # Gaussian noise, full scale 1 (real bursts reach 10 %: small frames of a dim scene)
GAIN, OFFSET = 0.1, 0.03  # brightness changes, in half of the bursts


def truth_raster(scene_name: str, scale: int, size: int, scene_seed: int, exposure: float) -> np.ndarray:
    """A training scene drawn on the output grid of a ``size`` x ``size`` px burst refined
    ``scale`` times: each output pixel the scene's average over it, (S size, S size) float64 in [0, 1]."""
    from hbis_torch.training.data import NATURAL_SCENES, natural_image

    pixel_mm = FoveaSystem().object_pixel_mm
    spec = SceneSpec.around_roi(size, size, pixel_mm)
    if scene_name in NATURAL_SCENES:
        scene = natural_image(scene_name, spec, np.random.default_rng(scene_seed), exposure)
    else:
        scene = load_scene(scene_name, spec, seed=scene_seed)
    n = scale * size
    centres = ((torch.arange(n, dtype=torch.float64) + 0.5) / scale - size / 2) * pixel_mm
    y, x = torch.meshgrid(centres, centres, indexing="ij")
    values = scene.sample(torch.stack((x, y), -1), spacing_mm=pixel_mm / scale, relative=True)
    return values.numpy().astype(np.float64)


def simulate_burst_example(scale: int, size: int, seed: int) -> dict:
    """One simulated burst, assembled and reconstructed by the classical method (module docstring).

    Parameters
    ----------
    scale : int
        S, the refinement of the reference grid.
    size : int
        Side of the square frames, LR px.
    seed : int
        The example's seed: every random choice comes from it.

    Returns
    -------
    dict
        As :func:`hbis_torch.training.data.simulate_example`'s: ``base`` (S size, S size) float32,
        the classical image; ``truth`` the same shape; ``noise`` (2, 2) float32, the true noise
        (0, sigma^2) (row 0) and the noise measured on the frames (row 1, as the learned method
        measures a burst's: :func:`~hbis_torch.reconstruct.learned.inputs.estimate_noise_params`);
        ``roi`` (4,); ``scene`` (name).
    """
    from hbis_torch.capture.burst import assemble_burst
    from hbis_torch.reconstruct.burst import burst_samples
    from hbis_torch.reconstruct.classical.burst import burst_sr
    from hbis_torch.reconstruct.learned.inputs import estimate_noise_params
    from hbis_torch.simulate.burst import random_motions, simulate_burst
    from hbis_torch.training.data import EXPOSURE, SCENE_WEIGHTS, TRAIN_SCENES, _log_uniform

    rng = np.random.default_rng(seed)
    name = str(rng.choice(TRAIN_SCENES, p=SCENE_WEIGHTS))
    truth = truth_raster(name, scale, size, int(rng.integers(2**31)), _log_uniform(rng, EXPOSURE))
    count = int(round(_log_uniform(rng, FRAMES)))
    motions = random_motions(count, (size, size), rng, max_shift=float(rng.uniform(*MAX_SHIFT_PX)),
                             max_rotation_deg=MAX_ROTATION_DEG if rng.random() < 0.5 else 0.0,
                             max_zoom=MAX_ZOOM if rng.random() < 0.25 else 0.0)
    patch, moving = None, ()
    if rng.random() < MOVING_SHARE:
        side = int(scale * size * rng.uniform(0.15, 0.35))
        v0, u0 = (int(rng.integers(0, scale * size - 2 * side)) for _ in range(2))
        dv, du = (int(rng.integers(-side // 2, side // 2 + 1)) for _ in range(2))
        patch = (v0 + side // 2, u0 + side // 2, side, dv, du)
        moving = tuple(int(k) for k in np.flatnonzero(rng.random(count) < 0.4) if k > 0)
    gains = None
    if rng.random() < 0.5:
        gains = [(1.0, 0.0)] + [(1 + rng.uniform(-GAIN, GAIN), rng.uniform(-OFFSET, OFFSET)) for _ in range(count - 1)]
    sigma = _log_uniform(rng, NOISE)
    burst = simulate_burst(truth, scale, motions, noise=sigma, seed=int(rng.integers(2**31)), moving_patch=patch,
                           moving_frames=moving, gains=gains, blur_px=float(rng.uniform(*BLUR_PX)))
    stack, _ = assemble_burst(burst.frames, scale)
    frames, positions, _, weights = burst_samples(stack)
    base = burst_sr(frames, positions, scale, weights)
    return {
        "base": base.numpy(),
        "truth": burst.truth,
        "noise": np.array([(0.0, sigma**2), estimate_noise_params(frames.numpy())], np.float32),
        "roi": np.array([0, 0, size, size]),
        "scene": f"burst:{name}",
    }


def training_domain_with_bursts() -> dict:
    """The domain of a pool of scans and bursts: the scans'
    (:func:`hbis_torch.training.data.training_domain`), its noise range widened to the bursts'
    (:data:`NOISE`, with the 8-bit quantisation's), full scale 1."""
    from hbis_torch.training.data import training_domain

    domain = training_domain()
    quantisation = 1 / (255 * 12**0.5)
    low, high = domain["noise_at_mid_grey"]
    domain["noise_at_mid_grey"] = [min(low, float(np.hypot(NOISE[0], quantisation))),
                                   max(high, float(np.hypot(NOISE[1], quantisation)))]
    return domain


def build_burst_pool(scale: int, count: int, size: int, seed: int, indices=None) -> list[dict]:
    """``count`` burst examples (or those of ``indices``), example i of seed
    :func:`~hbis_torch.training.data.example_seed` (seed, i), as
    :func:`~hbis_torch.training.data.build_pool` builds the scans'."""
    from hbis_torch.training.data import example_seed

    indices = range(count) if indices is None else indices
    return [simulate_burst_example(scale, size, example_seed(seed, i)) for i in indices]
