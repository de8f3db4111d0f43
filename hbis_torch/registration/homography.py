"""Homographies: how a frame's pixels map onto the reference, and the motion models' parameters.

A homography ``H`` is a (3, 3) float64 matrix (batched as (F, 3, 3)) mapping frame pixel
coordinates to reference pixel coordinates: ``[u_r, v_r, 1] ~ H [u, v, 1]``, with pixel (u, v)
the centre of column u and row v. Points are (u, v) in px, shaped (..., 2).

The motion models (:data:`MODELS`) are parametrised as small warps ``W(p)`` (identity at p = 0)
in *normalised* coordinates: centred on the frame and scaled so that its half-size is about 1
(:func:`_normaliser`), so that every parameter moves the frame by a comparable amount. Their
parameter vectors have :data:`N_PARAMS` entries: translation (tx, ty), similarity (tx, ty,
scale, rotation), affine (tx, ty and the 2 x 2 linear part's four increments; burst stacks'
ladder, :data:`ALL_MODELS`), homography (the 8 free entries of the matrix).
"""

from __future__ import annotations

import functools

import kornia
import torch
from torch import Tensor

from hbis_torch.errors import HbisInputError

MODELS = ("translation", "similarity", "homography")
#: Every model the fitter knows, simplest first (the ladder a burst's per-frame choice climbs).
ALL_MODELS = ("translation", "similarity", "affine", "homography")
N_PARAMS = {"translation": 2, "similarity": 4, "affine": 6, "homography": 8}


def apply_homography(homographies: Tensor, points: Tensor) -> Tensor:
    """Map points through homographies.

    Each point ``(u, v)`` becomes ``(x / w, y / w)`` with ``[x, y, w] = H_k [u, v, 1]``; in this
    package ``H_k`` takes frame-k pixel coordinates to reference pixel coordinates.

    The registration, the reconstruction's sample positions and the array's stitching all map
    points through this one function.

    Parameters
    ----------
    homographies : Tensor, shape (F, 3, 3) or (3, 3)
    points : Tensor, shape (F, N, 2) or (N, 2)
        (u, v) pixel coordinates: frame k's own N points, or N points shared by every frame
        (mapped through each of the F homographies). Cast to the homographies' dtype. (Leading
        dimensions broadcast as in ``torch.matmul``.)

    Returns
    -------
    Tensor, shape (F, N, 2) (or (N, 2) for one homography), in the homographies' dtype.
        (u, v) after the mapping; points sent to infinity (w = 0) come out non-finite.
    """
    points = points.to(homographies.dtype)
    ones = torch.ones(points.shape[:-1] + (1,), dtype=points.dtype)
    mapped = torch.cat((points, ones), -1) @ homographies.mT  # (F, N, 3)
    return mapped[..., :2] / mapped[..., 2:]


def apply_homography_to_grid(homographies: Tensor, rows: Tensor, cols: Tensor, out: Tensor | None = None) -> Tensor:
    """:func:`apply_homography` of every pixel (u, v) = (cols[j], rows[i]) of a grid.

    Each row of ``H [u, v, 1]`` is ``a u + (b v + c)``: a column term plus a row term, one add a
    pixel, where :func:`apply_homography` builds and multiplies (N, 3) matrices (on a 12 MP
    frame a tenth of its time and no (N, 3) temporaries). The sums are associated differently,
    so the two agree to float64 rounding (within four roundings of the coordinate, 7e-12 px on
    frames up to 8192 px; tests check it), not bit for bit.

    Parameters
    ----------
    homographies : Tensor, shape (F, 3, 3), float64
    rows, cols : Tensor, shape (R,) and (C,)
        The grid's v and u coordinates, px.
    out : Tensor, shape (F, R, C, 2), float64, optional
        Written in place and returned (a caller's kept memory: no copy).

    Returns
    -------
    Tensor, shape (F, R, C, 2), float64
        (u, v) after the mapping.
    """
    h = homographies.to(torch.float64)
    rows, cols = rows.to(torch.float64), cols.to(torch.float64)
    if out is None:
        out = torch.empty((len(h), len(rows), len(cols), 2), dtype=torch.float64)
    w = None
    # An affine motion's (translation, similarity, affine) w is 1 at every pixel, exactly
    # (0 u + (0 v + 1)): its division, which leaves every value as it is, is skipped.
    affine = (h[:, 2, 0] == 0) & (h[:, 2, 1] == 0) & (h[:, 2, 2] == 1)
    for k, m in enumerate(h):
        divide = not bool(affine[k])
        if divide:
            w = torch.empty((len(rows), len(cols)), dtype=torch.float64) if w is None else w
            torch.add((m[2, 1] * rows + m[2, 2])[:, None], (m[2, 0] * cols)[None, :], out=w)
        for axis in (0, 1):
            torch.add((m[axis, 1] * rows + m[axis, 2])[:, None], (m[axis, 0] * cols)[None, :], out=out[k, ..., axis])
            if divide:
                out[k, ..., axis].div_(w)
    return out


def homographies_from_positions(positions, step: int = 4) -> Tensor:
    """Least-squares homographies that best map each frame's pixel grid onto given positions.

    Parameters
    ----------
    positions : Tensor, shape (F, H, W, 2)
        Where pixel (u, v) of frame k lands, in reference pixel coordinates (for example
        :func:`hbis_torch.reconstruct.positions.optical_sample_positions`).
    step : int
        Use every ``step``-th pixel in each direction (the maps are smooth).

    Returns
    -------
    Tensor, shape (F, 3, 3), float64
    """
    positions = torch.as_tensor(positions, dtype=torch.float64)
    if positions.ndim != 4 or positions.shape[-1] != 2 or min(positions.shape[1:3]) < 2:
        raise HbisInputError(f"positions must have shape (F, H, W, 2), got {tuple(positions.shape)}")
    if not torch.isfinite(positions).all():
        raise HbisInputError("positions contain non-finite values")
    H, W = positions.shape[1:3]
    rows, cols = fit_grid(H, W, step)
    return homographies_from_grid(positions[:, rows][:, :, cols], rows, cols, H, W)


def fit_grid(H: int, W: int, step: int = 4, most: int = 64) -> tuple[Tensor, Tensor]:
    """The rows and columns (int64) :func:`homographies_from_positions` fits a homography on:
    every ``step``-th one of an (H, W) frame, and the last; a larger step where that would give
    more than ``most`` lines (a smooth map's least-squares homography barely changes with a
    denser grid, and a full frame's 16 fits of 77k points each took a third of a second)."""
    rows = torch.unique(torch.cat((torch.arange(0, H, max(step, -(-H // most))), torch.tensor([H - 1]))))
    cols = torch.unique(torch.cat((torch.arange(0, W, max(step, -(-W // most))), torch.tensor([W - 1]))))
    return rows, cols


def homographies_from_grid(positions, rows, cols, H: int, W: int) -> Tensor:
    """:func:`homographies_from_positions` from the positions of a product grid of pixels only.

    Parameters
    ----------
    positions : Tensor, shape (F, len(rows), len(cols), 2)
        Where pixel (cols[j], rows[i]) of frame k lands, in reference pixel coordinates.
    rows, cols : Tensor
        Pixel rows and columns of an (H, W) frame (for example :func:`fit_grid`'s).
    H, W : int
        The frame's size (it conditions the fit).

    Returns
    -------
    Tensor, shape (F, 3, 3), float64
    """
    positions = torch.as_tensor(positions, dtype=torch.float64)
    if not torch.isfinite(positions).all():
        raise HbisInputError("positions contain non-finite values")
    F = positions.shape[0]
    vv, uu = torch.meshgrid(torch.as_tensor(rows).double(), torch.as_tensor(cols).double(), indexing="ij")
    # Condition the DLT: centre and scale both point sets the same way.
    norm = _normaliser(H, W, torch.float64)
    src = apply_homography(norm, torch.stack((uu, vv), -1).reshape(-1, 2))[None]  # (1, N, 2)
    # One frame per DLT: its system (2N, 9) is a few tens of MB where a full frame's stack of
    # them would take gigabytes; each frame's fit is independent.
    h_n = torch.cat([
        kornia.geometry.homography.find_homography_dlt(src, apply_homography(norm, frame.reshape(1, -1, 2)))
        for frame in positions
    ])
    out = torch.linalg.inv(norm) @ h_n @ norm
    return out / out[:, 2:3, 2:3]


def _normaliser(H: int, W: int, dtype) -> Tensor:
    """3x3 matrix taking pixel coordinates to a centred frame of half-size about 1."""
    s = max(H, W) / 2.0
    return torch.tensor(
        [[1 / s, 0, -(W - 1) / 2 / s], [0, 1 / s, -(H - 1) / 2 / s], [0, 0, 1]], dtype=dtype
    )


@functools.lru_cache(maxsize=16)
def _frame_constants(H: int, W: int) -> tuple[Tensor, ...]:
    """Per frame size, float64, shared (callers must not modify them): the normaliser and its
    inverse (3, 3), the identity (3, 3), the corners (4, 3) and the centre (3,) in homogeneous
    pixel coordinates."""
    corners = torch.tensor([[0, 0, 1], [W - 1, 0, 1], [0, H - 1, 1], [W - 1, H - 1, 1]], dtype=torch.float64)
    centre = torch.tensor([(W - 1) / 2, (H - 1) / 2, 1.0], dtype=torch.float64)
    return (_normaliser(H, W, torch.float64), _normaliser_inverse(H, W), torch.eye(3, dtype=torch.float64),
            corners, centre)


@functools.lru_cache(maxsize=32)
def _update_basis(H: int, W: int, model: str) -> Tensor:
    """(3, 3, k) for frames of H x W px: W(dp) = I + basis @ dp is the small warp of ``model`` with
    normalised parameters dp, in pixel coordinates. Shared: callers must not modify it."""
    norm, norm_inv, eye3 = _frame_constants(H, W)[:3]
    steps = _params_to_matrix(torch.eye(N_PARAMS[model], dtype=torch.float64), model) - eye3  # (k, 3, 3)
    return (norm_inv @ steps @ norm).permute(1, 2, 0).contiguous()


@functools.lru_cache(maxsize=32)
def _corner_jacobian(H: int, W: int, model: str) -> Tensor:
    """(8, k): d(x', y')/dp in px at the four corners of an H x W frame (x' rows, then y'), for
    ``model``'s normalised parameters. Shared: callers must not modify it."""
    scale = max(H, W) / 2.0
    hx, hy = (W - 1) / 2 / scale, (H - 1) / 2 / scale
    x = torch.tensor([-hx, hx, -hx, hx], dtype=torch.float64)
    y = torch.tensor([-hy, -hy, hy, hy], dtype=torch.float64)
    jx, jy = _warp_jacobian(x, y, model)
    return torch.cat((torch.stack(jx, -1), torch.stack(jy, -1))) * scale


def _normaliser_inverse(H: int, W: int) -> Tensor:
    """Inverse of ``_normaliser(H, W, float64)``: normalised -> pixel coordinates."""
    s = max(H, W) / 2.0
    return torch.tensor([[s, 0, (W - 1) / 2], [0, s, (H - 1) / 2], [0, 0, 1]], dtype=torch.float64)


def _params_to_matrix(p: Tensor, model: str) -> Tensor:
    """(F, k) parameters of a small motion -> (F, 3, 3) matrices (identity at p = 0)."""
    m = torch.eye(3, dtype=p.dtype).repeat(p.shape[0], 1, 1)
    m[:, 0, 2], m[:, 1, 2] = p[:, 0], p[:, 1]
    if model == "similarity":
        m[:, 0, 0] += p[:, 2]
        m[:, 1, 1] += p[:, 2]
        m[:, 0, 1], m[:, 1, 0] = -p[:, 3], p[:, 3]
    elif model in ("affine", "homography"):
        m[:, 0, 0] += p[:, 2]
        m[:, 0, 1] += p[:, 3]
        m[:, 1, 0] += p[:, 4]
        m[:, 1, 1] += p[:, 5]
        if model == "homography":
            m[:, 2, 0], m[:, 2, 1] = p[:, 6], p[:, 7]
    return m


def _embedding(model: str) -> Tensor:
    """(8, k) matrix E with warp_jacobian(model) = warp_jacobian("homography") @ E."""
    e = torch.zeros(8, N_PARAMS[model], dtype=torch.float64)
    e[0, 0] = e[1, 1] = 1.0
    if model == "similarity":
        e[2, 2] = e[5, 2] = 1.0  # scale: (x, y)
        e[3, 3], e[4, 3] = -1.0, 1.0  # rotation: (-y, x)
    elif model == "affine":
        e = torch.eye(8, 6, dtype=torch.float64)
    elif model == "homography":
        e = torch.eye(8, dtype=torch.float64)
    return e


_EMBEDDING = {m: _embedding(m) for m in ALL_MODELS}


def _warp_jacobian(x: Tensor, y: Tensor, model: str) -> tuple[list[Tensor], list[Tensor]]:
    """d(x', y')/dp at the identity, as two lists of k tensors shaped like x (normalised units)."""
    one, zero = torch.ones_like(x), torch.zeros_like(x)
    jx, jy = [one, zero], [zero, one]
    if model == "similarity":
        jx += [x, -y]
        jy += [y, x]
    elif model == "affine":
        jx += [x, y, zero, zero]
        jy += [zero, zero, x, y]
    elif model == "homography":
        jx += [x, y, zero, zero, -x * x, -x * y]
        jy += [zero, zero, x, y, -x * y, -y * y]
    return jx, jy


@functools.lru_cache(maxsize=16)
def _grid_jacobian(H: int, W: int, model: str) -> Tensor:
    """d(x', y')/dp of ``model`` at a 5 x 5 grid over the frame, stacked as (2 * 25, k)."""
    s = max(H, W) / 2.0
    x = torch.linspace(-(W - 1) / 2, (W - 1) / 2, 5, dtype=torch.float64) / s
    y = torch.linspace(-(H - 1) / 2, (H - 1) / 2, 5, dtype=torch.float64) / s
    x, y = (t.reshape(-1) for t in torch.meshgrid(x, y, indexing="ij"))
    jx, jy = _warp_jacobian(x, y, model)
    return torch.cat((torch.stack(jx, -1), torch.stack(jy, -1)))


def lk_motion_difference(a: Tensor, b: Tensor, H: int, W: int, use: Tensor | None) -> Tensor:
    """Distance (px) between where two sets of homographies send the frame's corners: the
    largest over the frames in ``use`` (F,) bool, or per frame (F,) when ``use`` is None."""
    corners = torch.tensor([[0, 0], [W - 1, 0], [0, H - 1], [W - 1, H - 1]], dtype=torch.float64)
    d = (apply_homography(a, corners) - apply_homography(b, corners)).norm(dim=-1).amax(-1)
    return d if use is None else d[use].max()
