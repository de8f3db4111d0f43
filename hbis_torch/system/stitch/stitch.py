"""Stitching the nine views into one panorama on the fovea's image plane.

Homographies map a view's pixel coordinates to the (parked) fovea's pixel coordinates at the
same binning: ``H_k = K R_k K^-1`` from the design (or assembly) rotations, or estimated from
the images (:mod:`hbis_torch.system.stitch.refine`). The panorama (the *canvas*) is the fovea's image
plane extended to hold every view, scaled by ``scale``: canvas pixel = ``canvas.A @`` fovea pixel.
Pixel coordinates are 0-based pixel centres throughout (Kornia's ``align_corners=True``).

Overlaps are blended by feathering: each view is weighted by a tent that falls to zero at its
borders, so seams fade instead of stepping.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from kornia.geometry.transform import warp_perspective
from torch import Tensor

from hbis_torch.errors import HbisInputError
from hbis_torch.registration.homography import apply_homography
from hbis_torch.system.array.cameras import CAMERA_NAMES, CameraArray


def design_homographies(array: CameraArray, binning: int = 1, rotations: Tensor | None = None) -> Tensor:
    """H_k = K R_k K^-1 (9, 3, 3) float64: view-k pixel -> fovea pixel, both binned by ``binning``.

    ``rotations`` defaults to the design's (what a stitcher knows without calibration); pass
    ``array.rotations`` for the true assembly.
    """
    k = array.intrinsics(binning)
    rot = array.design_rotations if rotations is None else rotations
    return k @ rot @ torch.linalg.inv(k)


def view_corners(view_shape: tuple[int, int]) -> Tensor:
    """The four outer pixel-edge corners (4, 2) of a (rows, cols) view, clockwise from top-left."""
    rows, cols = view_shape
    return torch.tensor([[-0.5, -0.5], [cols - 0.5, -0.5], [cols - 0.5, rows - 0.5], [-0.5, rows - 0.5]],
                        dtype=torch.float64)


# A warped corner farther than this (px) is a homography that sends the view (nearly) to
# infinity: no canvas can hold it.
MAX_OUTLINE_PX = 1e7


def view_outlines(homographies: Tensor, view_shape: tuple[int, int]) -> Tensor:
    """Where homographies (F, 3, 3) send a view's corners: (F, 4, 2) float64, or HbisInputError
    if a corner goes (nearly) to infinity."""
    outlines = apply_homography(homographies.to(torch.float64), view_corners(view_shape))
    if not bool(torch.isfinite(outlines).all()) or float(outlines.abs().max()) > MAX_OUTLINE_PX:
        raise HbisInputError("a view's corner maps to infinity under its homography")
    return outlines


@dataclass(frozen=True)
class Canvas:
    """The panorama's pixel grid: canvas pixel = A @ fovea pixel (binned fovea grid).

    Attributes
    ----------
    A : Tensor (3, 3) float64, a scale and a translation
    shape : (rows, cols)
    focal_px : float, the focal length in canvas pixels
    axis_px : (x, y), canvas coordinates of the fovea's original optical axis
    """

    A: Tensor
    shape: tuple[int, int]
    focal_px: float
    axis_px: tuple[float, float]

    def angle_deg(self, coord, axis: str) -> Tensor:
        """Field angle (deg) of canvas coordinate(s) along 'x' or 'y', measured at the axis."""
        c = self.axis_px[0 if axis == "x" else 1]
        return torch.rad2deg(torch.atan((torch.as_tensor(coord, dtype=torch.float64) - c) / self.focal_px))

    def from_directions(self, directions: Tensor) -> Tensor:
        """Canvas pixels (..., 2) of directions (..., 3) in the fovea's frame (z > 0)."""
        xy = directions[..., :2] / directions[..., 2:3]
        return xy * self.focal_px + torch.tensor(self.axis_px, dtype=xy.dtype)

    def to_directions(self, pixels: Tensor) -> Tensor:
        """Unnormalised directions (x/z, y/z, 1) (..., 3) of canvas pixels (..., 2)."""
        xy = (pixels - torch.tensor(self.axis_px, dtype=pixels.dtype)) / self.focal_px
        return torch.cat((xy, torch.ones_like(xy[..., :1])), dim=-1)


def make_canvas(array: CameraArray, homographies: Tensor, binning: int = 1, scale: float = 1.0) -> Canvas:
    """The smallest canvas that holds every view's warped outline, at ``scale`` canvas pixels
    per (binned) fovea pixel."""
    if not (math.isfinite(scale) and scale > 0):
        raise HbisInputError(f"scale must be positive, got {scale!r}")
    k = array.intrinsics(binning)
    corners = view_outlines(homographies, array.view_shape(binning))
    lo = corners.reshape(-1, 2).amin(0) * scale
    hi = corners.reshape(-1, 2).amax(0) * scale
    x0, y0 = math.floor(float(lo[0])), math.floor(float(lo[1]))
    shape = (math.ceil(float(hi[1])) - y0 + 1, math.ceil(float(hi[0])) - x0 + 1)
    A = torch.tensor([[scale, 0.0, -x0], [0.0, scale, -y0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    axis = (scale * float(k[0, 2]) - x0, scale * float(k[1, 2]) - y0)
    return Canvas(A=A, shape=shape, focal_px=float(k[0, 0]) * scale, axis_px=axis)


def feather_weights(view_shape: tuple[int, int]) -> Tensor:
    """Tent weights (rows, cols) float32: 1 at the centre, falling linearly to ~0 at the edges."""
    rows, cols = view_shape
    wy = 1.0 - (torch.arange(rows, dtype=torch.float32) - (rows - 1) / 2).abs() / (rows / 2)
    wx = 1.0 - (torch.arange(cols, dtype=torch.float32) - (cols - 1) / 2).abs() / (cols / 2)
    return wy[:, None] * wx[None, :]


@dataclass
class Panorama:
    """A stitched panorama.

    Attributes
    ----------
    image : Tensor (rows, cols) float32 in [0, 1] (0 where nothing is seen)
    coverage : Tensor (rows, cols) uint8, how many views see each canvas pixel centre
    canvas : Canvas
    outlines : Tensor (9, 4, 2) float64, each view's corners in canvas pixels
    """

    image: Tensor
    coverage: Tensor
    canvas: Canvas
    outlines: Tensor


def stitch(views: Tensor, homographies: Tensor, canvas: Canvas, feather: bool = True) -> Panorama:
    """Warp views (V, H, W) into ``canvas`` by homographies (V, 3, 3) (view px -> fovea px).

    Each view is warped (Kornia ``warp_perspective``, bilinear) only into its own bounding box
    on the canvas. A canvas pixel counts as covered by a view when its centre maps inside that
    view's pixel area (to float32 rounding).
    """
    if views.ndim != 3 or homographies.shape != (views.shape[0], 3, 3):
        raise HbisInputError(
            f"need views (V, H, W) and homographies (V, 3, 3), got {tuple(views.shape)} and "
            f"{tuple(homographies.shape)}")
    if not torch.isfinite(views).all() or not torch.isfinite(homographies).all():
        raise HbisInputError("views or homographies contain NaN or inf")
    rows, cols = canvas.shape
    view_shape = tuple(views.shape[1:])
    acc = torch.zeros(rows, cols, dtype=torch.float32)
    wsum = torch.zeros(rows, cols, dtype=torch.float32)
    coverage = torch.zeros(rows, cols, dtype=torch.uint8)
    weights = feather_weights(view_shape) if feather else torch.ones(view_shape)
    to_canvas = canvas.A @ homographies.to(torch.float64)
    outlines = view_outlines(to_canvas, view_shape)
    for k in range(views.shape[0]):
        lo, hi = outlines[k].amin(0), outlines[k].amax(0)
        x0, y0 = max(0, math.floor(float(lo[0]))), max(0, math.floor(float(lo[1])))
        x1, y1 = min(cols, math.ceil(float(hi[0])) + 1), min(rows, math.ceil(float(hi[1])) + 1)
        if x1 <= x0 or y1 <= y0:
            continue
        shift = torch.tensor([[1.0, 0.0, -x0], [0.0, 1.0, -y0], [0.0, 0.0, 1.0]], dtype=torch.float64)
        h_box = (shift @ to_canvas[k]).to(torch.float32)[None]
        src = torch.stack((views[k] * weights, weights, torch.ones(view_shape)))[None]
        warped = warp_perspective(src, h_box, (y1 - y0, x1 - x0), mode="bilinear",
                                  padding_mode="zeros", align_corners=True)[0]
        acc[y0:y1, x0:x1] += warped[0]
        wsum[y0:y1, x0:x1] += warped[1]
        # A warped plane of ones, zero-padded, is 1/2 exactly half a pixel outside the view: the
        # edge of its pixel area. So > 1/2 means "the centre lies on the view".
        coverage[y0:y1, x0:x1] += (warped[2] > 0.5).to(torch.uint8)
    image = torch.where(wsum > 1e-6, acc / wsum.clamp_min(1e-6), torch.zeros_like(acc))
    return Panorama(image=image.clamp(0.0, 1.0), coverage=coverage, canvas=canvas, outlines=outlines)


def stitch_array(views: Tensor, array: CameraArray, binning: int, homographies: Tensor | None = None,
                 scale: float = 1.0, feather: bool = True) -> Panorama:
    """Stitch nine views with the given (default: design) homographies onto a fitting canvas."""
    if views.shape[0] != len(CAMERA_NAMES):
        raise HbisInputError(f"need the {len(CAMERA_NAMES)} views of the array, got {views.shape[0]}")
    if homographies is None:
        homographies = design_homographies(array, binning)
    canvas = make_canvas(array, homographies, binning, scale)
    return stitch(views, homographies, canvas, feather)


def rebin_homographies(homographies: Tensor, from_binning: int, to_binning: int) -> Tensor:
    """The same homographies (..., 3, 3) expressed on views binned by ``to_binning`` instead of
    ``from_binning`` (pixel centres: x_b = (x_1 + 0.5) / b - 0.5)."""
    r = from_binning / to_binning
    c = 0.5 * r - 0.5
    s = torch.tensor([[r, 0.0, c], [0.0, r, c], [0.0, 0.0, 1.0]], dtype=torch.float64)
    return s @ homographies.double() @ torch.linalg.inv(s)
