"""The built-in scenario: a photo wall that fills the array's field, and a sign that comes in,
stops in front of the fovea, and leaves.

Default numbers (the demo's): the wall is built from scikit-image's photographs with texels of
``wall_texel_px`` = 1.6 periphery pixels; the moving object is scikit-image's scanned ``page``
(text) at a quarter of a fovea pixel per texel divided by 1.25, so at h = 4 its letters are
resolvable only after super-resolution (the paper's Fig. 9 idea). Its path: in from the left
at 6 mm/s, a stop of 2.5 s near the middle of the scan field, then out to the right.
"""

from __future__ import annotations

import torch

from hbis_torch.system.array.cameras import CAMERA_NAMES, CameraArray
from hbis_torch.system.array.scene import MovingObject, PlanarScene, Trajectory, photo_object, photo_wall


def array_extent_mm(array: CameraArray, margin: float = 0.04) -> tuple[float, float, float, float]:
    """(x0, x1, y0, y1) mm on the plane that holds every view, grown by ``margin`` (fraction)."""
    points = torch.stack([array.view_points(name, 16) for name in CAMERA_NAMES])
    x0, x1 = float(points[..., 0].min()), float(points[..., 0].max())
    y0, y1 = float(points[..., 1].min()), float(points[..., 1].max())
    dx, dy = (x1 - x0) * margin, (y1 - y0) * margin
    return x0 - dx, x1 + dx, y0 - dy, y1 + dy


def default_path(stop_mm=(3.0, 2.0), speed_mm_s: float = 6.0, start_x_mm: float = -17.0,
                 end_x_mm: float = 20.0, enter_s: float = 0.2, stop_s: float = 2.5) -> Trajectory:
    """In from the left, a stop at ``stop_mm``, out to the right (mm, s)."""
    sx, sy = stop_mm
    t_arrive = enter_s + (sx - start_x_mm) / speed_mm_s
    t_leave = t_arrive + stop_s
    t_gone = t_leave + (end_x_mm - sx) / speed_mm_s
    return Trajectory((0.0, enter_s, t_arrive, t_leave, t_gone),
                      ((start_x_mm, sy), (start_x_mm, sy), (sx, sy), (sx, sy), (end_x_mm, sy)))


def default_scene(array: CameraArray, h: int = 4, wall_texel_px: float = 1.6,
                  path: Trajectory | None = None, object_name: str = "page") -> PlanarScene:
    """The photo wall over the array's field and one moving object (see the module's notes)."""
    pixel = array.system.object_pixel_mm
    wall = photo_wall(array_extent_mm(array), wall_texel_px * pixel)
    obj: MovingObject = photo_object(object_name, pixel / h / 1.25, path or default_path())
    return PlanarScene(wall, [obj], array.system.object_distance_mm)
