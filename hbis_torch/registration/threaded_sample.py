"""``grid_sample`` of one image on every thread torch has.

torch's CPU ``grid_sample`` runs the images of its batch in parallel, not the points of one
image: a frame's warp takes one core however many torch was given. :func:`grid_sample_threaded`
hands the points over as one batch per thread, read from the same image (expanded, not copied).
Each point's value is computed as before, so the result is the same to the bit; on two cores a
640 x 480 warp takes 0.6 to 0.7 of its time.
"""

from __future__ import annotations

import torch
from torch import Tensor

#: Fewer points than this are sampled in one call: below it the threads cost more than they save
#: (two threads broke even at about 12,000 points of a 640 x 480 image).
MIN_POINTS = 1 << 14


def grid_sample_threaded(images: Tensor, grid: Tensor, **options) -> Tensor:
    """``torch.nn.functional.grid_sample(images, grid, **options)``, the points split over threads.

    Parameters
    ----------
    images : Tensor, shape (B, C, H, W)
        Split only where B = 1 (a batch of several runs in parallel already).
    grid : Tensor, shape (B, rows, cols, 2)
        grid_sample's coordinates.
    **options
        grid_sample's ``mode``, ``padding_mode`` and ``align_corners``.

    Returns
    -------
    Tensor, shape (B, C, rows, cols), in ``images``' dtype: the same values as grid_sample's.
    """
    parts = torch.get_num_threads()
    B, rows, cols, _ = grid.shape
    if B != 1 or images.shape[0] != 1 or parts < 2 or rows * cols < MIN_POINTS or not grid.is_contiguous():
        return torch.nn.functional.grid_sample(images, grid, **options)
    if rows % parts == 0:
        batches = grid.view(parts, rows // parts, cols, 2)
    elif (rows * cols) % parts == 0:
        batches = grid.view(parts, 1, rows * cols // parts, 2)
    else:
        return torch.nn.functional.grid_sample(images, grid, **options)
    out = torch.nn.functional.grid_sample(images.expand(parts, -1, -1, -1), batches, **options)  # (parts, C, ., .)
    channels = images.shape[1]
    if channels == 1:  # the parts' points in order: a view
        return out.view(1, 1, rows, cols)
    return out.movedim(0, 1).reshape(1, channels, rows, cols)
