"""Rendering the array's nine views of a planar scene, through an exchangeable sensor model.

(The fovea's full-resolution scan frames come from the data branch's forward model instead:
:func:`hbis_torch.system.array.sensor.simulate_fovea_scan`.)

A view is the scene box-integrated over each (binned) pixel: ``supersample`` x
``supersample`` rays per pixel, averaged. What a real sensor adds (optics blur, noise,
quantisation) is the ``sensor`` callable's job: ``sensor(ideal (H, W) float32, seed, pitch_mm)
-> (H, W) float32 in [0, 1]``, where ``pitch_mm`` is the view's pixel spacing on the object
plane. ``None`` keeps the ideal image.

Images are float32; geometry (the ray traces) float64.
"""

from __future__ import annotations

from typing import Callable

import torch
import torch.nn.functional as F
from torch import Tensor

from hbis_torch.errors import HbisInputError
from hbis_torch.system.array.cameras import CAMERA_NAMES, FOVEA, PARKED_PHASES_DEG, CameraArray
from hbis_torch.system.array.scene import PlanarScene

#: sensor(ideal (..., H, W) float32, seed, pitch_mm) -> same shape, float32 in [0, 1]
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
    """Renders the nine views of a scene, caching the geometry
    and the static background per (camera, binning, phases).

    Parameters
    ----------
    array : CameraArray
    scene : PlanarScene
    sensor : SensorFn or None
        Sensor model applied to every rendered view (None: ideal).
    supersample : int
        Rays per pixel along each axis for the box integration of the views (their textures
        are also resampled to the pixel footprint, so 1 does not alias).
    """

    def __init__(self, array: CameraArray, scene: PlanarScene, sensor: SensorFn | None = None,
                 supersample: int = 1) -> None:
        if abs(scene.distance_mm - array.system.object_distance_mm) > 1e-9:
            raise HbisInputError(
                f"the scene plane is at {scene.distance_mm} mm but the system's object distance "
                f"is {array.system.object_distance_mm} mm")
        self.array, self.scene, self.sensor = array, scene, sensor
        self.supersample = supersample
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
        """Apply the sensor model to ideal image(s) (..., H, W)."""
        if self.sensor is None:
            return ideal
        out = self.sensor(ideal, seed, pitch_mm)
        if out.shape != ideal.shape or not torch.isfinite(out).all():
            raise HbisInputError("the sensor model returned an image of the wrong shape or with NaN")
        return out

    def _ideal(self, name: str, t_s: float, binning: int, phases_deg) -> Tensor:
        if name != FOVEA:
            phases_deg = PARKED_PHASES_DEG
        points, background = self._points_and_background(name, binning, phases_deg)
        fine = self.scene.add_objects(background, points, self._footprint(binning), t_s)
        return _box_average(fine, self.supersample)

    def view(self, name: str, t_s: float = 0.0, binning: int = 1, phases_deg=PARKED_PHASES_DEG,
             seed: int = 0) -> Tensor:
        """Camera ``name``'s (binned) view at time ``t_s``, (rows // b, cols // b) float32.

        ``phases_deg`` only matters for the fovea (C22).
        """
        ideal = self._ideal(name, t_s, binning, phases_deg)
        return self._finish(ideal, seed, self.array.footprint_mm(binning))

    def views(self, t_s: float = 0.0, binning: int = 1, fovea_phases_deg=PARKED_PHASES_DEG,
              seed: int = 0) -> Tensor:
        """All nine views (9, H, W) in ``CAMERA_NAMES`` order (the sensor model runs once on
        the nine together).

        ``fovea_phases_deg=None`` leaves the fovea's view out (zeros): it is busy scanning.
        """
        shape = self.array.view_shape(binning)
        ideal = torch.stack([
            torch.zeros(shape) if name == FOVEA and fovea_phases_deg is None
            else self._ideal(name, t_s, binning, fovea_phases_deg)
            for name in CAMERA_NAMES
        ])
        out = self._finish(ideal, seed, self.array.footprint_mm(binning))
        if fovea_phases_deg is None:
            out[CAMERA_NAMES.index(FOVEA)] = 0.0
        return out
