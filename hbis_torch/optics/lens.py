"""A real lens: OpenCV's pinhole-plus-distortion camera model, in torch.

A camera with a :class:`~hbis_torch.config.LensCalibration` maps pixel (u, v) to the chief ray
(x, y, 1) through

    xd = (u - cx) / fx,   yd = (v - cy) / fy              (distorted normalised coordinates)
    (xd, yd) = distort(x, y)                             (OpenCV's model, below)

    r2 = x^2 + y^2,  radial = (1 + k1 r2 + k2 r2^2 + k3 r2^3) / (1 + k4 r2 + k5 r2^2 + k6 r2^3)
    xd = x radial + 2 p1 x y + p2 (r2 + 2 x^2)
    yd = y radial + p1 (r2 + 2 y^2) + 2 p2 x y

(the model of ``cv2.projectPoints`` and ``cv2.undistortPoints``; tests/test_capture_lens.py checks
both against OpenCV). Undistortion is the fixed-point iteration OpenCV uses, run to convergence
in float64. A camera without a calibration never comes here: its rays are those of
docs/design.md section 1, bit for bit.
"""

from __future__ import annotations

import torch
from torch import Tensor

from hbis_torch.config import LensCalibration
from hbis_torch.errors import HbisInputError

ITERATIONS = 50
TOLERANCE = 1e-12


def distort(lens: LensCalibration, x: Tensor, y: Tensor) -> tuple[Tensor, Tensor]:
    """Distorted normalised coordinates (xd, yd) of the undistorted ones (x, y)."""
    if not lens.distortion:
        return x, y
    k1, k2, p1, p2, k3, k4, k5, k6 = lens.distortion
    r2 = x * x + y * y
    radial = (1 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1 + r2 * (k4 + r2 * (k5 + r2 * k6)))
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return xd, yd


def undistort(lens: LensCalibration, xd: Tensor, yd: Tensor) -> tuple[Tensor, Tensor]:
    """Undistorted normalised coordinates (x, y) whose distortion is (xd, yd) (fixed point)."""
    if not lens.distortion:
        return xd, yd
    k1, k2, p1, p2, k3, k4, k5, k6 = lens.distortion
    x, y = xd.clone(), yd.clone()
    for _ in range(ITERATIONS):
        r2 = x * x + y * y
        inverse = (1 + r2 * (k4 + r2 * (k5 + r2 * k6))) / (1 + r2 * (k1 + r2 * (k2 + r2 * k3)))
        dx = 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        dy = p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        nx, ny = (xd - dx) * inverse, (yd - dy) * inverse
        step = float(torch.maximum((nx - x).abs().max(), (ny - y).abs().max())) if nx.numel() else 0.0
        x, y = nx, ny
        if step < TOLERANCE:
            break
    ex, ey = distort(lens, x, y)
    if x.numel() and float(torch.maximum((ex - xd).abs().max(), (ey - yd).abs().max())) > 1e-9:
        raise HbisInputError("the lens distortion cannot be inverted over this sensor (the calibration's "
                             "coefficients fold the image): check the calibration")
    return x, y


def pixel_rays_through_lens(lens: LensCalibration, u: Tensor, v: Tensor) -> Tensor:
    """Unit chief rays (..., 3) of fractional pixel positions (u, v), through the lens."""
    x, y = undistort(lens, (u - lens.cx) / lens.fx, (v - lens.cy) / lens.fy)
    rays = torch.stack((x, y, torch.ones_like(x)), dim=-1)
    return rays / rays.norm(dim=-1, keepdim=True)


def pixels_of_directions(lens: LensCalibration, directions: Tensor) -> Tensor:
    """Fractional pixel positions (..., 2) (u, v) where incident directions (..., 3) are imaged."""
    x = directions[..., 0] / directions[..., 2]
    y = directions[..., 1] / directions[..., 2]
    xd, yd = distort(lens, x, y)
    return torch.stack((xd * lens.fx + lens.cx, yd * lens.fy + lens.cy), dim=-1)
