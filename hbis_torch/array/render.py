"""Rendering the array's views of a planar scene, through an exchangeable sensor model.

A view is the scene box-integrated over each (binned) pixel: ``supersample`` x
``supersample`` rays per pixel, averaged. What a real sensor adds (optics blur, noise,
quantisation) is the ``sensor`` callable's job: ``sensor(ideal (H, W) float32, seed, pitch_mm)
-> (H, W) float32 in [0, 1]``, where ``pitch_mm`` is the view's pixel spacing on the object
plane. ``None`` keeps the ideal image.

Images are float32; geometry (the ray traces) float64.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Callable

import torch
import torch.nn.functional as F
from torch import Tensor

from ..errors import HbisInputError
from ..optics import check_roi, landing_map_interpolated
from .cameras import CAMERA_NAMES, FOVEA, PARKED_PHASES_DEG, CameraArray
from .scene import PlanarScene

SensorFn = Callable[[Tensor, int, float], Tensor]


def _box_average(samples: Tensor, supersample: int) -> Tensor:
    """(..., H s, W s) -> (..., H, W) mean over s x s cells."""
    if supersample == 1:
        return samples
    lead = samples.shape[:-2]
    flat = samples.reshape(-1, 1, *samples.shape[-2:])
    out = F.avg_pool2d(flat, supersample)
    return out.reshape(*lead, *out.shape[-2:])


class ArrayRenderer:
    """Renders the nine views (and the fovea's ROI frames) of a scene, caching the geometry
    and the static background per (camera, binning, phases).

    Parameters
    ----------
    array : CameraArray
    scene : PlanarScene
    sensor : SensorFn or None
        Sensor model applied to every rendered view (None: ideal).
    supersample : int
        Rays per pixel along each axis for the box integration of the nine views (their
        textures are also resampled to the pixel footprint, so 1 does not alias).
    fovea_supersample : int
        The same for the fovea's full-resolution ROI frames, whose sub-pixel detail is what
        super-resolution recovers: keep it >= 4 there.
    """

    def __init__(self, array: CameraArray, scene: PlanarScene, sensor: SensorFn | None = None,
                 supersample: int = 1, fovea_supersample: int = 4) -> None:
        if abs(scene.distance_mm - array.system.object_distance_mm) > 1e-9:
            raise HbisInputError(
                f"the scene plane is at {scene.distance_mm} mm but the system's object distance "
                f"is {array.system.object_distance_mm} mm")
        self.array, self.scene, self.sensor = array, scene, sensor
        self.supersample, self.fovea_supersample = supersample, fovea_supersample
        self._cache: dict = {}

    def _points_and_background(self, name: str, binning: int, phases) -> tuple[Tensor, Tensor]:
        key = (name, binning, round(float(phases[0]), 9), round(float(phases[1]), 9))
        if key not in self._cache:
            if len(self._cache) > 64:  # the fovea's phases change during scans: keep it bounded
                self._cache.pop(next(iter(self._cache)))
            points = self.array.view_points(name, binning, phases, self.supersample, torch.float32)
            background = self.scene.background.sample(points, self._footprint(binning))
            self._cache[key] = (points, background)
        return self._cache[key]

    def _footprint(self, binning: int) -> float:
        return self.array.footprint_mm(binning) / self.supersample

    def _finish(self, ideal: Tensor, seed: int, pitch_mm: float) -> Tensor:
        if self.sensor is None:
            return ideal
        out = self.sensor(ideal, seed, pitch_mm)
        if out.shape != ideal.shape or not torch.isfinite(out).all():
            raise HbisInputError("the sensor model returned an image of the wrong shape or with NaN")
        return out

    def view(self, name: str, t_s: float = 0.0, binning: int = 1, phases_deg=PARKED_PHASES_DEG,
             seed: int = 0) -> Tensor:
        """Camera ``name``'s (binned) view at time ``t_s``, (rows // b, cols // b) float32.

        ``phases_deg`` only matters for the fovea (C22).
        """
        if name != FOVEA:
            phases_deg = PARKED_PHASES_DEG
        points, background = self._points_and_background(name, binning, phases_deg)
        fine = self.scene.add_objects(background, points, self._footprint(binning), t_s)
        return self._finish(_box_average(fine, self.supersample), seed, self.array.footprint_mm(binning))

    def views(self, t_s: float = 0.0, binning: int = 1, fovea_phases_deg=PARKED_PHASES_DEG,
              seed: int = 0) -> Tensor:
        """All nine views (9, H, W) in ``CAMERA_NAMES`` order.

        ``fovea_phases_deg=None`` leaves the fovea's view out (zeros): it is busy scanning.
        """
        shape = self.array.view_shape(binning)
        return torch.stack([
            torch.zeros(shape) if name == FOVEA and fovea_phases_deg is None
            else self.view(name, t_s, binning, fovea_phases_deg, seed * 9 + k)
            for k, name in enumerate(CAMERA_NAMES)
        ])

    def fovea_frames(self, phases_deg: Tensor, roi, times_s, seed: int = 0) -> Tensor:
        """The fovea's full-resolution ROI frames, one per phase pair, (F, H, W) float32.

        Parameters
        ----------
        phases_deg : Tensor, shape (F, 2), degrees
        roi : (u0, v0, width, height) pixels of the full sensor
        times_s : sequence of F times (where the moving objects are for each frame)
        """
        phases_deg = torch.as_tensor(phases_deg, dtype=torch.float64)
        if phases_deg.ndim != 2 or phases_deg.shape[1] != 2:
            raise HbisInputError(f"phases must have shape (F, 2), got {tuple(phases_deg.shape)}")
        times_s = [float(t) for t in times_s]
        if len(times_s) != len(phases_deg):
            raise HbisInputError("need one time per frame")
        system = self.array.system
        u0, v0, w, h = check_roi(system.camera, roi)
        s = self.fovea_supersample
        # The s x s cell centres of the ROI's pixels are exactly the pixel centres of a virtual
        # sensor of pitch p / s (and s times the rows and columns), so the main branch's spline
        # landing map (< 1e-4 pixel from the exact trace) gives all frames' sample points at once.
        cam = system.camera
        fine = replace(system, camera=replace(cam, pixel_pitch_um=cam.pixel_pitch_um / s,
                                              rows=cam.rows * s, cols=cam.cols * s))
        points = landing_map_interpolated(fine, phases_deg[:, 0], phases_deg[:, 1],
                                          (u0 * s, v0 * s, w * s, h * s))
        footprint = system.object_pixel_mm / s
        frames = []
        for k, t in enumerate(times_s):
            ideal = _box_average(self.scene.render(points[k], footprint, t), s)
            frames.append(self._finish(ideal, seed * 1000 + k, system.object_pixel_mm))
        return torch.stack(frames)
