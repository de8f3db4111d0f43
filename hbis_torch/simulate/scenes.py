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

The rasters (photographs, image files, words, textures) are made in
:mod:`hbis_torch.simulate.rasters`; the built-in scenes by name (:data:`BUILTIN_SCENES`,
:func:`load_scene`, which also takes an image path) are :mod:`hbis_torch.simulate.catalog`.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from hbis_torch.errors import HbisInputError

Size = tuple[float, float]


def check_size(size_mm) -> Size:
    """``size_mm`` as (width, height) in mm, two positive finite numbers, else HbisInputError."""
    try:
        w, h = (float(s) for s in size_mm)
    except (TypeError, ValueError):
        raise HbisInputError(f"scene size must be (width, height) in mm, got {size_mm!r}")
    if not (math.isfinite(w) and math.isfinite(h) and w > 0 and h > 0):
        raise HbisInputError(f"scene size must be two positive numbers of mm, got {size_mm!r}")
    return (w, h)


def box_interval(t: Tensor, half, width) -> Tensor:
    """The indicator of abs(t) <= half averaged over a window of ``width`` centred on t (exact).

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
    widths side abs(cos) and side abs(sin), whose convolution is a trapezoid with a piecewise quadratic
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
    (abs(t) < side; elsewhere the hard step is exact): the same values, much less work."""
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

    Read by bilinear interpolation, or bicubic (``interpolation="bicubic"``, Keys' cubic as
    ``grid_sample``'s, clipped to [0, 1]: detail near the raster's Nyquist frequency less
    attenuated); outside its extent the image is mirrored. Sampling with a spacing coarser than
    the raster pixel reads an area-averaged mip level, so fine rasters do not alias.
    """

    image: Tensor = field(default_factory=lambda: torch.zeros(1, 1))
    name: str = "image"
    interpolation: str = "bilinear"

    def __post_init__(self) -> None:
        img = torch.as_tensor(self.image)
        if img.ndim != 2 or img.numel() == 0:
            raise HbisInputError(f"a scene image must be 2-D (rows, cols), got shape {tuple(img.shape)}")
        if not bool(torch.isfinite(img).all()):
            raise HbisInputError("the scene image contains NaN or infinite values")
        object.__setattr__(self, "image", img.to(torch.float32).clamp(0.0, 1.0))
        if self.interpolation not in ("bilinear", "bicubic"):
            raise HbisInputError(f"interpolation must be 'bilinear' or 'bicubic', got {self.interpolation!r}")
        check_size(self.size_mm)

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
        out = F.grid_sample(self._level(spacing_mm), grid, mode=self.interpolation,
                            padding_mode="reflection", align_corners=False)
        if self.interpolation == "bicubic":  # its overshoot past the raster's range is no light
            out = out.clamp(0.0, 1.0)
        return out.reshape(shape)
