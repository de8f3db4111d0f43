"""The foveated composite: the panorama with the super-resolved fovea inlaid where it belongs.

The super-resolved image covers the reference frame's ROI on the output grid of docs/data.md:
HR pixel (U, V) sits at full-sensor position (u0 + (U + 0.5) / h - 0.5, v0 + (V + 0.5) / h - 0.5)
at the reference phases. A composite pixel is traced back exactly: canvas pixel -> direction
-> point on the scene plane -> fovea sensor position at the reference phases
(``optics.sensor_position``, the exact inverse of the landing map) -> HR coordinates. So the
inlay has its true place, scale and (slight, prism-made) distortion.

Composites are rendered at any zoom of the canvas: zoom 1 is the panorama's own grid (the SR
is then area-averaged down first, so it does not alias), zoom ``h * binning / canvas_scale``
shows one SR pixel per composite pixel.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from hbis_torch.config import FoveaSystem
from hbis_torch.errors import HbisInputError
from hbis_torch.optics import sensor_position
from hbis_torch.system.stitch.stitch import Canvas


@dataclass
class Inlay:
    """A super-resolved fovea and where it was taken.

    Attributes
    ----------
    sr : np.ndarray (h H, h W) float32 in [0, 1]
    roi : (u0, v0, W, H) on the full sensor
    h : int
    reference_phases_deg : (phi1, phi2)
    system : FoveaSystem
    """

    sr: np.ndarray
    roi: tuple[int, int, int, int]
    h: int
    reference_phases_deg: tuple[float, float]
    system: FoveaSystem

    def __post_init__(self) -> None:
        u0, v0, w, hh = self.roi
        sr = np.asarray(self.sr, dtype=np.float32)
        if sr.shape != (self.h * hh, self.h * w):
            raise HbisInputError(f"the SR image is {sr.shape}, expected {(self.h * hh, self.h * w)} for roi {self.roi}")
        if not np.isfinite(sr).all():
            raise HbisInputError("the SR image contains NaN or inf")
        self.sr = sr

    def hr_coordinates(self, plane_mm: Tensor) -> Tensor:
        """HR pixel coordinates (..., 2) (U, V) of scene-plane points (..., 2) mm."""
        u0, v0, _, _ = self.roi
        uv = sensor_position(self.system, plane_mm, *self.reference_phases_deg)
        return (uv - torch.tensor([u0, v0], dtype=uv.dtype) + 0.5) * self.h - 0.5


def composite(panorama: Tensor, canvas: Canvas, inlay: Inlay, binning: int, zoom: float = 1.0,
              window: tuple[int, int, int, int] | None = None, feather_hr_px: float = 4.0) -> Tensor:
    """The panorama with the SR fovea inlaid, (rows, cols) float32 in [0, 1].

    Parameters
    ----------
    panorama : Tensor (Hc, Wc), the stitched image on ``canvas``
    canvas : Canvas
    inlay : Inlay
    binning : int, the binning of the views the canvas was built from
    zoom : float, composite pixels per canvas pixel (the panorama is resampled bicubically)
    window : (x0, y0, width, height) in composite pixels, or None for the whole canvas
    feather_hr_px : float, width (HR pixels) of the ramp that blends the inlay's border
    """
    if panorama.shape != canvas.shape:
        raise HbisInputError(f"the panorama is {tuple(panorama.shape)}, the canvas {canvas.shape}")
    if not (math.isfinite(zoom) and zoom > 0):
        raise HbisInputError(f"zoom must be positive, got {zoom!r}")
    rows, cols = round(canvas.shape[0] * zoom), round(canvas.shape[1] * zoom)
    x0, y0, w, h = window if window is not None else (0, 0, cols, rows)
    ys = (torch.arange(y0, y0 + h, dtype=torch.float64) + 0.5) / zoom - 0.5
    xs = (torch.arange(x0, x0 + w, dtype=torch.float64) + 0.5) / zoom - 0.5
    cy, cx = torch.meshgrid(ys, xs, indexing="ij")
    canvas_px = torch.stack((cx, cy), -1)

    def sample(image: Tensor, coords: Tensor, mode: str) -> Tensor:
        grid = torch.stack((2 * (coords[..., 0] + 0.5) / image.shape[1] - 1,
                            2 * (coords[..., 1] + 0.5) / image.shape[0] - 1), -1).float()
        return F.grid_sample(image[None, None].float(), grid[None], mode=mode, padding_mode="zeros",
                             align_corners=False)[0, 0]

    out = sample(panorama, canvas_px, "bicubic" if zoom > 1 else "bilinear").clamp(0, 1)
    plane = canvas.to_directions(canvas_px)[..., :2] * inlay.system.object_distance_mm
    hr = inlay.hr_coordinates(plane)
    sr = torch.from_numpy(inlay.sr)
    # SR pixels per composite pixel: area-average the SR down to (about) the composite's scale.
    canvas_native = binning / canvas.A[0, 0].item()
    shrink = inlay.h * canvas_native / zoom
    if shrink > 1.0:
        size = [max(2, round(s / shrink)) for s in sr.shape]
        small = F.interpolate(sr[None, None], size=size, mode="bilinear", antialias=True, align_corners=False)[0, 0]
        hr_small = (hr + 0.5) * torch.tensor([size[1] / sr.shape[1], size[0] / sr.shape[0]], dtype=hr.dtype) - 0.5
        values = sample(small, hr_small, "bilinear")
    else:
        values = sample(sr, hr, "bicubic" if shrink < 1 else "bilinear")
    edge = torch.minimum(torch.minimum(hr[..., 0] + 0.5, sr.shape[1] - 0.5 - hr[..., 0]),
                         torch.minimum(hr[..., 1] + 0.5, sr.shape[0] - 0.5 - hr[..., 1]))
    weight = (edge / feather_hr_px).clamp(0, 1).float() if feather_hr_px > 0 else (edge >= 0).float()
    return (out * (1 - weight) + values.clamp(0, 1) * weight).clamp(0, 1)


def inlay_outline(canvas: Canvas, inlay: Inlay, samples: int = 16) -> Tensor:
    """The inlay's border in canvas pixels, (4 samples, 2), traced exactly (for drawing)."""
    from hbis_torch.optics import exit_directions, rays_at

    u0, v0, width, height = inlay.roi
    t = torch.linspace(0, 1, samples, dtype=torch.float64)
    left, right = u0 - 0.5, u0 + width - 0.5
    top, bottom = v0 - 0.5, v0 + height - 0.5
    us = torch.cat((left + (right - left) * t, torch.full_like(t, right), right - (right - left) * t,
                    torch.full_like(t, left)))
    vs = torch.cat((torch.full_like(t, top), top + (bottom - top) * t, torch.full_like(t, bottom),
                    bottom - (bottom - top) * t))
    rays = rays_at(inlay.system.camera, us, vs)
    dirs = exit_directions(rays, *inlay.reference_phases_deg, inlay.system.prisms)
    return canvas.from_directions(dirs)
