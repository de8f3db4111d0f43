"""A simulated HBIS the two-stage loop drives: it captures frames and knows its geometry.

The loop needs only three things from a device (a real array could offer the same):

- ``detection_frames(t_s, fovea_phases_deg) -> (9, h, w)``: one low-resolution (binned) frame
  per camera at time ``t_s``, in ``CAMERA_NAMES`` order, the fovea at the given phases (None:
  the fovea is busy, its frame is left out);
- ``fovea_scan(phases_deg (F, 2), reference_index, h, roi, times_s) -> (Stack, truth | None)``:
  the fovea's full-resolution ROI frames of a scan, as an hbis-stack/1 Stack (a simulator also
  returns the ground truth; a real device returns None);
- ``pixel_to_plane(camera_index, pixels (N, 2), fovea_phases_deg) -> (N, 2) mm``: where a
  detection-frame pixel looks on the scene plane, from the calibration the device holds (the
  design, or homographies refined from images), never from the true assembly.
"""

from __future__ import annotations

import torch
from torch import Tensor

from hbis_torch.config import FoveaSystem
from hbis_torch.errors import HbisInputError
from hbis_torch.optics import exit_directions, land_on_plane, rays_at
from hbis_torch.registration.homography import apply_homography
from hbis_torch.simulate import SensorModel
from hbis_torch.system.array.cameras import FOVEA_INDEX, CameraArray
from hbis_torch.system.array.render import ArrayRenderer
from hbis_torch.system.array.sensor import simulate_fovea_scan
from hbis_torch.system.stitch.stitch import design_homographies


class SimulatedHBIS:
    """The array's frames of a scene: views from :class:`ArrayRenderer`, scans from
    :func:`simulate_fovea_scan`.

    Parameters
    ----------
    renderer : ArrayRenderer
    detection_binning : int
        Binning of the detection frames (8: 120 x 160 pixels).
    calibration : Tensor (9, 3, 3) or None
        Homographies (detection-frame px -> parked-fovea detection-frame px); None: design.
    sensor : SensorModel
        The fovea's sensor for the scan frames (the renderer carries the views' own).
    """

    def __init__(self, renderer: ArrayRenderer, detection_binning: int = 8,
                 calibration: Tensor | None = None, sensor: SensorModel = SensorModel()) -> None:
        self.renderer, self.sensor = renderer, sensor
        self.array: CameraArray = renderer.array
        self.binning = int(detection_binning)
        self.array.view_shape(self.binning)  # validates the binning
        self.calibration = (design_homographies(self.array, self.binning) if calibration is None
                            else calibration.double())
        if self.calibration.shape != (9, 3, 3):
            raise HbisInputError("the calibration must be nine (3, 3) homographies")
        self._frame_count = 0

    @property
    def system(self) -> FoveaSystem:
        return self.array.system

    def detection_frames(self, t_s: float, fovea_phases_deg) -> Tensor:
        self._frame_count += 1
        return self.renderer.views(t_s, self.binning, fovea_phases_deg, seed=self._frame_count)

    def fovea_scan(self, phases_deg: Tensor, reference_index: int, h: int, roi, times_s):
        self._frame_count += 1
        return simulate_fovea_scan(self.renderer.scene, self.system, phases_deg, reference_index, h, roi,
                                   times_s, self.sensor, seed=self._frame_count)

    def pixel_to_plane(self, camera_index: int, pixels: Tensor, fovea_phases_deg) -> Tensor:
        pixels = torch.as_tensor(pixels, dtype=torch.float64).reshape(-1, 2)
        b = self.binning
        if camera_index == FOVEA_INDEX:
            full = (pixels + 0.5) * b - 0.5
            rays = rays_at(self.system.camera, full[:, 0], full[:, 1])
            out = exit_directions(rays, float(fovea_phases_deg[0]), float(fovea_phases_deg[1]),
                                  self.system.prisms)
            return land_on_plane(out, self.system.object_distance_mm)
        fovea_px = apply_homography(self.calibration[camera_index], pixels)
        k_inv = torch.linalg.inv(self.array.intrinsics(b))
        rays = torch.cat((fovea_px, torch.ones_like(fovea_px[:, :1])), 1) @ k_inv.T
        return land_on_plane(rays, self.system.object_distance_mm)
