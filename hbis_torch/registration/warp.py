"""A frame resampled onto the reference grid through its homography, and where it is valid.

Kornia's ``warp_perspective`` builds a full (H, W) mesh, maps it with (H, W) temporaries and
samples a ones channel beside the image to tell where the frame covers the reference: on a 12 MP
frame more than half of a warp's time went there. Each row of the homography is a column term
plus a row term (``a x + (b y + c)``, as :func:`~.homography.apply_homography_to_grid` writes
it), so the sampling grid costs five passes over the pixels, and whether a point lies inside the
frame is read from its coordinates. The coordinates are grid_sample's normalised ones
(``align_corners=True``, float32, as Kornia's), so the samples agree with Kornia's warp to
float32 rounding of the coordinates (about 1e-7 of the frame's size).

Homographies are (3, 3) float64, frame px -> reference px, pixel centres at integers.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from hbis_torch.registration.threaded_sample import grid_sample_threaded

#: A reference pixel counts as covered where it maps within this far (px) outside the frame's
#: outer pixel centres (Kornia's ones channel sampled above 0.999 bilinearly, as the callers had it).
EDGE_TOLERANCE_PX = 1e-3
#: Frames of more than PIECES_FROM pixels are warped PIECE_SAMPLES pixels at a time
#: (:func:`warp_onto_reference`; smaller ones' temporaries are reused by the allocator anyway).
PIECE_SAMPLES, PIECES_FROM = 1 << 16, 1 << 20


def sampling_grid(motion: np.ndarray, shape: tuple[int, int], size: tuple[int, int] | None = None,
                  rows: slice = slice(None)) -> Tensor:
    """Where each pixel of the reference grid lies in the frame, as ``grid_sample`` reads it.

    Parameters
    ----------
    motion : np.ndarray, shape (3, 3)
        Frame px -> reference px.
    shape : (H, W)
        The frame's and the reference's size, px.
    size : (rows, cols), optional
        The pixels (v, u) with v < rows, u < cols of the reference grid, carried on past its
        edge where larger than ``shape`` (default: ``shape``).
    rows : slice, optional
        Only these of its rows (the same values as the whole grid's rows).

    Returns
    -------
    Tensor, shape (1, rows, cols, 2), float32
        (x, y) in [-1, 1] across the frame's outer pixel centres (``align_corners=True``);
        non-finite where the homography sends the point to infinity.
    """
    return _grid(_grid_matrix(motion, shape), shape, size, rows)


def _grid_matrix(motion: np.ndarray, shape: tuple[int, int]) -> Tensor:
    """(3, 3) float64: reference normalised -> reference px -> frame px -> frame normalised."""
    H, W = shape
    norm = np.array([[2 / max(W - 1, 1), 0, -1], [0, 2 / max(H - 1, 1), -1], [0, 0, 1.0]])
    try:
        inverse = np.linalg.inv(np.asarray(motion, dtype=np.float64))
    except np.linalg.LinAlgError:  # a degenerate motion: nowhere on the frame
        inverse = np.full((3, 3), np.nan)
    return torch.from_numpy(norm @ inverse @ np.linalg.inv(norm))


def _grid(m: Tensor, shape: tuple[int, int], size: tuple[int, int] | None, rows: slice) -> Tensor:
    """:func:`sampling_grid` from its :func:`_grid_matrix` ``m``."""
    H, W = shape
    height, cols = size or shape
    xs = torch.arange(cols, dtype=torch.float64) * (2 / max(W - 1, 1)) - 1
    ys = (torch.arange(height, dtype=torch.float64) * (2 / max(H - 1, 1)) - 1)[rows]
    grid = torch.empty((1, len(ys), cols, 2), dtype=torch.float32)

    def plane(row: int, out: Tensor | None = None) -> Tensor:  # m[row] . (x, y, 1) at every pixel
        across = (m[row, 0] * xs).float()[None, :]
        down = (m[row, 1] * ys + m[row, 2]).float()[:, None]
        return torch.add(down, across, out=out)

    affine = bool(m[2, 0] == 0 and m[2, 1] == 0)
    for axis in (0, 1):
        plane(axis, out=grid[0, ..., axis])
    if affine:
        if float(m[2, 2]) != 1.0:
            grid.div_(float(m[2, 2]))
    else:
        w = plane(2)
        grid[0, ..., 0].div_(w)
        grid[0, ..., 1].div_(w)
    return grid


def inside(grid: Tensor, shape: tuple[int, int] | None = None) -> Tensor:
    """(rows, cols) bool: where a :func:`sampling_grid` (1, rows, cols, 2) of a frame of
    ``shape`` (H, W) (default: the grid's size) lies on the frame, up to
    :data:`EDGE_TOLERANCE_PX` beyond its outer pixel centres (False where non-finite)."""
    H, W = shape or grid.shape[1:3]
    reach = grid[0].abs()  # one pass over both coordinates (a strided one per axis took longer)
    out = reach[..., 0] <= 1 + 2 * EDGE_TOLERANCE_PX / max(W - 1, 1)
    return out.logical_and_(reach[..., 1] <= 1 + 2 * EDGE_TOLERANCE_PX / max(H - 1, 1))


def warp_onto_reference(images: Tensor, motion: np.ndarray, mode: str = "bilinear",
                        size: tuple[int, int] | None = None,
                        out: tuple[Tensor, Tensor] | None = None) -> tuple[Tensor, Tensor]:
    """``images`` (1, C, H, W) of a frame resampled onto the reference grid (zeros outside).

    Parameters
    ----------
    images : Tensor, shape (1, C, H, W), float32
    motion : np.ndarray, shape (3, 3)
        Frame px -> reference px.
    mode : str
        ``grid_sample``'s interpolation.
    size : (rows, cols), optional
        The reference grid's pixels to resample at (:func:`sampling_grid`; default (H, W)).
    out : (Tensor, Tensor), optional
        Memory to write ``warped`` and ``valid`` into (a caller's, kept frame after frame).

    Returns
    -------
    warped : Tensor, shape (1, C, rows, cols), float32
    valid : Tensor, shape (rows, cols), bool
        Where the frame covers the reference pixel (:func:`inside`).
    """
    shape = tuple(images.shape[-2:])
    rows, cols = size or shape
    step = max(1, PIECE_SAMPLES // max(cols, 1))
    if rows * cols <= PIECES_FROM and out is None:
        grid = sampling_grid(motion, shape, size)
        warped = grid_sample_threaded(images, grid, mode=mode, padding_mode="zeros", align_corners=True)
        return warped, inside(grid, shape)
    # A piece of rows at a time (each pixel's the same values): the grid's temporaries stay
    # small and in the cache, where a 12 MP frame's would be 96 MB of fresh pages.
    warped, valid = out or (torch.empty(images.shape[:2] + (rows, cols), dtype=images.dtype),
                            torch.empty((rows, cols), dtype=torch.bool))
    m = _grid_matrix(motion, shape)
    for first in range(0, rows, step):
        piece = slice(first, min(first + step, rows))
        grid = _grid(m, shape, (rows, cols), piece)
        warped[..., piece, :] = grid_sample_threaded(images, grid, mode=mode, padding_mode="zeros",
                                                     align_corners=True)
        valid[piece] = inside(grid, shape)
    return warped, valid
