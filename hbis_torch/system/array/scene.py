"""A wide planar scene for the array: a wall of real photographs plus moving objects.

The scene is the plane z = v (``FoveaSystem.object_distance_mm``) in the fovea's frame, the same plane
the fovea's landing maps use, so every camera's view of it is a homography of the others (the
nine cameras are modelled as sharing one centre of projection). Positions on the plane are
(x, y) in mm; images are float32 grey levels in [0, 1], geometry float64.

A texture layer covers a rectangle of the plane with square texels; sampling it at points
spaced ``footprint_mm`` apart first resamples the texture (antialiased) to texels no finer than
half the footprint, so views do not alias: this is the ideal, band-limited scene a sensor
model then integrates, blurs and digitises.

There is one family of scenes: a :class:`PlanarScene` is a scene that changes with time, and
:meth:`PlanarScene.at` freezes it into a :class:`hbis_torch.simulate.Scene`, which the fovea's
forward model renders like any built-in scene.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from hbis_torch.errors import HbisInputError
from hbis_torch.simulate import Scene

#: skimage.data photographs used for the default wall (all ship with scikit-image, no download).
WALL_PHOTOS = (
    "astronaut", "coffee", "chelsea", "rocket",
    "stereo_motorcycle", "camera", "coins", "hubble_deep_field",
    "clock", "immunohistochemistry", "moon", "cat",
)


def photograph(name: str) -> np.ndarray:
    """A scikit-image sample photograph as a float32 grey image (H, W) in [0, 1]."""
    import skimage.color
    import skimage.data

    loader = getattr(skimage.data, name, None)
    if loader is None:
        raise HbisInputError(f"scikit-image ships no sample image called {name!r}")
    image = loader()
    if isinstance(image, tuple):  # stereo pairs: keep the left view
        image = image[0]
    image = np.asarray(image)
    if image.ndim == 3:
        image = skimage.color.rgb2gray(image[..., :3])
    image = image.astype(np.float32)
    if image.max() > 1.0:
        image = image / 255.0
    return np.clip(image, 0.0, 1.0)


@dataclass
class TextureLayer:
    """A grey texture covering the plane rectangle that starts at ``origin_mm`` (its top-left
    corner, smallest x and y) and spans ``texel_mm`` per texel.

    Attributes
    ----------
    image : Tensor, shape (H, W), float32 in [0, 1]
    origin_mm : (x0, y0) in mm
    texel_mm : float, texel size in mm
    """

    image: Tensor
    origin_mm: tuple[float, float]
    texel_mm: float
    _levels: dict = field(default_factory=dict, repr=False)

    def __post_init__(self) -> None:
        self.image = torch.as_tensor(self.image, dtype=torch.float32)
        if self.image.ndim != 2 or min(self.image.shape) < 2:
            raise HbisInputError(f"a texture must be a 2-D image, got shape {tuple(self.image.shape)}")
        if not torch.isfinite(self.image).all():
            raise HbisInputError("a texture contains NaN or inf")
        if not (math.isfinite(self.texel_mm) and self.texel_mm > 0):
            raise HbisInputError(f"texel size must be positive, got {self.texel_mm!r}")

    @property
    def size_mm(self) -> tuple[float, float]:
        """(width, height) in mm."""
        return self.image.shape[1] * self.texel_mm, self.image.shape[0] * self.texel_mm

    def _level(self, footprint_mm: float) -> Tensor:
        """The texture resampled to texels of about footprint/2 (powers of sqrt 2, cached)."""
        ratio = footprint_mm / (2.0 * self.texel_mm)
        if ratio <= 1.0:
            return self.image
        step = round(2.0 * math.log2(ratio)) / 2.0  # quantise so that the cache stays small
        if step not in self._levels:
            factor = 2.0 ** -step
            size = [max(2, round(s * factor)) for s in self.image.shape]
            self._levels[step] = F.interpolate(
                self.image[None, None], size=size, mode="bilinear", antialias=True, align_corners=False
            )[0, 0]
        return self._levels[step]

    def sample(self, points_mm: Tensor, footprint_mm: float, premultiplied_alpha: bool = False,
               origin_mm: tuple[float, float] | None = None):
        """Bilinear samples at plane points (..., 2) mm; zero outside the texture.

        Returns (...) float32 values and, with ``premultiplied_alpha``, the coverage (...) in
        [0, 1] as well (1 inside the texture, falling to 0 across its border). ``origin_mm``
        places the texture elsewhere for this call (moving objects).
        """
        level = self._level(footprint_mm)
        width, height = self.size_mm
        # float32 texture coordinates: 1e-7 of the texture's size, far below a texel.
        scale = torch.tensor([2.0 / width, 2.0 / height], dtype=torch.float32)
        offset = torch.tensor(self.origin_mm if origin_mm is None else origin_mm, dtype=torch.float32)
        grid = (points_mm.to(torch.float32) - offset) * scale - 1.0
        flat = grid.reshape(1, 1, -1, 2)
        planes = [level]
        if premultiplied_alpha:
            planes.append(torch.ones_like(level))
        stack = torch.stack(planes)[None]  # (1, C, H, W)
        out = F.grid_sample(stack, flat, mode="bilinear", padding_mode="zeros", align_corners=False)
        out = out[0, :, 0].reshape(len(planes), *points_mm.shape[:-1])
        return (out[0], out[1]) if premultiplied_alpha else out[0]


@dataclass
class Trajectory:
    """Piecewise-linear path of an object's centre on the plane: held before the first and
    after the last waypoint.

    Attributes
    ----------
    times_s : sequence of float, increasing
    points_mm : sequence of (x, y) in mm, one per time
    """

    times_s: tuple[float, ...]
    points_mm: tuple[tuple[float, float], ...]

    def __post_init__(self) -> None:
        t = np.asarray(self.times_s, dtype=np.float64)
        p = np.asarray(self.points_mm, dtype=np.float64)
        if t.ndim != 1 or len(t) < 1 or p.shape != (len(t), 2):
            raise HbisInputError("a trajectory needs one (x, y) point per time")
        if not (np.isfinite(t).all() and np.isfinite(p).all()):
            raise HbisInputError("a trajectory contains NaN or inf")
        if np.any(np.diff(t) <= 0):
            raise HbisInputError("trajectory times must increase strictly")

    def position(self, t_s: float) -> np.ndarray:
        """Centre (x, y) in mm at time ``t_s``, float64 array of shape (2,)."""
        t = np.asarray(self.times_s, dtype=np.float64)
        p = np.asarray(self.points_mm, dtype=np.float64)
        return np.array([np.interp(t_s, t, p[:, 0]), np.interp(t_s, t, p[:, 1])])


@dataclass
class MovingObject:
    """A photograph that moves across the scene (it is what the periphery detects).

    Attributes
    ----------
    texture : TextureLayer whose origin is ignored: the texture is centred on the trajectory.
    trajectory : Trajectory of its centre.
    name : str
    """

    texture: TextureLayer
    trajectory: Trajectory
    name: str = "object"

    def origin_at(self, t_s: float) -> tuple[float, float]:
        """Top-left corner (x, y) mm of the texture at time ``t_s``."""
        cx, cy = self.trajectory.position(t_s)
        w, h = self.texture.size_mm
        return float(cx - w / 2), float(cy - h / 2)


@dataclass
class PlanarScene:
    """The scene: a background texture and objects in front of it, on the plane z = distance.

    Attributes
    ----------
    background : TextureLayer
    objects : list of MovingObject
    distance_mm : float, the plane's distance from the (common) pupil
    """

    background: TextureLayer
    objects: list = field(default_factory=list)
    distance_mm: float = 50.0

    def render(self, points_mm: Tensor, footprint_mm: float, t_s: float = 0.0) -> Tensor:
        """Ideal scene radiance at plane points.

        Parameters
        ----------
        points_mm : Tensor, shape (..., 2), mm on the plane
        footprint_mm : float
            Spacing of the samples on the plane (sets the antialiasing).
        t_s : float
            Time in seconds (positions of the moving objects).

        Returns
        -------
        Tensor, shape (...), float32 in [0, 1]; zero outside every texture.
        """
        points_mm = torch.as_tensor(points_mm)
        if points_mm.ndim < 1 or points_mm.shape[-1] != 2:
            raise HbisInputError(f"points must have shape (..., 2), got {tuple(points_mm.shape)}")
        if not torch.isfinite(points_mm).all():
            raise HbisInputError("scene points contain NaN or inf")
        return self.add_objects(self.background.sample(points_mm, footprint_mm), points_mm,
                                footprint_mm, t_s)

    def add_objects(self, background: Tensor, points_mm: Tensor, footprint_mm: float,
                    t_s: float) -> Tensor:
        """Composite the objects, as they are at ``t_s``, over an already sampled background
        (..., float32) at the same points; lets a caller keep the static background."""
        image = background.clone()
        for obj in self.objects:
            origin = obj.origin_at(t_s)
            region = _covered_region(points_mm, origin, obj.texture.size_mm, footprint_mm)
            if region is None:
                continue
            value, alpha = obj.texture.sample(points_mm[region], footprint_mm, True, origin)
            image[region] = image[region] * (1.0 - alpha) + value
        return image.clamp(0.0, 1.0)

    def at(self, t_s: float, center_mm=(0.0, 0.0)) -> "SceneAtInstant":
        """The scene frozen at time ``t_s``, as the :class:`hbis_torch.simulate.Scene` the fovea's
        forward model renders; ``center_mm`` anchors its float32 local coordinates (put it near
        the region being simulated)."""
        return SceneAtInstant(size_mm=(1.0, 1.0), center_mm=tuple(center_mm), source=self, t_s=float(t_s))

    def object_position(self, t_s: float, index: int = 0) -> np.ndarray:
        """Centre (x, y) mm of object ``index`` at time ``t_s``."""
        return self.objects[index].trajectory.position(t_s)


def _covered_region(points_mm: Tensor, origin_mm, size_mm, margin_mm: float):
    """Index (slices) of the part of a (H, W, 2) point grid that can touch the rectangle at
    ``origin_mm`` of ``size_mm`` (w, h); None if no point does. Other shapes: everything."""
    if points_mm.ndim != 3:
        return (Ellipsis,)
    width, height = size_mm
    x0, y0 = origin_mm[0] - margin_mm, origin_mm[1] - margin_mm
    x, y = points_mm[..., 0], points_mm[..., 1]
    inside = (x >= x0) & (x <= x0 + width + 2 * margin_mm) & (y >= y0) & (y <= y0 + height + 2 * margin_mm)
    rows, cols = inside.any(dim=1).nonzero(), inside.any(dim=0).nonzero()
    if len(rows) == 0:
        return None
    return (slice(int(rows[0]), int(rows[-1]) + 1), slice(int(cols[0]), int(cols[-1]) + 1))


def _cover(image: np.ndarray, rows: int, cols: int) -> np.ndarray:
    """Resize (antialiased) to cover rows x cols, then crop the centre."""
    src = torch.as_tensor(image)[None, None]
    scale = max(rows / image.shape[0], cols / image.shape[1])
    size = [max(rows, math.ceil(image.shape[0] * scale)), max(cols, math.ceil(image.shape[1] * scale))]
    big = F.interpolate(src, size=size, mode="bilinear", antialias=True, align_corners=False)[0, 0]
    r0, c0 = (size[0] - rows) // 2, (size[1] - cols) // 2
    return big[r0:r0 + rows, c0:c0 + cols].numpy()


def photo_wall(extent_mm: tuple[float, float, float, float], texel_mm: float,
               grid: tuple[int, int] = (3, 4), photos=WALL_PHOTOS) -> TextureLayer:
    """A wall of photographs tiled rows x cols over ``extent_mm`` = (x0, x1, y0, y1).

    Each photograph is scaled to cover its tile and cropped; distinct photographs keep the
    wall free of repeats, which image-based stitching needs.
    """
    x0, x1, y0, y1 = (float(e) for e in extent_mm)
    if not (x1 > x0 and y1 > y0):
        raise HbisInputError(f"wall extent {extent_mm!r} is empty")
    n_rows, n_cols = grid
    if n_rows * n_cols > len(photos):
        raise HbisInputError(f"a {n_rows} x {n_cols} wall needs {n_rows * n_cols} photographs")
    tile_r = math.ceil((y1 - y0) / texel_mm / n_rows)
    tile_c = math.ceil((x1 - x0) / texel_mm / n_cols)
    wall = np.zeros((tile_r * n_rows, tile_c * n_cols), dtype=np.float32)
    for k in range(n_rows * n_cols):
        r, c = divmod(k, n_cols)
        wall[r * tile_r:(r + 1) * tile_r, c * tile_c:(c + 1) * tile_c] = _cover(
            photograph(photos[k]), tile_r, tile_c)
    # Centre the (slightly larger, whole-texel) wall on the requested extent.
    cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
    origin = (cx - wall.shape[1] * texel_mm / 2, cy - wall.shape[0] * texel_mm / 2)
    return TextureLayer(torch.from_numpy(wall), origin, texel_mm)


def photo_object(name: str, texel_mm: float, trajectory: Trajectory, border: int = 4) -> MovingObject:
    """A photograph as a moving object, with a dark frame of ``border`` texels (a sign board)."""
    image = photograph(name)
    if border > 0:
        image = np.pad(image, border, constant_values=0.05)
    return MovingObject(TextureLayer(torch.from_numpy(image), (0.0, 0.0), texel_mm), trajectory, name)


@dataclass(frozen=True)
class SceneAtInstant(Scene):
    """The array's :class:`PlanarScene` at one time, as a ``hbis_torch.simulate.Scene``.

    ``center_mm`` only anchors the simulator's float32 local coordinates (put it near the
    ROI); ``size_mm`` is nominal, the scene covers the whole plane.
    """

    source: PlanarScene | None = field(default=None, compare=False)
    t_s: float = 0.0
    name: str = "hbis-array-scene"

    def value(self, x: Tensor, y: Tensor, spacing_mm: float | None = None) -> Tensor:
        cx, cy = self.center_mm or (0.0, 0.0)
        points = torch.stack(torch.broadcast_tensors(x.double() + cx, y.double() + cy), dim=-1)
        return self.source.render(points, spacing_mm or 1e-6, self.t_s)
