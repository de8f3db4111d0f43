"""Scenes on the object plane: grey levels in [0, 1] over (x, y) in mm.

Every scene knows its physical size (``size_mm`` = (width, height)) and where its centre sits on
the object plane (``center_mm``; None lets the simulator centre it on the view of the region of
interest). Image x grows with the column and y with the row, as sensor u and v do (docs/design.md
section 1), so an image appears upright in the frames.

Procedural patterns (Siemens star, bar target, edges, gradients, gratings) are evaluated
analytically at any point; patterns that are easier to draw than to write as a formula (words,
noise textures) and photographs are :class:`ImageScene` rasters, interpolated bilinearly.

:meth:`Scene.sample` takes the spacing of the points it is asked for and averages the scene over a
cell of that size (supersampling for analytic scenes with edges, a mip level for rasters), so that
sharp patterns do not alias on the simulator's grid.

Built-in scenes by name: :data:`BUILTIN_SCENES`; :func:`load_scene` also takes an image path.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from hbis_torch.errors import HbisInputError

Size = tuple[float, float]

PHOTOS = (
    "camera", "astronaut", "brick", "grass", "gravel", "coffee", "chelsea", "moon", "page",
    "text", "coins", "rocket", "immunohistochemistry", "hubble_deep_field", "clock", "cell",
)
"""Photographs from skimage.data that ship with scikit-image (no download needed)."""


def _check_size(size_mm) -> Size:
    try:
        w, h = (float(s) for s in size_mm)
    except (TypeError, ValueError):
        raise HbisInputError(f"scene size must be (width, height) in mm, got {size_mm!r}")
    if not (math.isfinite(w) and math.isfinite(h) and w > 0 and h > 0):
        raise HbisInputError(f"scene size must be two positive numbers of mm, got {size_mm!r}")
    return (w, h)


def box_interval(t: Tensor, half, width) -> Tensor:
    """The indicator of |t| <= half averaged over a window of ``width`` centred on t (exact).

    ``half`` is a number or a tensor like ``t``; ``width`` None or 0 gives the indicator itself.
    The average is the length of [t - width/2, t + width/2] inside [-half, half], over width,
    written with the indicator's integral ``P(z) = clamp(z + half, 0, 2 half)``.
    """
    if not width:
        return (t.abs() <= half).to(t.dtype)
    full = torch.as_tensor(2 * half, dtype=t.dtype)

    def integral(z):
        return torch.minimum(torch.clamp(z + half, min=0.0), full)

    return (integral(t + 0.5 * width) - integral(t - 0.5 * width)) / width


def square_edge_coverage(t: Tensor, angle_rad, side: float | None) -> Tensor:
    """Fraction of a square cell of ``side`` (axis aligned) on the positive side of a straight
    edge whose normal makes ``angle_rad`` (a number or a tensor like ``t``) with +x, ``t`` being
    the cell centre's signed distance to the edge.

    Exact: the step is averaged by the two boxes the square projects to along the normal, of
    widths side |cos| and side |sin|, whose convolution is a trapezoid with a piecewise quadratic
    integral.
    """
    if not side:
        return (t >= 0).to(t.dtype)
    c = torch.as_tensor(angle_rad, dtype=t.dtype)
    cos, sin = torch.cos(c).abs(), torch.sin(c).abs()
    a = side * torch.maximum(cos, sin)
    b = (side * torch.minimum(cos, sin)).clamp(min=1e-9 * side)
    u = t.abs()
    inner = 0.5 + u / a  # on the flat top of the trapezoid, |t| <= (a - b) / 2
    outer = 1.0 - torch.clamp((a + b) / 2 - u, min=0.0) ** 2 / (2 * a * b)
    cover = torch.where(u <= (a - b) / 2, inner, outer)
    return torch.where(t >= 0, cover, 1.0 - cover)


def soft_step(t: Tensor, angle_rad, side: float | None) -> Tensor:
    """:func:`square_edge_coverage`, computed only where the cell can straddle the edge
    (|t| < side; elsewhere the hard step is exact): the same values, much less work."""
    hard = (t >= 0).to(t.dtype)
    if not side:
        return hard
    near = (t.abs() < side).nonzero(as_tuple=True)
    if near[0].numel():
        angle = angle_rad[near] if torch.is_tensor(angle_rad) else angle_rad
        hard[near] = square_edge_coverage(t[near], angle, side)
    return hard


@dataclass(frozen=True)
class Scene:
    """A grey-level pattern on the object plane (base class).

    Attributes
    ----------
    size_mm : (float, float)
        Width and height on the object plane, mm.
    center_mm : (float, float) or None
        Object-plane position of the scene's centre, mm (None: centred on the view).
    name : str
        Short description, stored in the stack's metadata.
    antialias : int
        For subclasses whose :meth:`value` ignores ``spacing_mm``: supersamples per axis that
        :meth:`sample` averages instead (1: none).
    """

    size_mm: Size = (1.0, 1.0)
    center_mm: tuple[float, float] | None = None
    name: str = "scene"
    antialias: int = 1

    def value(self, x: Tensor, y: Tensor, spacing_mm: float | None = None) -> Tensor:
        """Grey level at scene-local coordinates (mm from the centre), same shape as x and y.

        With ``spacing_mm`` the value is the average over the square cell of that side centred
        on the point (analytically where the pattern allows).
        """
        raise NotImplementedError

    def placed_at(self, center_mm) -> "Scene":
        """A copy of the scene whose centre is at ``center_mm`` on the object plane."""
        return dataclasses.replace(self, center_mm=(float(center_mm[0]), float(center_mm[1])))

    def sample(self, points_mm: Tensor, spacing_mm: float | None = None, relative: bool = False) -> Tensor:
        """Grey levels at object-plane points.

        Parameters
        ----------
        points_mm : Tensor, shape (..., 2)
            (x, y) on the object plane, mm (float64: the centre is subtracted in float64, the
            pattern is then evaluated in float32, about 1e-6 mm on a scene of 10 mm).
        spacing_mm : float or None
            Spacing of the points; when given, each value is the scene averaged over a square
            cell of that side, so that sharp patterns do not alias.
        relative : bool
            The points are already relative to the scene's centre (scene-local coordinates).

        Returns
        -------
        Tensor, shape (...), float32, in [0, 1]
        """
        center = (0.0, 0.0) if relative else (self.center_mm or (0.0, 0.0))
        x = (points_mm[..., 0] - center[0]).to(torch.float32)
        y = (points_mm[..., 1] - center[1]).to(torch.float32)
        k = self.antialias if spacing_mm else 1
        if k <= 1:
            return self.value(x, y, spacing_mm).to(torch.float32).clamp(0.0, 1.0)
        total = torch.zeros(x.shape, dtype=torch.float32)
        offsets = ((torch.arange(k, dtype=torch.float64) + 0.5) / k - 0.5) * spacing_mm
        for dy in offsets.tolist():
            for dx in offsets.tolist():
                total += self.value(x + dx, y + dy, None)
        return (total / (k * k)).clamp(0.0, 1.0)


@dataclass(frozen=True)
class FlatScene(Scene):
    """A uniform grey level."""

    level: float = 0.5
    name: str = "flat"

    def value(self, x, y, spacing_mm=None):
        return torch.full(torch.broadcast_shapes(x.shape, y.shape), self.level, dtype=x.dtype)


@dataclass(frozen=True)
class GratingScene(Scene):
    """A sinusoidal grating ``mean + amplitude cos(2 pi (k . r) / period + phase)``.

    Cell averages are exact: the amplitude is multiplied by sinc(s kx) sinc(s ky).
    """

    period_mm: float = 0.05
    angle_deg: float = 0.0
    mean: float = 0.5
    amplitude: float = 0.4
    phase: float = 0.0
    name: str = "grating"

    def value(self, x, y, spacing_mm=None):
        a = math.radians(self.angle_deg)
        kx, ky = math.cos(a) / self.period_mm, math.sin(a) / self.period_mm
        amplitude = self.amplitude
        if spacing_mm:
            amplitude *= float(np.sinc(spacing_mm * kx) * np.sinc(spacing_mm * ky))
        return self.mean + amplitude * torch.cos(2 * math.pi * (x * kx + y * ky) + self.phase)


@dataclass(frozen=True)
class SiemensStar(Scene):
    """Binary Siemens star of ``spokes`` dark/bright pairs filling a disc of the scene's size.

    Cell averages use the signed arc distance to the nearest spoke edge (exact for cells small
    against the radius; near the centre, where spokes are finer than a cell, it tends to grey).
    """

    spokes: int = 36
    dark: float = 0.1
    bright: float = 0.9
    background: float = 0.5
    name: str = "siemens-star"

    def value(self, x, y, spacing_mm=None):
        radius = 0.5 * min(self.size_mm)
        r = torch.hypot(x, y)
        theta = torch.atan2(y, x)
        distance = r * torch.asin(torch.sin(self.spokes * theta).clamp(-1.0, 1.0)) / self.spokes
        # spoke edges are radial (normal: tangential), the rim is a circle (normal: radial)
        star = self.dark + (self.bright - self.dark) * soft_step(distance, theta + math.pi / 2, spacing_mm)
        inside = soft_step(radius - r, theta, spacing_mm)
        return self.background + inside * (star - self.background)


@dataclass(frozen=True)
class BarTarget(Scene):
    """USAF-style groups of three bars (vertical and horizontal) with widths from coarse to fine.

    The scene is a grid of ``columns`` x ``rows`` cells; cell i (raster order) holds a group of
    vertical bars left of its centre and one of horizontal bars right of it, bars of width
    ``bar_widths_mm[i]`` and length five widths. Cell averages are exact (separable boxes).
    """

    bar_widths_mm: tuple[float, ...] = (0.02, 0.01)
    columns: int = 2
    dark: float = 0.1
    bright: float = 0.9
    name: str = "bars"

    def value(self, x, y, spacing_mm=None):
        w, h = self.size_mm
        rows = math.ceil(len(self.bar_widths_mm) / self.columns)
        cw, ch = w / self.columns, h / rows
        col = torch.clamp(torch.floor((x + w / 2) / cw), 0, self.columns - 1)
        row = torch.clamp(torch.floor((y + h / 2) / ch), 0, rows - 1)
        index = (row * self.columns + col).long().clamp(max=len(self.bar_widths_mm) - 1)
        widths = torch.tensor(self.bar_widths_mm, dtype=x.dtype)[index]
        lx = x + w / 2 - (col + 0.5) * cw  # cell-local, centred
        ly = y + h / 2 - (row + 0.5) * ch
        ink = torch.zeros_like(lx)
        reach = 2.5 * widths + (0.5 * spacing_mm if spacing_mm else 0.0)
        for along, across in ((lx + 3.5 * widths, ly), (ly, lx - 3.5 * widths)):
            near = ((along.abs() <= reach) & (across.abs() <= reach)).nonzero(as_tuple=True)
            if not near[0].numel():
                continue
            a, c, wn = along[near], across[near], widths[near]
            bars = sum(box_interval(a - k * wn, 0.5 * wn, spacing_mm) for k in (-2, 0, 2))
            ink[near] += bars * box_interval(c, 2.5 * wn, spacing_mm)
        return self.bright - (self.bright - self.dark) * ink


@dataclass(frozen=True)
class EdgesScene(Scene):
    """Piecewise-constant regions cut by straight edges at arbitrary angles.

    Edge k is the line ``n_k . r = c_k``; a point's grey level is ``levels[code % len(levels)]``,
    ``code`` having bit k set on the positive side of edge k, so every edge is a sharp step.
    Cell averages are exact for a cell crossed by one edge (where edges cross, to first order).
    """

    normals_deg: tuple[float, ...] = (5.0, 95.0)
    offsets_mm: tuple[float, ...] = (0.0, 0.0)
    levels: tuple[float, ...] = (0.1, 0.9, 0.4, 0.7)
    name: str = "edges"

    def value(self, x, y, spacing_mm=None):
        levels = torch.tensor(self.levels, dtype=x.dtype)
        n = len(self.levels)
        code = torch.zeros(torch.broadcast_shapes(x.shape, y.shape), dtype=torch.long)
        distances = []
        for k, (angle, offset) in enumerate(zip(self.normals_deg, self.offsets_mm)):
            a = math.radians(angle)
            t = x * math.cos(a) + y * math.sin(a) - offset
            code = code | ((t >= 0).long() << k)
            distances.append((k, a, t))
        out = levels[code % n]
        if not spacing_mm:
            return out
        for k, a, t in distances:
            near = (t.abs() < spacing_mm).nonzero(as_tuple=True)  # cells this edge may cross
            if not near[0].numel():
                continue
            c = code[near]
            on, off = levels[(c | (1 << k)) % n], levels[(c & ~(1 << k)) % n]
            side = ((c >> k) & 1).to(x.dtype)
            out[near] += (on - off) * (square_edge_coverage(t[near], a, spacing_mm) - side)
        return out


@dataclass(frozen=True)
class GradientScene(Scene):
    """Smooth shading: a linear ramp, a radial term and two slow sinusoids."""

    ramp_deg: float = 30.0
    waves: tuple[float, float] = (3.0, 5.0)  # periods across the scene's width
    name: str = "gradient"

    def value(self, x, y, spacing_mm=None):
        w, h = self.size_mm
        a = math.radians(self.ramp_deg)
        ramp = (x * math.cos(a) + y * math.sin(a)) / max(w, h)
        radial = torch.hypot(x / w, y / h)
        wave = torch.sin(2 * math.pi * self.waves[0] * x / w) * torch.cos(2 * math.pi * self.waves[1] * y / w)
        return 0.5 + 0.35 * ramp - 0.2 * radial + 0.1 * wave


@dataclass(frozen=True)
class ImageScene(Scene):
    """A raster image (H, W) in [0, 1] spread over ``size_mm``; pixel (i, j) covers its cell.

    Read by bilinear interpolation; outside its extent the image is mirrored. Sampling with a
    spacing coarser than the raster pixel reads an area-averaged mip level, so fine rasters do
    not alias.
    """

    image: Tensor = field(default_factory=lambda: torch.zeros(1, 1))
    name: str = "image"

    def __post_init__(self) -> None:
        img = torch.as_tensor(self.image)
        if img.ndim != 2 or img.numel() == 0:
            raise HbisInputError(f"a scene image must be 2-D (rows, cols), got shape {tuple(img.shape)}")
        if not bool(torch.isfinite(img).all()):
            raise HbisInputError("the scene image contains NaN or infinite values")
        object.__setattr__(self, "image", img.to(torch.float32).clamp(0.0, 1.0))
        _check_size(self.size_mm)

    @property
    def pixel_mm(self) -> float:
        """Larger side of one raster pixel on the object plane, mm."""
        rows, cols = self.image.shape
        return max(self.size_mm[0] / cols, self.size_mm[1] / rows)

    def _level(self, spacing_mm: float | None) -> Tensor:
        img = self.image[None, None]
        if not spacing_mm:
            return img
        level = int(math.floor(math.log2(max(spacing_mm / self.pixel_mm, 1.0))))
        for _ in range(level):
            if min(img.shape[-2:]) < 2:
                break
            img = F.avg_pool2d(img, 2, ceil_mode=True)
        return img

    def value(self, x, y, spacing_mm=None):
        shape = torch.broadcast_shapes(x.shape, y.shape)
        gx = (2 / self.size_mm[0]) * x
        gy = (2 / self.size_mm[1]) * y
        grid = torch.stack(torch.broadcast_tensors(gx, gy), -1).reshape(1, 1, -1, 2).to(torch.float32)
        out = F.grid_sample(self._level(spacing_mm), grid, mode="bilinear",
                            padding_mode="reflection", align_corners=False)
        return out.reshape(shape)


# --------------------------------------------------------------------------------------------
# Rasters: photographs, files, words, textures


def to_gray(array) -> np.ndarray:
    """Any image array (gray, RGB, RGBA; bool, integer or float) as float32 gray in [0, 1]."""
    a = np.asarray(array)
    if a.dtype == bool:
        a = a.astype(np.float32)
    elif np.issubdtype(a.dtype, np.integer):
        a = a.astype(np.float32) / float(np.iinfo(a.dtype).max)
    else:
        a = a.astype(np.float32)
        top = float(np.nanmax(a)) if a.size else 1.0
        if top > 1.0:
            a = a / top
    if a.ndim == 3 and a.shape[-1] in (3, 4):
        a = a[..., :3] @ np.array([0.2125, 0.7154, 0.0721], dtype=np.float32)
    if a.ndim != 2:
        raise HbisInputError(f"expected a grayscale or RGB image, got shape {np.asarray(array).shape}")
    if not np.isfinite(a).all():
        raise HbisInputError("the image contains NaN or infinite values")
    return np.clip(a, 0.0, 1.0)


@lru_cache(maxsize=None)
def photo(name: str) -> np.ndarray:
    """A photograph from skimage.data as float32 gray in [0, 1] (cached)."""
    import skimage.data

    if name not in PHOTOS:
        raise HbisInputError(f"unknown photograph {name!r}; choose from {', '.join(PHOTOS)}")
    return to_gray(getattr(skimage.data, name)())


def read_image_file(path) -> np.ndarray:
    """An image file (PNG, JPEG, TIFF, ...) as float32 gray in [0, 1]."""
    path = Path(path)
    try:
        if path.suffix.lower() in (".tif", ".tiff"):
            import tifffile

            array = tifffile.imread(path)
            if array.ndim == 3 and array.shape[-1] not in (3, 4):
                array = array[0]  # first page of a stack
        else:
            from PIL import Image

            with Image.open(path) as image:
                if image.mode.startswith("I;16"):
                    array = np.asarray(image).astype(np.uint16)  # 16-bit: scaled by 65535
                else:
                    array = np.asarray(image)
    except FileNotFoundError:
        raise HbisInputError(f"{path}: no such image file") from None
    except Exception as exc:  # noqa: BLE001 - the readers raise many types for bad files
        raise HbisInputError(f"{path}: cannot read the image ({type(exc).__name__}: {exc})") from None
    return to_gray(array)


def cover_size(image_shape, footprint_mm: Size) -> Size:
    """Size (mm) at which an image of ``image_shape`` (rows, cols) just covers ``footprint_mm``,
    keeping its aspect ratio."""
    rows, cols = image_shape
    fw, fh = _check_size(footprint_mm)
    pixel = max(fw / cols, fh / rows)
    return (cols * pixel, rows * pixel)


WORDS = (
    "fovea", "prism", "risley", "pixel", "camera", "optics", "scan", "sensor", "lens", "field",
    "view", "image", "light", "wedge", "phase", "super", "resolution", "eye", "compound", "array",
    "HBIS", "zoom", "focus", "signal", "noise", "Quartz", "jumps", "OVER", "lazy", "dog",
    "Xylophone", "wizard", "BOX", "vexing", "jig", "47", "2024", "0.95", "f/1.4", "3.75um",
)


@lru_cache(maxsize=64)
def _font(size_px: int):
    from matplotlib import font_manager
    from PIL import ImageFont

    return ImageFont.truetype(font_manager.findfont("DejaVu Sans"), size_px)


def words_image(shape, letter_heights_px, count: int, rng: np.random.Generator) -> np.ndarray:
    """Random words at several sizes, as a float32 raster (rows, cols) in [0, 1].

    ``letter_heights_px`` is the (min, max) capital-letter height in raster pixels; sizes are
    drawn log-uniformly. The background is a random light or dark grey, text of random contrast.
    """
    from PIL import Image, ImageDraw

    rows, cols = (int(s) for s in shape)
    dark_text = rng.random() < 0.7
    background = rng.uniform(0.6, 0.95) if dark_text else rng.uniform(0.05, 0.4)
    canvas = Image.new("F", (cols, rows), float(background))
    draw = ImageDraw.Draw(canvas)
    lo, hi = (max(float(v), 1.0) for v in letter_heights_px)
    for _ in range(count):
        cap = math.exp(rng.uniform(math.log(lo), math.log(max(hi, lo))))
        font = _font(max(2, int(round(cap / 0.73))))
        word = WORDS[rng.integers(len(WORDS))]
        if rng.random() < 0.3:
            word = "".join(chr(c) for c in rng.integers(65, 91, size=rng.integers(2, 7)))
        ink = rng.uniform(0.0, background - 0.2) if dark_text else rng.uniform(background + 0.2, 1.0)
        left, top, right, bottom = font.getbbox(word)
        x = rng.uniform(-0.1 * (right - left), max(cols - 0.9 * (right - left), 1.0))
        y = rng.uniform(-top, max(rows - bottom, 1.0))
        draw.text((x, y), word, fill=float(ink), font=font)
    return np.clip(np.asarray(canvas, dtype=np.float32), 0.0, 1.0)


def texture_image(shape, correlation_px: float, rng: np.random.Generator, beta: float = 1.0) -> np.ndarray:
    """Random texture: Gaussian noise with a power-law spectrum (exponent ``beta``) above a
    correlation length, stretched to [0, 1], as a float32 raster."""
    rows, cols = (int(s) for s in shape)
    noise = rng.standard_normal((rows, cols))
    fy = np.fft.fftfreq(rows)[:, None]
    fx = np.fft.rfftfreq(cols)[None, :]
    f = np.hypot(fx, fy)
    f0 = 1.0 / max(correlation_px * 8.0, 2.0)
    amplitude = (f0**2 + f**2) ** (-beta / 2) * np.exp(-((f * correlation_px) ** 2))
    field_ = np.fft.irfft2(np.fft.rfft2(noise) * amplitude, s=(rows, cols))
    lo, hi = np.percentile(field_, [1, 99])
    contrast = rng.uniform(0.4, 1.0)
    out = 0.5 + contrast * ((field_ - lo) / max(hi - lo, 1e-12) - 0.5)
    return np.clip(out, 0.0, 1.0).astype(np.float32)


# --------------------------------------------------------------------------------------------
# Built-in scenes by name


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
            spec = dataclasses.replace(spec, size_mm=_check_size(size_mm))
        return BUILTIN_SCENES[name_or_path](spec, rng)
    if path.suffix or path.exists():
        image = read_image_file(path)
        if size_mm is None:
            size = cover_size(image.shape, spec.size_mm)
        elif np.isscalar(size_mm):
            size = (float(size_mm), float(size_mm) * image.shape[0] / image.shape[1])
        else:
            size = _check_size(size_mm)
        return ImageScene(size_mm=size, image=torch.from_numpy(image), name=path.name)
    raise HbisInputError(
        f"unknown scene {name_or_path!r}: give an image path or one of {', '.join(BUILTIN_SCENES)}"
    )
