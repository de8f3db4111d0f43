"""Local motion on top of a frame's global one: a smooth field of small shifts, tile by tile.

A homography holds for a flat scene seen by a global-shutter camera through a distortion-free
lens. A hand-held burst breaks each a little: the rolling shutter reads rows at different
moments (a shift that changes down the frame), near and far objects move apart (parallax), and
the lens's distortion bends what a homography keeps straight. What is left after the global
motion is small and smooth, so it is measured as one shift per tile of the reference grid by
Lucas-Kanade on the blurred images (a few Gauss-Newton steps of a translation, as HDR+ [1]_ and
Wronski et al. [2]_ align tiles), shrunk towards zero where the tile's texture does not pin it down,
smoothed across the tiles (:func:`smooth_offsets`), and interpolated bilinearly between the tiles'
centres. What no motion explains (a moving object) stays the robustness weights' to handle.

Offsets are (F, rows, cols, 2) float64 in LR px, (du, dv) at the centre of each tile of the
reference grid: a sample that the frame's homography puts at x lands at x + offset(x).

References
----------
.. [1] S. W. Hasinoff et al., "Burst photography for high dynamic range and low-light imaging on
   mobile cameras", ACM Transactions on Graphics 35(6), 2016 (tile alignment).
.. [2] B. Wronski et al., "Handheld multi-frame super-resolution", ACM Transactions on Graphics
   38(4), 2019.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from hbis_torch.registration.threaded_sample import grid_sample_threaded

# The shifted reference (:func:`_shift`) is made in the warp's pieces: PIECE_SAMPLES pixels at a
# time, in grids of more pixels than PIECES_FROM.
from hbis_torch.registration.warp import PIECE_SAMPLES, PIECES_FROM, warp_onto_reference

#: Side of a tile, LR px: small enough to follow a rolling shutter's skew down a frame, large
#: enough that a textured tile pins its shift (a setting, not tuned).
TILE_PX = 32
#: Largest local shift (LR px) on top of the global motion; a tile that asks for more has no say
#: in the field and takes its neighbours' shift (its own content moved: the robustness weights' case).
MAX_LOCAL_PX = 1.5
ITERATIONS = 3
#: Frames smaller than this many tiles across (either way) keep their global motion alone.
MIN_TILES = 3
BLUR_PX = 1.0
#: Gaussian sigma (tiles) of the smoothing across tiles. What a homography leaves (a rolling
#: shutter's skew, the lens's distortion, a distant scene's parallax) changes over many tiles; a
#: tile's own estimate also carries its noise and its aliasing, which change from tile to tile
#: (a setting: on the held-out renderer's bursts, 1 and 2 tiles were looked at, not more).
SMOOTH_TILES = 2.0


def tile_grid(shape: tuple[int, int], tile: int = TILE_PX) -> tuple[int, int]:
    """(rows, cols) of tiles over a frame of ``shape`` (H, W) (the last ones may be partial)."""
    H, W = shape
    return -(-H // tile), -(-W // tile)


def sample_offsets(offsets: Tensor, points: Tensor, tile: int = TILE_PX) -> Tensor:
    """The offsets field at ``points``: bilinear between the tiles' centres, held at the edges.

    Parameters
    ----------
    offsets : Tensor, shape (F, rows, cols, 2)
    points : Tensor, shape (F, ..., 2)
        (u, v) on the reference grid, LR px.

    Returns
    -------
    Tensor, shape of ``points``, in ``points``' dtype
    """
    out = _field_at(offsets, points, tile)  # (F, 2, N)
    return out.permute(0, 2, 1).reshape(points.shape).to(points.dtype)


def add_offsets(offsets: Tensor, points: Tensor, tile: int = TILE_PX) -> Tensor:
    """``points += sample_offsets(offsets, points, tile)``, in place (no copy of the points in
    the field's float32 or back): ``points``, a contiguous (F, ..., 2) tensor. Each axis is added
    from the field's (F, 2, N) rows as they are (no interleaved copy of the field first)."""
    field = _field_at(offsets, points, tile)
    flat = points.view(field.shape[0], -1, 2)
    for axis in (0, 1):
        flat[..., axis].add_(field[:, axis])
    return points


def _field_at(offsets: Tensor, points: Tensor, tile: int) -> Tensor:
    """The field (F, rows, cols, 2) read at ``points`` (F, ..., 2): (F, 2, N) float32 (grid_sample)."""
    F, rows, cols, _ = offsets.shape
    flat = points.reshape(F, -1, 2)
    # Tile (i, j)'s centre is at ((j + 0.5) tile - 0.5, (i + 0.5) tile - 0.5): grid_sample's
    # coordinate of u is ((u + 0.5) / tile - 0.5) 2 / (cols - 1) - 1, i.e. u a + b, computed in
    # the points' dtype and written in float32.
    grid = torch.empty((F, 1, flat.shape[1], 2), dtype=torch.float32)
    for axis, count in ((0, cols), (1, rows)):
        a = 2 / (tile * max(count - 1, 1))
        b = (0.5 / tile - 0.5) * (2 / max(count - 1, 1)) - 1
        torch.add(torch.tensor(b, dtype=flat.dtype), flat[..., axis], alpha=a, out=grid[:, 0, :, axis])
    field = offsets.permute(0, 3, 1, 2).to(torch.float32)
    out = grid_sample_threaded(field, grid, mode="bilinear", padding_mode="border", align_corners=True)
    return out[:, :, 0]


def _shift(image: Tensor, offsets: Tensor, tile: int, spread: tuple[Tensor, Tensor],
           axes: tuple[Tensor, Tensor], out: tuple[Tensor, Tensor] | None = None) -> Tensor:
    """``image`` (1, C, H, W) read at x + the field of ``offsets`` (1, rows, cols, 2, px) at x,
    bilinear, for the pixels x of a grid: ``axes``, its rows' and columns' coordinates in
    grid_sample's [-1, 1] (float32, kept by the caller; they may go on past the image's edge),
    ``spread``, :func:`_spread`'s two matrices for it. The offsets are scaled to grid_sample's
    units before they are spread (two passes over the pixels, not six). (1, C, rows, cols),
    written into ``out[0]`` if given, the field into ``out[1]`` (1, 2, rows, cols) (the caller's
    memory, reused frame after frame: a 12 MP frame's result and field are 240 MB of fresh pages
    otherwise); the grid is made and read a piece of :data:`PIECE_SAMPLES` pixels at a time (each
    pixel's values the same)."""
    _, C, H, W = image.shape
    size = (len(axes[0]), len(axes[1]))
    out, field = out or (torch.empty((1, C, *size), dtype=torch.float32), None)
    field = _field(offsets * torch.tensor([2 / (W - 1), 2 / (H - 1)]), size, tile, spread, field)  # (1, rows, cols, 2)
    step = max(1, PIECE_SAMPLES // max(size[1], 1)) if size[0] * size[1] > PIECES_FROM else size[0]
    for first in range(0, size[0], step):
        piece = slice(first, min(first + step, size[0]))
        grid = torch.empty((1, piece.stop - first, size[1], 2), dtype=torch.float32)  # no stacking copy
        torch.add(field[:, piece, :, 0], axes[1][None, None, :], out=grid[..., 0])
        torch.add(field[:, piece, :, 1], axes[0][piece][None, :, None], out=grid[..., 1])
        grid_sample_threaded(image, grid, out=out[:, :, piece], mode="bilinear", padding_mode="border",
                             align_corners=True)
    return out


def local_offsets(grey: Tensor, reference: int, motions: np.ndarray, gain_offset: np.ndarray,
                  use: list[int], tile: int = TILE_PX) -> np.ndarray | None:
    """Each frame's local shifts on top of its homography (module docstring).

    Parameters
    ----------
    grey : Tensor, shape (F, H, W), float32 in [0, 1]
    reference : int
    motions : np.ndarray, shape (F, 3, 3)
        Frame px -> reference px.
    gain_offset : np.ndarray, shape (F, 2)
        ``g * frame + o`` matches the reference.
    use : list of int
        The frames to refine (the others get zero offsets).
    tile : int
        Tile side, LR px.

    Returns
    -------
    np.ndarray, shape (F, rows, cols, 2), float64, or None
        None where the frames are smaller than :data:`MIN_TILES` tiles either way.
    """
    import kornia

    from hbis_torch.sensor.noise import noise_sigma

    F, H, W = grey.shape
    rows, cols = tile_grid((H, W), tile)
    if min(rows, cols) < MIN_TILES:
        return None
    out = np.zeros((F, rows, cols, 2))
    if not use:
        return out
    blur = (lambda x: kornia.filters.gaussian_blur2d(x, (7, 7), (BLUR_PX, BLUR_PX), border_type="replicate"))
    ref = blur(grey[reference][None, None])
    gradient = kornia.filters.spatial_gradient(ref, mode="diff", order=1, normalized=False)[:, 0]  # (1, 2, H, W)
    ref_and_gradient = torch.cat((ref, gradient * 0.5), 1)  # central differences: (f(x+1) - f(x-1)) / 2
    # Noise of a blurred difference of two frames, for the shrinkage of poorly pinned tiles.
    noise = float(noise_sigma(grey[reference][None])[0]) * 2 ** 0.5 / (2 * np.pi ** 0.5 * BLUR_PX)
    # Per pixel everything lives on the tiles' whole grid (Hp, Wp): the pixels past the frame's
    # edge (a partial last row or column of tiles) are never valid, and the reference is read
    # there as at its edge (replicated, as grid_sample clamps).
    Hp, Wp = rows * tile, cols * tile
    axes = tuple((torch.arange(size, dtype=torch.float64) * (2 / (n - 1)) - 1).float()
                 for size, n in ((Hp, H), (Wp, W)))
    spread = (_spread(Hp, rows, tile), _spread(Wp, cols, tile).T.contiguous())
    unshifted = torch.nn.functional.pad(ref_and_gradient, (0, Wp - W, 0, Hp - H), mode="replicate")
    # each tile's pixel count: a partial tile's sums count as a whole tile's mean would
    area = _tile_sums(torch.ones((1, H, W)), tile)[0]
    # Each tile's masked gradients and residual, a tile's pixels contiguous, written in place each
    # step through ``by_pixel`` (the same memory as (3, Hp, Wp)); one batched product then sums
    # every tile's five products (a third of the time of forming them and summing).
    tiles = torch.empty((rows, cols, 3, tile, tile))
    by_pixel = tiles.permute(2, 0, 3, 1, 4)
    flat = tiles.view(rows * cols, 3, tile * tile)
    # memory kept for every frame (a 12 MP frame's arrays would be fresh pages each time): the
    # shifted reference, its field, the frame brightness-matched, warped, and where it is valid
    shifted, field = torch.empty_like(unshifted), torch.empty((1, 2, Hp, Wp))
    matched, warped, valid = torch.empty((1, 1, H, W)), torch.empty((1, 1, Hp, Wp)), torch.empty((1, Hp, Wp))
    inside = torch.empty((Hp, Wp), dtype=torch.bool)

    def as_tiles(x: Tensor) -> Tensor:  # (C, Hp, Wp) as (C, rows, tile, cols, tile)
        return x.reshape(x.shape[0], rows, tile, cols, tile)

    for k in use:
        gain, offset = gain_offset[k]
        torch.mul(grey[k], gain, out=matched[0, 0]).add_(offset)
        warp_onto_reference(blur(matched), motions[k], size=(Hp, Wp), out=(warped, inside))
        inside[:2], inside[H - 2:], inside[:, :2], inside[:, W - 2:] = False, False, False, False
        valid.copy_(inside[None])
        n = _tile_sums(valid, tile)[0]
        d = torch.zeros(1, rows, cols, 2)
        for step in range(ITERATIONS):
            # the first step starts from no shift: the reference as it is (reading it at x + 0 would
            # only add roundings of 1e-7 px)
            at = unshifted if step == 0 else _shift(ref_and_gradient, d, tile, spread, axes, out=(shifted, field))
            torch.mul(as_tiles(at[0, 1:3]), as_tiles(valid), out=by_pixel[0:2])  # so every product is masked
            torch.sub(as_tiles(warped[0]), as_tiles(at[0, :1]), out=by_pixel[2:3])
            sums = (flat @ flat[:, :2].mT).view(rows, cols, 3, 2)  # [gx, gy, r] x [gx, gy] summed
            axx, axy, ayy, bx, by = sums[..., 0, 0], sums[..., 1, 0], sums[..., 1, 1], sums[..., 2, 0], sums[..., 2, 1]
            # Tikhonov: a tile whose texture is at the noise's level keeps (nearly) its shift.
            lam = (noise ** 2) * n.clamp_min(1) * 4.0
            det = (axx + lam) * (ayy + lam) - axy * axy
            step_u = ((ayy + lam) * bx - axy * by) / det.clamp_min(1e-20)
            step_v = ((axx + lam) * by - axy * bx) / det.clamp_min(1e-20)
            d = d + torch.stack((step_u, step_v), -1)[None]
        # a tile mostly outside the frame or asking for more than MAX_LOCAL_PX has no say
        kept = (n > 0.5 * area) & (d[0].norm(dim=-1) <= MAX_LOCAL_PX)
        out[k] = smooth_offsets(d[0].double().numpy(), torch.where(kept, axx + ayy, 0.0).double().numpy(),
                                SMOOTH_TILES)
    return out


def smooth_offsets(offsets: np.ndarray, weight: np.ndarray, sigma: float) -> np.ndarray:
    """A frame's tile offsets (rows, cols, 2) LR px, averaged over the tiles around each by a
    Gaussian of ``sigma`` tiles, each tile weighted by how well its texture pins its shift
    (``weight`` (rows, cols), its gradients' energy; 0: no say).

    The field's plane (a shift plus a gradient across the frame: what a turn or a zoom that the
    frame's model left out gives) is fitted by weighted least squares and kept as it is; only
    what departs from it is averaged, by normalised convolution, so the average neither flattens
    a turn at the frame's edges nor lets a tile without a say pull its neighbours to zero (it gets
    theirs). Zero where no tile has a say.
    """
    from hbis_torch.gaussian_filter import gaussian_filter

    if not (weight > 0).any():
        return np.zeros_like(offsets)
    rows, cols = weight.shape
    v, u = np.mgrid[0:rows, 0:cols].astype(np.float64)
    basis = np.stack((np.ones_like(u), u, v), -1).reshape(-1, 3)  # (tiles, 3)
    root = np.sqrt(weight).reshape(-1, 1)
    coefficients = np.linalg.lstsq(basis * root, offsets.reshape(-1, 2) * root, rcond=None)[0]  # (3, 2)
    plane = (basis @ coefficients).reshape(offsets.shape)
    rest = offsets - plane
    total = gaussian_filter(weight, sigma, mode="nearest")
    has = total > 1e-12 * float(total.max())
    out = plane.copy()
    for axis in (0, 1):
        out[..., axis] += np.where(has, gaussian_filter(weight * rest[..., axis], sigma, mode="nearest")
                                   / np.where(has, total, 1.0), 0.0)
    return out


def _tile_sums(x: Tensor, tile: int) -> Tensor:
    """Sums of ``x`` (C, H, W) over each tile (C, rows, cols) (the last ones partial): the full
    tiles' as views summed, the partial row and column of tiles apart (no padded copy)."""
    C, H, W = x.shape
    full = W - W % tile
    across = x[..., :full].reshape(C, H, full // tile, tile).sum(-1)
    if full < W:
        across = torch.cat((across, x[..., full:].sum(-1, keepdim=True)), -1)
    full = H - H % tile
    out = across[:, :full].reshape(C, full // tile, tile, -1).sum(-2)
    if full < H:
        out = torch.cat((out, across[:, full:].sum(-2, keepdim=True)), -2)
    return out


def _field(offsets: Tensor, shape: tuple[int, int], tile: int, spread: tuple[Tensor, Tensor] | None = None,
           out: Tensor | None = None) -> Tensor:
    """The offsets (F, rows, cols, 2) at every pixel of a (H, W) grid: (F, H, W, 2) float32.

    The same bilinear field as :func:`sample_offsets` (a tile's value sits at its centre and is
    held beyond the outer centres), as torch's bilinear enlargement (``align_corners=False``)
    by ``tile`` gives it, written as two matrix products, (H, rows) x (rows, cols) x (cols, W)
    (:func:`_spread`): a tenth of the enlargement's time, the same values to float32 rounding.
    ``spread``: the two matrices (the second transposed), where the caller keeps them; ``out``,
    (F, 2, H, W) float32 memory to write into (the result is its permuted view)."""
    H, W = shape
    F, rows, cols, _ = offsets.shape
    down, across = spread or (_spread(H, rows, tile), _spread(W, cols, tile).T.contiguous())
    out = torch.matmul(down @ offsets.permute(0, 3, 1, 2).to(torch.float32), across, out=out)  # (F, 2, H, W)
    return out.permute(0, 2, 3, 1)


def _spread(size: int, count: int, tile: int) -> Tensor:
    """(size, count) float32: the weights of ``count`` tile centres ``tile`` px apart at each of
    ``size`` pixels, bilinear, held beyond the first and last centres (as torch's bilinear
    enlargement with ``align_corners=False`` weighs them)."""
    source = ((torch.arange(size, dtype=torch.float32) + 0.5) / tile - 0.5).clamp_min(0)
    first = source.floor().to(torch.int64).clamp_max(count - 1)
    second = (first + 1).clamp_max(count - 1)
    far = (source - first).clamp_max(1.0)
    out = torch.zeros((size, count), dtype=torch.float32)
    rows = torch.arange(size)
    out.index_put_((rows, first), 1 - far, accumulate=True)
    out.index_put_((rows, second), far, accumulate=True)
    return out
