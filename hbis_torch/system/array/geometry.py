"""Orientation of the nine cameras of the 3 x 3 HBIS array.

Camera C_ij (paper notation, i = row 1..3 from the top, j = column 1..3 from the left) looks
along an axis tilted by -varphi_h (j = 1), 0 or +varphi_h (j = 3) horizontally and -varphi_v
(i = 1, up, since y grows downward), 0 or +varphi_v (i = 3) vertically; the corner axes point
along (tan varphi_h, tan varphi_v, 1) with signs, so their inclination is varphi_c. C_22 is the
fovea (behind the Risley pair). Rotations map camera coordinates to the fovea's frame.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor


def camera_axis(varphi_h_deg: float, varphi_v_deg: float, row: int, col: int) -> Tensor:
    """Unit optical axis of camera C_{row,col} (1-based), float64 tensor of shape (3,)."""
    sx, sy = col - 2, row - 2
    if sx not in (-1, 0, 1) or sy not in (-1, 0, 1):
        raise ValueError(f"no camera C_{row}{col} in a 3 x 3 array")
    axis = torch.tensor(
        [sx * math.tan(math.radians(varphi_h_deg)), sy * math.tan(math.radians(varphi_v_deg)), 1.0],
        dtype=torch.float64,
    )
    return axis / axis.norm()


def camera_rotation(axis: Tensor) -> Tensor:
    """Rotation (3, 3) whose columns are the camera's x, y, z axes in the fovea's frame.

    z is ``axis``; x stays horizontal (perpendicular to the world y axis), so rows stay level.
    """
    z = axis / axis.norm()
    x = torch.stack((z[2], torch.zeros_like(z[0]), -z[0]))
    x = x / x.norm()
    y = torch.linalg.cross(z, x)
    return torch.stack((x, y, z), dim=1)


def array_rotations(varphi_h_deg: float, varphi_v_deg: float) -> dict[tuple[int, int], Tensor]:
    """{(row, col): rotation (3, 3)} for all nine cameras (1-based indices)."""
    return {
        (r, c): camera_rotation(camera_axis(varphi_h_deg, varphi_v_deg, r, c))
        for r in (1, 2, 3)
        for c in (1, 2, 3)
    }
