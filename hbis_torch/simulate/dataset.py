"""Training data: random synthetic stacks generated on the fly, deterministically per index.

Item ``i`` of a :class:`SyntheticStacks` dataset depends only on ``(config.seed, i)``: the same
index gives the same stack in any process, worker or epoch. Each item draws

* h from ``h_choices`` and a scan plan from ``plan_scan`` at one of ``initial_phases``;
* a crop (roi) anywhere on the sensor; with probability ``edge_probability`` it is pushed against
  a sensor edge on each axis independently, so corners, where pixels move most unevenly, are
  well represented;
* a scene kind, and its random layout (photographs: a random crop, scale and orientation);
* a sensor: full well, read noise, black level, bit depth, fill factor, exposure, and a random
  error of the prism phases (frames rendered at the erroneous phases, positions "measured" from
  the planned ones, as a reconstructor would).

Items are dicts of tensors (see :meth:`SyntheticStacks.__getitem__`). Items with different h have
different shapes; :class:`SameHBatchSampler` batches indices of equal h.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np
import torch
from torch.utils.data import Dataset, Sampler

from hbis_torch.config import System
from hbis_torch.errors import HbisInputError
from hbis_torch.stack_io import Stack, make_meta
from hbis_torch.simulate.forward import grid_factor, render_scan
from hbis_torch.simulate.geometry import sample_positions
from hbis_torch.simulate.scenes import BUILTIN_SCENES, PHOTOS, PROCEDURAL, ImageScene, SceneSpec, photo
from hbis_torch.simulate.sensor import SensorModel, expose, normalise

DEFAULT_SCENES = PROCEDURAL + PHOTOS


@dataclass(frozen=True)
class DatasetConfig:
    """What :class:`SyntheticStacks` draws from. Ranges are (low, high), drawn uniformly unless
    a name says ``log`` (log-uniform).

    Attributes
    ----------
    length : int
        Number of items.
    crop : (int, int)
        (width, height) of the frames in sensor pixels.
    h_choices : tuple of int
        Resolution improvement factors (one per item, uniform); F = h * h frames.
    initial_phases : tuple of (float, float)
        Initial (reference) phases of the scans, degrees; the paper's three examples by default.
    scenes : tuple of str
        Scene kinds: names of BUILTIN_SCENES (photographs get random crops).
    edge_probability : float
        Per axis, the chance that the crop touches a sensor edge.
    full_well_log : (float, float)
        Full well in electrons (sets the shot noise), log-uniform.
    read_noise : (float, float)
        Read noise in electrons.
    exposure : (float, float)
        Fraction of the full well reached by a white scene.
    black_level : (float, float)
        Black level as a fraction of the white level.
    bit_depths : tuple of int
        ADC bit depths.
    fill_factor : (float, float)
        Pixel fill factor.
    defocus_um : (float, float)
        Sensor defocus in micrometres (0, 0: always in focus).
    phase_error_deg : (float, float)
        Range of the standard deviation of the prisms' phase errors.
    photo_pixel : (float, float)
        Size of a photograph's pixel as a fraction of the ground-truth pitch p/h, log-uniform.
    margin_px : float
        Forward model margin (render_scan).
    seed : int
    system : System
    """

    length: int = 100_000
    crop: tuple[int, int] = (64, 64)
    h_choices: tuple[int, ...] = (4,)
    initial_phases: tuple[tuple[float, float], ...] = ((5.0, 70.0), (45.0, 130.0), (80.0, 20.0))
    scenes: tuple[str, ...] = DEFAULT_SCENES
    edge_probability: float = 0.25
    full_well_log: tuple[float, float] = (1000.0, 40000.0)
    read_noise: tuple[float, float] = (0.5, 8.0)
    exposure: tuple[float, float] = (0.4, 1.0)
    black_level: tuple[float, float] = (0.0, 0.06)
    bit_depths: tuple[int, ...] = (10, 12)
    fill_factor: tuple[float, float] = (0.5, 1.0)
    defocus_um: tuple[float, float] = (0.0, 0.0)
    phase_error_deg: tuple[float, float] = (0.0, 0.002)
    photo_pixel: tuple[float, float] = (0.5, 1.5)
    margin_px: float = 4.0
    seed: int = 0
    system: System = field(default_factory=System)

    def __post_init__(self) -> None:
        cam = self.system.camera
        w, h = self.crop
        if not (1 <= w <= cam.cols and 1 <= h <= cam.rows):
            raise HbisInputError(f"crop {self.crop} does not fit the {cam.cols} x {cam.rows} sensor")
        if not self.h_choices or any(int(x) != x or x < 1 for x in self.h_choices):
            raise HbisInputError(f"h_choices must be integers >= 1, got {self.h_choices}")
        unknown = [s for s in self.scenes if s not in BUILTIN_SCENES]
        if unknown or not self.scenes:
            raise HbisInputError(f"unknown scene kind(s) {unknown}; choose from {', '.join(BUILTIN_SCENES)}")
        if self.length < 1:
            raise HbisInputError(f"length must be at least 1, got {self.length}")


@lru_cache(maxsize=64)
def _plan(system: System, h: int, initial: tuple[float, float]):
    from hbis_torch.scan import plan_scan

    return plan_scan(system, h, initial)


def _uniform(rng, bounds) -> float:
    lo, hi = bounds
    return float(lo if hi <= lo else rng.uniform(lo, hi))


def _log_uniform(rng, bounds) -> float:
    lo, hi = bounds
    return float(lo if hi <= lo else math.exp(rng.uniform(math.log(lo), math.log(hi))))


def _photo_scene(name: str, region_mm: tuple[float, float], pixel_mm: float, rng) -> ImageScene:
    """A random crop of a photograph with pixels of about ``pixel_mm``, in a random orientation."""
    image = photo(name)
    if rng.random() < 0.5:
        image = image.T
    image = image[:: rng.choice([-1, 1]), :: rng.choice([-1, 1])]
    rows, cols = image.shape
    # no smaller pixels than the photo can cover the region with
    pixel_mm = max(pixel_mm, region_mm[0] / cols, region_mm[1] / rows)
    need_c = min(cols, math.ceil(region_mm[0] / pixel_mm))
    need_r = min(rows, math.ceil(region_mm[1] / pixel_mm))
    top = int(rng.integers(0, rows - need_r + 1))
    left = int(rng.integers(0, cols - need_c + 1))
    crop = np.ascontiguousarray(image[top:top + need_r, left:left + need_c])
    return ImageScene(size_mm=(need_c * pixel_mm, need_r * pixel_mm), image=torch.from_numpy(crop), name=name)


@dataclass
class RenderedItem:
    """One item before it becomes tensors: its draw, phases, noise-free render and frames."""

    draw: "Draw"
    phases: torch.Tensor  # (F, 2) planned (recorded) phases, degrees
    true_phases: torch.Tensor  # (F, 2) phases rendered (planned + error)
    reference_index: int
    rendered: object  # RenderedScan of the true phases
    measured_positions: torch.Tensor  # (F, H, W, 2) roi-local, from the planned phases
    frames: np.ndarray  # (F, H, W) stored frames (uint8/uint16)


@dataclass
class Draw:
    """Everything drawn for one item (kept for the validation set's index)."""

    h: int
    initial_phases: tuple[float, float]
    roi: tuple[int, int, int, int]
    scene: str
    sensor: SensorModel
    exposure: float
    phase_error_deg: float
    noise_seed: int
    scene_seed: int
    photo_pixel_mm: float

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["sensor"] = self.sensor.to_dict()
        return d


class SyntheticStacks(Dataset):
    """On-the-fly synthetic stacks for training (see the module docstring).

    Parameters
    ----------
    config : DatasetConfig
    """

    def __init__(self, config: DatasetConfig = DatasetConfig()):
        self.config = config

    def __len__(self) -> int:
        return self.config.length

    def _rng(self, index: int) -> np.random.Generator:
        if not 0 <= index < len(self):
            raise IndexError(f"index {index} out of range for {len(self)} items")
        return np.random.default_rng([self.config.seed, index])

    def h_of(self, index: int) -> int:
        """The h of item ``index`` (cheap: the first draw of its generator)."""
        return int(self._rng(index).choice(self.config.h_choices))


    def draw(self, index: int) -> Draw:
        """The random choices of item ``index`` (cheap: no scene is built)."""
        cfg = self.config
        rng = self._rng(index)
        h = int(rng.choice(cfg.h_choices))
        initial = tuple(cfg.initial_phases[int(rng.integers(len(cfg.initial_phases)))])
        cam = cfg.system.camera
        w, hh = cfg.crop
        corner = []
        for span, size in ((cam.cols, w), (cam.rows, hh)):
            if rng.random() < cfg.edge_probability:
                corner.append(0 if rng.random() < 0.5 else span - size)
            else:
                corner.append(int(rng.integers(0, span - size + 1)))
        bits = int(rng.choice(cfg.bit_depths))
        sensor = SensorModel(
            fill_factor=_uniform(rng, cfg.fill_factor),
            defocus_um=_uniform(rng, cfg.defocus_um),
            full_well_e=_log_uniform(rng, cfg.full_well_log),
            read_noise_e=_uniform(rng, cfg.read_noise),
            black_level_dn=float(round(_uniform(rng, cfg.black_level) * (2**bits - 1))),
            bit_depth=bits,
        )
        return Draw(
            h=h,
            initial_phases=initial,
            roi=(corner[0], corner[1], w, hh),
            scene=cfg.scenes[int(rng.integers(len(cfg.scenes)))],
            sensor=sensor,
            exposure=_uniform(rng, cfg.exposure),
            phase_error_deg=_uniform(rng, cfg.phase_error_deg),
            noise_seed=int(rng.integers(2**62)),
            scene_seed=int(rng.integers(2**62)),
            photo_pixel_mm=_log_uniform(rng, cfg.photo_pixel) * cfg.system.object_pixel_mm / h,
        )

    def scene(self, draw: Draw):
        """The (unplaced) scene of a draw: it covers the crop's view with room for the scan,
        the margin and the PSF's tails."""
        cfg = self.config
        rng = np.random.default_rng(draw.scene_seed)
        pixel_mm = cfg.system.object_pixel_mm
        w, hh = cfg.crop
        region = ((w + 2 * (cfg.margin_px + 4)) * pixel_mm, (hh + 2 * (cfg.margin_px + 4)) * pixel_mm)
        if draw.scene in PHOTOS:
            return _photo_scene(draw.scene, region, draw.photo_pixel_mm, rng)
        detail = pixel_mm / (draw.h * grid_factor(draw.h))
        return BUILTIN_SCENES[draw.scene](SceneSpec(region, pixel_mm, detail), rng)

    def render(self, index: int) -> RenderedItem:
        """Item ``index`` rendered and exposed (see :class:`RenderedItem`)."""
        cfg = self.config
        draw = self.draw(index)
        scene = self.scene(draw)
        plan = _plan(cfg.system, draw.h, draw.initial_phases)
        generator = torch.Generator().manual_seed(draw.noise_seed)
        phases = plan.phases_deg
        true_phases = phases
        if draw.phase_error_deg > 0:
            jitter = draw.phase_error_deg * torch.randn(phases.shape, generator=generator, dtype=torch.float64)
            jitter[plan.reference_index] = 0.0
            true_phases = phases + jitter
        # positions of the true and of the planned phases in one call (the planned ones are what a
        # reconstructor computes from the stack); the reference frame has no error in both
        n = phases.shape[0]
        both = sample_positions(cfg.system, torch.cat((true_phases, phases)), plan.reference_index, draw.roi)
        rendered = render_scan(scene, cfg.system, true_phases, plan.reference_index, draw.h, draw.roi,
                               draw.sensor, margin_px=cfg.margin_px, positions=both[:n])
        rendered.irradiance.mul_(draw.exposure)
        rendered.truth.mul_(draw.exposure)
        frames = expose(rendered.irradiance, draw.sensor, generator)
        return RenderedItem(draw, phases, true_phases, plan.reference_index, rendered, both[n:], frames)

    def __getitem__(self, index: int) -> dict:
        """One training item.

        Returns
        -------
        dict with
            frames : (F, H, W) float32 in [0, 1], normalised as Stack.to_float does (noisy);
            positions : (F, H, W, 2) float32, roi-local sample positions computed from the
                recorded (planned) phases, what a reconstructor would use;
            true_positions : (F, H, W, 2) float32, the positions of the phases actually rendered;
            truth : (h*H, h*W) float32 in [0, 1];
            reference_index, h : int64 scalars;
            roi : (4,) int64; phases_deg : (F, 2) float64 (recorded);
            full_well_e, read_noise_e, exposure : float32 scalars (the noise drawn).
        """
        cfg = self.config
        item = self.render(index)
        draw = item.draw
        return {
            "frames": normalise(item.frames, draw.sensor),
            "positions": item.measured_positions.float(),
            "true_positions": item.rendered.positions.float(),
            "truth": item.rendered.truth,
            "reference_index": torch.tensor(item.reference_index),
            "h": torch.tensor(draw.h),
            "roi": torch.tensor(draw.roi),
            "phases_deg": item.phases.clone(),
            "full_well_e": torch.tensor(draw.sensor.full_well_e, dtype=torch.float32),
            "read_noise_e": torch.tensor(draw.sensor.read_noise_e, dtype=torch.float32),
            "exposure": torch.tensor(draw.exposure, dtype=torch.float32),
        }

    def stack(self, index: int) -> tuple[Stack, np.ndarray, Draw]:
        """Item ``index`` as an hbis-stack/1 Stack (integer frames), its truth, and its draw."""
        cfg = self.config
        item = self.render(index)
        draw = item.draw
        record = {"dataset_seed": cfg.seed, "index": int(index), **draw.to_dict()}
        if item.true_phases is not item.phases:
            record["true_phases_deg"] = item.true_phases.tolist()
        meta = make_meta(cfg.system, draw.h, draw.roi, item.phases.numpy(), bit_depth=draw.sensor.bit_depth,
                         reference_index=item.reference_index, black_level=draw.sensor.black_level_dn,
                         simulation=record)
        return Stack(item.frames, meta).validate("synthetic stack"), item.rendered.truth.numpy(), draw


class SameHBatchSampler(Sampler):
    """Batches of indices whose items share h (so their tensors stack), shuffled per epoch.

    Parameters
    ----------
    dataset : SyntheticStacks
    batch_size : int
    shuffle : bool
        Shuffle indices (and batches) with ``seed + epoch``; call :meth:`set_epoch` each epoch.
    drop_last : bool
    seed : int
    """

    def __init__(self, dataset: SyntheticStacks, batch_size: int, shuffle: bool = True,
                 drop_last: bool = False, seed: int = 0):
        if batch_size < 1:
            raise HbisInputError(f"batch size must be at least 1, got {batch_size}")
        self.dataset, self.batch_size, self.shuffle, self.drop_last, self.seed = (
            dataset, batch_size, shuffle, drop_last, seed)
        self.epoch = 0
        self._groups: dict[int, list[int]] | None = None

    def set_epoch(self, epoch: int) -> None:
        self.epoch = int(epoch)

    def _by_h(self) -> dict[int, list[int]]:
        if self._groups is None:
            groups: dict[int, list[int]] = {}
            for i in range(len(self.dataset)):
                groups.setdefault(self.dataset.h_of(i), []).append(i)
            self._groups = groups
        return self._groups

    def _batches(self) -> list[list[int]]:
        rng = np.random.default_rng([self.seed, self.epoch])
        batches = []
        for indices in self._by_h().values():
            order = rng.permutation(indices).tolist() if self.shuffle else list(indices)
            for start in range(0, len(order), self.batch_size):
                batch = order[start:start + self.batch_size]
                if len(batch) == self.batch_size or not self.drop_last:
                    batches.append(batch)
        if self.shuffle:
            batches = [batches[i] for i in rng.permutation(len(batches))]
        return batches

    def __iter__(self):
        return iter(self._batches())

    def __len__(self) -> int:
        return len(self._batches())
