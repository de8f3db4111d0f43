"""Training data for the SR network: simulated scans under randomised degradations.

A *pool* is a list of simulated stacks (:func:`hbis_torch.simulate.simulate_stack`, the project's
physical forward model), each reconstructed by the classical method, which is what the network
refines (:mod:`hbis_torch.training.net`). Every example draws its own degradations,
wider than any one sensor, so that the network holds on captured stacks whose optics, sensor and
scan the training never saw exactly (:func:`draw_example`):

* the scan: initial phases anywhere, the paper's or the exact inverse, phase errors, and the
  reference frame anywhere in the scan;
* the place on the sensor: anywhere, corners included;
* the optics: Airy from F 1 (next to no blur at 3.75 um pixels) to F 8, defocus up to 0.6 waves
  (unknown to the classical step, as a real lens's focus is), fill factor 0.5 to 1;
* the noise: full well 1,000 to 100,000 e-, read noise 1 to 15 e-, 8 to 16 bits, exposures from
  a tenth of full scale to clipped highlights;
* the scene: procedural test scenes (words, texture, edges, bars, Siemens stars, gradients),
  procedural *natural-image* rasters (dead leaves and 1/f^2 random fields, :func:`natural_image`)
  and the photographs of :data:`TRAIN_PHOTOS` (also :func:`natural_image`), from 1/8 to 4 sensor pixels
  per raster pixel, read by bilinear or bicubic interpolation. The photographs of
  :data:`HELD_OUT_PHOTOS` are never used for training: they are the held-out test
  (training/eval_matrix.py).

Each example keeps the classical image, the truth and two noise models: the one the stack's
sensor model gives and the one measured on the classical step's lattice
(:func:`~hbis_torch.reconstruct.classical.lattice_noise_params`), as the learned method measures
a stack without a sensor model (:func:`~hbis_torch.reconstruct.learned.method.classical_and_noise`);
a training crop takes either, so the network learns the measurement's errors too. Crops are
transformed by the 8 flips/transposes of the square (both images are on the same output grid, so
they move together).

This is the project's one training-data pipeline (training/train_sr.py, the tests and
benchmarks/bench_simulate.py use it):

1. :func:`draw_example` makes every random choice of pool example ``seed`` (cheap: nothing is
   simulated), :func:`simulate_example` renders and reconstructs it, and :func:`build_pool` makes
   a pool of examples whose seeds come from one pool seed and the example's index
   (:func:`example_seed`), so example i of a pool is the same whichever process builds it;
2. :func:`save_pool` / :func:`load_pool` cache a pool as one .npz;
3. :func:`make_batch` cuts a batch of random crops (:func:`crop_example`, :func:`dihedral`) in the
   network's input layout; :func:`whole_example` gives a whole example as a batch of one;
4. :func:`training_domain` is the optics and noise these draws span, which the export records
   in the model (the runtime's check, :mod:`hbis_torch.reconstruct.learned.domain`, reads it there).

All randomness comes from the seeds and generators passed in: the same seeds give the same pools
and batches, bit for bit.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
import torch

from hbis_torch.config import Camera, FoveaSystem
from hbis_torch.errors import HbisInputError
from hbis_torch.io_utils import atomic_path
from hbis_torch.optics import sample_positions
from hbis_torch.reconstruct.classical import classical_sr, optics_cutoff
from hbis_torch.reconstruct.learned.domain import noise_at_mid_grey
from hbis_torch.reconstruct.learned.inputs import network_inputs, noise_params_from_meta, sensor_noise_params
from hbis_torch.scan import plan_scan
from hbis_torch.simulate import (
    SceneSpec,
    SensorModel,
    load_scene,
    simulate_stack,
)
from hbis_torch.simulate.rasters import HELD_OUT_PHOTOS, PHOTOS, photo, texture_image
from hbis_torch.simulate.scenes import ImageScene

TRAIN_PHOTOS = tuple(name for name in PHOTOS if name not in HELD_OUT_PHOTOS)
"""The photographs shipped with scikit-image but for :data:`HELD_OUT_PHOTOS` (training/eval_matrix.py's
scenes): rasters of the ``"photograph"`` scenes."""
NATURAL_SCENES = ("dead-leaves", "natural-field", "photograph")
TRAIN_SCENES = ("words", "texture", "edges", "bars", "siemens-star", "gradient", "slanted-edge") + NATURAL_SCENES
SCENE_WEIGHTS = (0.15, 0.1, 0.05, 0.05, 0.05, 0.05, 0.05, 0.2, 0.1, 0.2)
# Ranges of the randomised degradations (log-uniform where the range spans decades).
F_NUMBER = (1.0, 8.0)
DEFOCUS_WAVES = 0.6  # largest defocus (W020, waves), in half of the examples
FILL_FACTOR = (0.5, 1.0)
FULL_WELL_E = (1_000.0, 100_000.0)
READ_NOISE_E = (1.0, 15.0)
BIT_DEPTHS = (8, 10, 12, 14, 16)
EXPOSURE = (0.1, 2.0)  # scale of a natural raster's grey levels before clipping at full scale
RASTER_PX = (1 / 8, 4.0)  # sensor pixels per raster pixel of a natural raster
PHASE_ERROR_DEG = 0.05  # largest phase error, in half of the examples
POOL_KEYS = ("base", "truth", "noise", "roi", "scene")  # the entries of a pool example
# Bumped whenever the pool's contents change, so that cached pools of another kind are not reused.
POOL_VERSION = 5


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


def natural_image(name: str, spec: SceneSpec, rng: np.random.Generator, exposure: float = 1.0) -> ImageScene:
    """A natural-image scene: a dead-leaves raster, a 1/f^2 random field or a training photograph.

    The raster pixel is :data:`RASTER_PX` sensor pixels (log-uniform) and the scene reads it by
    bilinear or bicubic interpolation (even odds), as a photograph stretched over the view is
    read: coarse rasters give smooth, interpolated content, fine ones sharp natural detail. Real
    scenes have detail beyond any raster's: bilinear reads alone taught the network a scene
    spectrum that falls off at the raster's Nyquist frequency, and it lost detail on scenes
    rendered without that fall-off (training/independent_render.py's cubic reads). A photograph
    (one of :data:`TRAIN_PHOTOS`, turned by one of the square's 8 symmetries) gives a crop of its own
    pixels; where it has too few pixels for the view at the drawn scale, its pixels are read
    coarser. Contrast and mean level are random; ``exposure`` then scales the grey levels, and
    what passes full scale clips.

    Parameters
    ----------
    name : str
        ``"dead-leaves"`` (:func:`dead_leaves`), ``"natural-field"`` (a 1/f^beta field) or
        ``"photograph"``.
    spec : SceneSpec
        The view to cover: ``size_mm`` (width, height) in mm and ``pixel_mm``, the sensor
        pixel's footprint in the object plane, mm.
    rng : numpy.random.Generator
        Source of every random choice.
    exposure : float
        Scale of the grey levels (1: the raster as drawn, in [0, 1]).

    Returns
    -------
    ImageScene
        Of ``spec.size_mm``, its raster (rows, cols) float32 in [0, 1].
    """
    raster_px = float(np.exp(rng.uniform(np.log(RASTER_PX[0]), np.log(RASTER_PX[1]))))
    if name == "photograph":
        source = photo(str(rng.choice(TRAIN_PHOTOS)))
        source = np.rot90(source, int(rng.integers(4)))[:, ::int(rng.choice((-1, 1)))]
        fits = max(spec.size_mm[0] / source.shape[1], spec.size_mm[1] / source.shape[0]) / spec.pixel_mm
        raster_px = max(raster_px, fits)
    cols = max(8, int(np.ceil(spec.size_mm[0] / (spec.pixel_mm * raster_px))))
    rows = max(8, int(np.ceil(spec.size_mm[1] / (spec.pixel_mm * raster_px))))
    if name == "photograph":
        rows, cols = min(rows, source.shape[0]), min(cols, source.shape[1])
        y0, x0 = (int(rng.integers(0, n - m + 1)) for n, m in zip(source.shape, (rows, cols)))
        image = np.ascontiguousarray(source[y0:y0 + rows, x0:x0 + cols])
    elif name == "dead-leaves":
        image = dead_leaves((rows, cols), rng, r_min=float(rng.uniform(0.5, 2.0)))
    else:
        image = texture_image((rows, cols), correlation_px=float(rng.uniform(0.0, 1.0)), rng=rng,
                              beta=float(rng.uniform(0.8, 1.3)))
    contrast, gamma = rng.uniform(0.3, 1.0), float(np.exp(rng.uniform(-0.5, 0.5)))
    image = image**gamma
    image = np.clip(exposure * (rng.uniform(0.0, 1.0 - contrast) + contrast * image), 0.0, 1.0)
    interpolation = str(rng.choice(("bilinear", "bicubic")))
    return ImageScene(size_mm=spec.size_mm, image=torch.from_numpy(image.astype(np.float32)), name=name,
                      interpolation=interpolation)


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
    exposure : float
        Grey-level scale of a natural scene (:func:`natural_image`).
    initial_phases_deg : (float, float)
        Phases of the scan's initial frame, degrees.
    plan_method : str
        ``"paper"`` or ``"exact"`` (:func:`~hbis_torch.scan.plan_scan`).
    phase_error_deg : float
        Standard deviation of the prisms' phase errors, degrees.
    reference_index : int
        The frame that defines the output grid.
    f_number : float
    sensor : SensorModel
        Fill factor, defocus, full well, read noise and bit depth.
    noise_seed : int
        Seed of ``simulate_stack``'s noise and phase errors.
    """

    roi: tuple[int, int, int, int]
    scene: str
    scene_seed: int
    exposure: float
    initial_phases_deg: tuple[float, float]
    plan_method: str
    phase_error_deg: float
    reference_index: int
    f_number: float
    sensor: SensorModel
    noise_seed: int


def example_seed(seed: int, index: int) -> int:
    """Seed of example ``index`` of the pool of seed ``seed`` (as :func:`build_pool` uses it).

    Returns
    -------
    int
        In [0, 2^32), from ``numpy.random.SeedSequence([seed, index])``.
    """
    return int(np.random.SeedSequence([seed, index]).generate_state(1)[0])


def _log_uniform(rng: np.random.Generator, bounds: tuple[float, float]) -> float:
    return float(np.exp(rng.uniform(np.log(bounds[0]), np.log(bounds[1]))))


def draw_example(camera: Camera, h: int, size: int, seed: int) -> ExampleDraw:
    """The random choices of the example of seed ``seed`` (cheap: nothing is built).

    Parameters
    ----------
    camera : Camera
        Its sensor bounds the ROI (its f-number is drawn anew).
    h : int
        Resolution improvement factor (the reference frame is one of h^2).
    size : int
        Side of the square ROI, sensor pixels.
    seed : int
        The example's seed (:func:`example_seed` in a pool).

    Returns
    -------
    ExampleDraw

    Raises
    ------
    HbisInputError
        ``size`` below 1 or larger than the sensor.
    """
    if not 1 <= size <= min(camera.cols, camera.rows):
        raise HbisInputError(f"example size {size} does not fit the {camera.cols} x {camera.rows} sensor")
    rng = np.random.default_rng(seed)
    roi = (int(rng.integers(0, camera.cols - size + 1)), int(rng.integers(0, camera.rows - size + 1)), size, size)
    name = str(rng.choice(TRAIN_SCENES, p=SCENE_WEIGHTS))
    scene_seed = int(rng.integers(2**31))
    exposure = _log_uniform(rng, EXPOSURE)
    # The prisms' phase difference away from 0 (both bend the same way: the edge of the field,
    # where an h x h scan can leave the pair's reach) and from 180 deg (the pair cancels).
    phi1 = float(rng.uniform(0, 360))
    phases = (phi1, (phi1 + float(rng.choice((-1, 1)) * rng.uniform(20, 160))) % 360)
    method = str(rng.choice(("paper", "exact")))
    phase_error = float(rng.uniform(0, PHASE_ERROR_DEG)) if rng.random() < 0.5 else 0.0
    reference = int(rng.integers(h * h))
    f_number = _log_uniform(rng, F_NUMBER)
    waves = float(rng.uniform(0, DEFOCUS_WAVES)) if rng.random() < 0.5 else 0.0
    # W020 = dz / (8 F^2) for a defocus dz, so dz = 8 F^2 lambda W020 (waves)
    defocus_um = 8 * f_number**2 * camera.wavelength_nm * 1e-3 * waves
    sensor = SensorModel(fill_factor=float(rng.uniform(*FILL_FACTOR)), defocus_um=defocus_um,
                         full_well_e=_log_uniform(rng, FULL_WELL_E), read_noise_e=float(rng.uniform(*READ_NOISE_E)),
                         bit_depth=int(rng.choice(BIT_DEPTHS)))
    return ExampleDraw(roi, name, scene_seed, exposure, phases, method, phase_error, reference, f_number,
                       sensor, int(rng.integers(2**31)))


def simulate_example(h: int, size: int, seed: int, system: FoveaSystem | None = None) -> dict:
    """One simulated stack under the degradations of :func:`draw_example`, and its classical image.

    Parameters
    ----------
    h : int
        Resolution improvement factor.
    size : int
        Side of the square ROI, sensor pixels.
    seed : int
        The example's seed: :func:`draw_example` makes its choices.
    system : FoveaSystem, optional
        The fovea (default: Table 1's); its camera's f-number is replaced by the drawn one.

    Returns
    -------
    dict
        ``base`` (h size, h size) float32, the classical image; ``truth`` (h size, h size)
        float32; ``noise`` (2, 2) float32, the noise parameters (a, b) of the stack's sensor
        model (row 0) and measured on the classical step's lattice (row 1); ``roi`` (4,) and ``scene`` (name).
    """
    system = system or FoveaSystem()
    draw = draw_example(system.camera, h, size, seed)
    system = dataclasses.replace(system, camera=dataclasses.replace(system.camera, f_number=draw.f_number))
    try:
        plan = plan_scan(system, h, draw.initial_phases_deg, method=draw.plan_method)
    except HbisInputError:  # a scan the paper's model cannot reach from there: the exact one can
        plan = plan_scan(system, h, draw.initial_phases_deg, method="exact")
    plan = dataclasses.replace(plan, reference_index=draw.reference_index)
    spec = SceneSpec.around_roi(size, size, system.object_pixel_mm)
    if draw.scene in NATURAL_SCENES:
        scene = natural_image(draw.scene, spec, np.random.default_rng(draw.scene_seed), draw.exposure)
    else:
        scene = load_scene(draw.scene, spec, seed=draw.scene_seed)
    stack, truth = simulate_stack(scene, system, plan, roi=draw.roi, sensor=draw.sensor, seed=draw.noise_seed,
                                  phase_error_deg=draw.phase_error_deg)
    # The classical step sees what a user's stack says: the planned phases, not the erroneous ones.
    positions = sample_positions(system, plan.phases_deg, plan.reference_index, draw.roi)
    measured = []  # the noise measured on the classical step's lattice, as the learned method measures it
    base = classical_sr(stack.to_float(), positions, h, cutoff=optics_cutoff(system),
                        fill_factor=draw.sensor.fill_factor, noise_params_out=measured)
    noise = np.array([noise_params_from_meta(stack.meta), measured[0]], np.float32)
    return {
        "base": base.numpy(),
        "truth": np.asarray(truth, np.float32),
        "noise": noise,
        "roi": np.asarray(draw.roi),
        "scene": draw.scene,
    }


def build_pool(h: int, count: int, size: int, seed: int, indices=None) -> list[dict]:
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

    Returns
    -------
    list of dict
        :func:`simulate_example` dicts, in the order of ``indices``.
    """
    indices = range(count) if indices is None else indices
    return [simulate_example(h, size, example_seed(seed, i)) for i in indices]


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


def dihedral(base, truth, k: int):
    """Apply the k-th (0..7) flip/transpose of the square to two images of one square crop.

    Parameters
    ----------
    base, truth : ndarray, shape (S, S)
        Images on the same output grid.
    k : int
        Bit 4: transpose, bit 1: flip x, bit 2: flip y (applied in that order).

    Returns
    -------
    base, truth
        The same shapes (views).
    """
    if k & 4:
        base, truth = base.T, truth.T
    if k & 1:
        base, truth = base[:, ::-1], truth[:, ::-1]
    if k & 2:
        base, truth = base[::-1], truth[::-1]
    return base, truth


def crop_example(example: dict, h: int, patch: int, rng: np.random.Generator, augment: bool = True):
    """A random (patch x patch) crop, transformed, as the network's inputs and the truth.

    The noise map comes from the example's sensor model or from the noise measured on its
    lattice, one or the other at random.

    Parameters
    ----------
    example : dict
        A pool example (:func:`simulate_example`).
    h : int
        Its resolution improvement factor.
    patch : int
        Side of the crop, LR pixels.
    rng : numpy.random.Generator
        Source of the crop's place, flip and noise model.
    augment : bool
        Apply a random one of the 8 flips/transposes (:func:`dihedral`).

    Returns
    -------
    base : ndarray, shape (h^2, patch, patch), float32
    noise : ndarray, shape (1, patch, patch), float32
        As :func:`~hbis_torch.reconstruct.learned.network_inputs` gives them.
    truth : ndarray, shape (1, h patch, h patch), float32

    Raises
    ------
    HbisInputError
        ``patch`` below 1 or larger than the example.
    """
    image, truth = example["base"], example["truth"]
    size_y, size_x = image.shape[0] // h, image.shape[1] // h
    if not 1 <= patch <= min(size_y, size_x):
        raise HbisInputError(f"patch {patch} does not fit the {size_x} x {size_y} example")
    y0 = h * int(rng.integers(0, size_y - patch + 1))
    x0 = h * int(rng.integers(0, size_x - patch + 1))
    image = image[y0:y0 + h * patch, x0:x0 + h * patch]
    truth = truth[y0:y0 + h * patch, x0:x0 + h * patch]
    if augment:
        image, truth = dihedral(image, truth, int(rng.integers(8)))
    base, noise = network_inputs(image, h, example["noise"][int(rng.integers(2))])
    return base, noise, np.ascontiguousarray(truth, dtype=np.float32)[None]


def make_batch(pool: list[dict], h: int, patch: int, batch: int, rng: np.random.Generator):
    """base (B, h^2, P, P), noise (B, 1, P, P), truth (B, 1, hP, hP), float32.

    ``batch`` crops (:func:`crop_example`, augmented) of examples of ``pool`` drawn uniformly
    with ``rng``; the same generator state gives the same batch.
    """
    parts = [crop_example(pool[int(rng.integers(len(pool)))], h, patch, rng) for _ in range(batch)]
    return tuple(np.stack(a) for a in zip(*parts))


def whole_example(example: dict, h: int, measured_noise: bool = False):
    """The full example as a batch of one (no crop, no augmentation).

    Parameters
    ----------
    measured_noise : bool
        Use the noise measured on the lattice rather than the sensor model's.

    Returns
    -------
    base : ndarray, shape (1, h^2, H, W), float32
    noise : ndarray, shape (1, 1, H, W), float32
    truth : ndarray, shape (1, 1, hH, hW), float32
    """
    base, noise = network_inputs(example["base"], h, example["noise"][int(measured_noise)])
    return base[None], noise[None], example["truth"][None, None]


def training_domain() -> dict:
    """The domain of this training pipeline: what :func:`export_model
    <hbis_torch.training.export.export_model>` records as the model's ``training_domain``
    (a pool with bursts: :func:`hbis_torch.training.burst_data.training_domain_with_bursts`).

    Returns
    -------
    dict
        ``cutoff_cycles_per_px``: [lowest, highest] lens cutoff, cycles per LR pixel, over
        :data:`F_NUMBER` on the default camera; ``noise_at_mid_grey``: [lowest, highest] frame
        noise at half of full scale (:func:`~hbis_torch.reconstruct.learned.domain.noise_at_mid_grey`,
        full scale 1), over :data:`FULL_WELL_E`, :data:`READ_NOISE_E` and :data:`BIT_DEPTHS`.
    """
    base = FoveaSystem()

    def cutoff(f_number: float) -> float:
        return optics_cutoff(dataclasses.replace(base, camera=dataclasses.replace(base.camera, f_number=f_number)))

    def noise(full_well: float, read: float, bits: int) -> float:
        return noise_at_mid_grey(sensor_noise_params(full_well, read, bits))

    return {"cutoff_cycles_per_px": [cutoff(F_NUMBER[1]), cutoff(F_NUMBER[0])],
            "noise_at_mid_grey": [noise(FULL_WELL_E[1], READ_NOISE_E[0], max(BIT_DEPTHS)),
                                  noise(FULL_WELL_E[0], READ_NOISE_E[1], min(BIT_DEPTHS))]}
