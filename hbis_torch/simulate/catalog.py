"""Built-in scenes by name, fitted to the simulated view: :data:`BUILTIN_SCENES`, :func:`load_scene`.

A factory takes a :class:`SceneSpec` (the view's size and sampling) and a NumPy generator (the
random choices of procedural scenes) and returns a :class:`~hbis_torch.simulate.scenes.Scene`.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from hbis_torch.errors import HbisInputError
from hbis_torch.simulate.rasters import (
    PHOTOS,
    cover_size,
    photo,
    read_image_file,
    texture_image,
    words_image,
)
from hbis_torch.simulate.scenes import (
    BarTarget,
    EdgesScene,
    FlatScene,
    GradientScene,
    ImageScene,
    Scene,
    SiemensStar,
    Size,
    check_size,
)


@dataclass(frozen=True)
class SceneSpec:
    """What a scene factory needs to know to fit a pattern to the simulated view.

    Attributes
    ----------
    size_mm : (float, float)
        Object-plane size the scene should cover, mm.
    pixel_mm : float
        One sensor pixel on the object plane, mm (sets the feature sizes of patterns).
    detail_mm : float
        Finest spacing the simulator samples, mm (sets raster resolutions).
    """

    size_mm: Size
    pixel_mm: float
    detail_mm: float

    @classmethod
    def around_roi(cls, width: int, height: int, pixel_mm: float) -> "SceneSpec":
        """The view of a ``width`` x ``height`` px ROI with a 25 % margin (so the scene covers
        every frame of a scan), detail down to 1/16 of a pixel (``pixel_mm``: one sensor pixel
        on the object plane, mm)."""
        return cls(size_mm=(width * pixel_mm * 1.25, height * pixel_mm * 1.25), pixel_mm=pixel_mm,
                   detail_mm=pixel_mm / 16)

    def raster_shape(self, limit: int = 4096) -> tuple[int, int]:
        w, h = self.size_mm
        step = max(self.detail_mm, max(w, h) / limit)
        return max(8, int(math.ceil(h / step))), max(8, int(math.ceil(w / step)))


def _star(spec: SceneSpec, rng):
    return SiemensStar(size_mm=spec.size_mm, spokes=int(rng.choice([24, 36, 48, 72])))


def _bars(spec: SceneSpec, rng):
    # nine bar widths, geometric, from the largest that fits a cell (two groups of 5 x 5 widths
    # with gaps) down to a sixth of a sensor pixel
    cell = min(spec.size_mm[0] / 3, spec.size_mm[1] / 3)
    coarse = cell / 14
    fine = spec.pixel_mm / 6
    widths = tuple(coarse * (fine / coarse) ** (k / 8) for k in range(9))
    return BarTarget(size_mm=spec.size_mm, bar_widths_mm=widths, columns=3)


def _edges(spec: SceneSpec, rng):
    n = int(rng.integers(2, 6))
    w, h = spec.size_mm
    return EdgesScene(
        size_mm=spec.size_mm,
        normals_deg=tuple(float(a) for a in rng.uniform(0, 360, n)),
        offsets_mm=tuple(float(o) for o in rng.uniform(-0.3, 0.3, n) * min(w, h)),
        levels=tuple(float(v) for v in rng.uniform(0.05, 0.95, 2**n)),
    )


def _slanted_edge(spec: SceneSpec, rng):
    return EdgesScene(size_mm=spec.size_mm, normals_deg=(5.0,), offsets_mm=(0.0,), levels=(0.2, 0.8),
                      name="slanted-edge")


def _gradient(spec: SceneSpec, rng):
    return GradientScene(size_mm=spec.size_mm, ramp_deg=float(rng.uniform(0, 360)),
                         waves=(float(rng.uniform(1, 4)), float(rng.uniform(1, 4))))


def _flat(spec: SceneSpec, rng):
    return FlatScene(size_mm=spec.size_mm, level=0.5)


def _words(spec: SceneSpec, rng):
    shape = spec.raster_shape()
    per_px = spec.pixel_mm / (spec.size_mm[0] / shape[1])  # raster pixels per sensor pixel
    count = int(np.clip(spec.size_mm[0] * spec.size_mm[1] / (12 * spec.pixel_mm) ** 2, 4, 400))
    image = words_image(shape, (1.5 * per_px, 12 * per_px), count, rng)
    return ImageScene(size_mm=spec.size_mm, image=torch.from_numpy(image), name="words")


def _texture(spec: SceneSpec, rng):
    shape = spec.raster_shape()
    per_px = spec.pixel_mm / (spec.size_mm[0] / shape[1])
    image = texture_image(shape, correlation_px=float(rng.uniform(0.15, 1.0)) * per_px, rng=rng,
                          beta=float(rng.uniform(0.5, 1.5)))
    return ImageScene(size_mm=spec.size_mm, image=torch.from_numpy(image), name="texture")


def _photo_factory(name):
    def make(spec: SceneSpec, rng):
        image = photo(name)
        return ImageScene(size_mm=cover_size(image.shape, spec.size_mm), image=torch.from_numpy(image),
                          name=name)

    return make


BUILTIN_SCENES = {
    "siemens-star": _star,
    "bars": _bars,
    "edges": _edges,
    "slanted-edge": _slanted_edge,
    "gradient": _gradient,
    "words": _words,
    "texture": _texture,
    "flat": _flat,
    **{name: _photo_factory(name) for name in PHOTOS},
}
"""Factories ``(SceneSpec, numpy Generator) -> Scene`` of the scenes ``hbis simulate`` knows."""

PROCEDURAL = ("siemens-star", "bars", "edges", "slanted-edge", "gradient", "words", "texture")


def load_scene(name_or_path: str, spec: SceneSpec, seed: int = 0, size_mm=None) -> Scene:
    """A built-in scene by name, or an image file, fitted to ``spec``.

    Parameters
    ----------
    name_or_path : str
        A key of :data:`BUILTIN_SCENES` or the path of an image file (PNG, JPEG, TIFF, ...).
    spec : SceneSpec
        The view to cover and its sampling.
    seed : int
        Seed of the random choices of procedural scenes.
    size_mm : (float, float) or float or None
        Physical size of the scene (a single number: width, height from the aspect ratio for
        images, square otherwise). None: cover ``spec.size_mm``.
    """
    rng = np.random.default_rng(seed)
    path = Path(name_or_path)
    if name_or_path in BUILTIN_SCENES:
        if size_mm is not None:
            if np.isscalar(size_mm):
                size_mm = (float(size_mm), float(size_mm))
            spec = dataclasses.replace(spec, size_mm=check_size(size_mm))
        return BUILTIN_SCENES[name_or_path](spec, rng)
    if path.suffix or path.exists():
        image = read_image_file(path)
        if size_mm is None:
            size = cover_size(image.shape, spec.size_mm)
        elif np.isscalar(size_mm):
            size = (float(size_mm), float(size_mm) * image.shape[0] / image.shape[1])
        else:
            size = check_size(size_mm)
        return ImageScene(size_mm=size, image=torch.from_numpy(image), name=path.name)
    raise HbisInputError(
        f"unknown scene {name_or_path!r}: give an image path or one of {', '.join(BUILTIN_SCENES)}"
    )
