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


def grid_sample_threaded(images: Tensor, grid: Tensor, out: Tensor | None = None, **options) -> Tensor:
    """``torch.nn.functional.grid_sample(images, grid, **options)``, the points split over threads.

    Parameters
    ----------
    images : Tensor, shape (B, C, H, W)
        Split only where B = 1 (a batch of several runs in parallel already).
    grid : Tensor, shape (B, rows, cols, 2)
        grid_sample's coordinates.
    out : Tensor, shape (B, C, rows, cols), optional
        Written with the result and returned (the caller's memory: a split result with several
        channels is gathered straight into it, one copy rather than two).
    **options
        grid_sample's ``mode``, ``padding_mode`` and ``align_corners``.

    Returns
    -------
    Tensor, shape (B, C, rows, cols), in ``images``' dtype: the same values as grid_sample's
    (``out`` where given).
    """
    parts = torch.get_num_threads()
    B, rows, cols, _ = grid.shape
    batches = None
    if B == 1 and images.shape[0] == 1 and parts > 1 and rows * cols >= MIN_POINTS and grid.is_contiguous():
        if rows % parts == 0:
            batches = grid.view(parts, rows // parts, cols, 2)
        elif (rows * cols) % parts == 0:
            batches = grid.view(parts, 1, rows * cols // parts, 2)
    if batches is None:
        result = torch.nn.functional.grid_sample(images, grid, **options)
        return result if out is None else out.copy_(result)
    result = torch.nn.functional.grid_sample(images.expand(parts, -1, -1, -1), batches, **options)  # (parts, C, ., .)
    channels = images.shape[1]
    if out is not None and rows % parts == 0:  # each channel's rows split in the parts (a view of any out)
        out.view(channels, parts, rows // parts, cols).copy_(result.movedim(0, 1))
        return out
    if channels == 1:  # the parts' points in order: a view
        result = result.view(1, 1, rows, cols)
    else:
        result = result.movedim(0, 1).reshape(1, channels, rows, cols)
    return result if out is None else out.copy_(result)
