"""The FOV extension ratio (FER) measured on a stitched panorama's coverage.

Two measures, both as angles seen from the fovea's original axis (canvas column x is at field
angle atan((x - axis_x) / f)):

- ``central``: the covered run through the optical axis, along the axis's row (horizontal) and
  column (vertical). With a perfect assembly this equals the design's 2 (varphi + theta).
- ``rectangle``: the largest axis-aligned rectangle that is covered everywhere, which is what a
  cropped rectangular panorama shows (the paper's prototype reports 49 x 34 deg this way).
  Keystoned corner views make it smaller than the central extent.

FER = measured FOV / single-camera FOV (2 theta).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
import torch
import torch.nn.functional as F

from hbis_torch.config import Camera
from hbis_torch.errors import HbisInputError
from hbis_torch.system.stitch.stitch import Canvas


@dataclass
class FovMeasure:
    """Whole FOV (deg) and FER of one measure, with its extent in canvas pixels
    (x0, x1, y0, y1: pixel-edge coordinates)."""

    fov_h_deg: float
    fov_v_deg: float
    fer_h: float
    fer_v: float
    extent_px: tuple[float, float, float, float]

    def to_dict(self) -> dict:
        return asdict(self)


def _run_through(line: np.ndarray, centre: int) -> tuple[int, int]:
    """First and last index of the run of True in ``line`` that contains ``centre``."""
    if not line[centre]:
        raise HbisInputError("the optical axis itself is not covered by the panorama")
    lo = centre
    while lo > 0 and line[lo - 1]:
        lo -= 1
    hi = centre
    while hi < len(line) - 1 and line[hi + 1]:
        hi += 1
    return lo, hi


def largest_rectangle(mask: np.ndarray) -> tuple[int, int, int, int]:
    """Largest axis-aligned all-True rectangle (row0, row1, col0, col1), inclusive indices.

    The classic histogram-and-stack method, O(rows x cols).
    """
    rows, cols = mask.shape
    heights = np.zeros(cols + 1, dtype=np.int64)  # sentinel column of height 0
    best, best_rect = 0, (0, -1, 0, -1)
    for r in range(rows):
        heights[:cols] = np.where(mask[r], heights[:cols] + 1, 0)
        stack: list[int] = []
        for c in range(cols + 1):
            while stack and heights[stack[-1]] >= heights[c]:
                top = stack.pop()
                left = stack[-1] + 1 if stack else 0
                area = int(heights[top]) * (c - left)
                if area > best:
                    best, best_rect = area, (r - int(heights[top]) + 1, r, left, c - 1)
            stack.append(c)
    return best_rect


def _measure(x0: float, x1: float, y0: float, y1: float, canvas: Canvas, camera: Camera) -> FovMeasure:
    fov_h = float(canvas.angle_deg(x1, "x") - canvas.angle_deg(x0, "x"))
    fov_v = float(canvas.angle_deg(y1, "y") - canvas.angle_deg(y0, "y"))
    return FovMeasure(fov_h, fov_v, fov_h / (2 * camera.half_fov_h_deg),
                      fov_v / (2 * camera.half_fov_v_deg), (x0, x1, y0, y1))


def measure_fer(coverage: torch.Tensor, canvas: Canvas, camera: Camera, max_side: int = 400) -> dict:
    """FOV and FER from a panorama's coverage (rows, cols) (> 0 where some view sees).

    Returns {"central": FovMeasure, "rectangle": FovMeasure}. The rectangle is searched on a
    grid of at most ``max_side`` cells a side (a cell counts only if wholly covered), so it
    can be up to one cell smaller than the exact one.
    """
    covered = (torch.as_tensor(coverage) > 0)
    if covered.ndim != 2 or tuple(covered.shape) != tuple(canvas.shape):
        raise HbisInputError(f"coverage must have the canvas's shape {canvas.shape}")
    mask = covered.numpy()
    ax, ay = canvas.axis_px
    cx, cy = int(round(ax)), int(round(ay))
    if not (0 <= cx < mask.shape[1] and 0 <= cy < mask.shape[0]):
        raise HbisInputError("the optical axis lies outside the panorama")
    c0, c1 = _run_through(mask[cy], cx)
    r0, r1 = _run_through(mask[:, cx], cy)
    central = _measure(c0 - 0.5, c1 + 0.5, r0 - 0.5, r1 + 0.5, canvas, camera)
    cell = max(1, int(np.ceil(max(mask.shape) / max_side)))
    # A coarse cell is covered only if all its pixels are: min-pool (as -max-pool of -mask).
    coarse = -F.max_pool2d(-covered.float()[None, None], cell, ceil_mode=True)[0, 0] > 0.5
    rr0, rr1, cc0, cc1 = largest_rectangle(coarse.numpy())
    if rr1 < rr0:
        raise HbisInputError("no part of the panorama is covered")
    rect = _measure(cc0 * cell - 0.5, (cc1 + 1) * cell - 0.5, rr0 * cell - 0.5, (rr1 + 1) * cell - 0.5,
                    canvas, camera)
    return {"central": central, "rectangle": rect}


def assembly_fer_study(array, sigma_deg: float, seeds=range(12), binning: int = 8) -> dict:
    """FER of many random assemblies with side cameras misaligned by ``sigma_deg`` rms.

    Each assembly is stitched with its true homographies (a perfect calibration), so what
    changes is the coverage itself. Returns means and minima of both measures over the seeds.
    """
    from hbis_torch.system.stitch.stitch import design_homographies, make_canvas, stitch

    rows = []
    for seed in seeds:
        bent = array.with_assembly_errors(sigma_deg, seed)
        hs = design_homographies(bent, binning, bent.rotations)
        canvas = make_canvas(bent, hs, binning)
        empty = torch.zeros(len(hs), *bent.view_shape(binning))
        m = measure_fer(stitch(empty, hs, canvas).coverage, canvas, bent.system.camera)
        rows.append([m["rectangle"].fer_h, m["rectangle"].fer_v, m["central"].fer_h, m["central"].fer_v])
    r = np.asarray(rows)
    keys = ("rectangle_fer_h", "rectangle_fer_v", "central_fer_h", "central_fer_v")
    out = {"sigma_deg": float(sigma_deg), "assemblies": len(rows)}
    out.update({f"{k}_mean": float(r[:, i].mean()) for i, k in enumerate(keys)})
    out.update({f"{k}_min": float(r[:, i].min()) for i, k in enumerate(keys)})
    return out
