"""A colour plane of a raw burst from its scattered samples: the splat, a band at a time, and
the hole filling (the joint path of :mod:`hbis_torch.reconstruct.classical.raw_burst`).

Each colour's samples of every frame, at the positions the frames' motions give them on the
reference's grid, with their weights (:func:`sample_weights_of_colour`), are added onto the
output grid by the classical method's Gaussian splat
(:class:`Splat`: :func:`~hbis_torch.reconstruct.classical.splat.splat`'s sums in a third of its
time), a band of rows at a time (:func:`bands`), their positions computed where read
(:class:`PlanePositions`); the plane is the numerator over the denominator with the holes filled
(:func:`~hbis_torch.reconstruct.classical.holes.fill_holes` with its whole-image blurs in
float32, :func:`blur_pair`), and where clipped samples carry most of a
node's weight it goes to the clip level (:func:`plane_from_sums`). Red and blue are splatted as
differences from green, which in noisy frames go through a guided filter with green the guide
(:func:`guided_difference`).
"""

from __future__ import annotations

import torch
from torch import Tensor

# A colour whose unclipped samples weigh less than this share near an output pixel is taken as
# clipped there (set to the clip level).
CLIPPED_SHARE = 0.5


class Splat:
    """The classical method's Gaussian splat (:func:`~hbis_torch.reconstruct.classical.splat.splat`:
    each sample onto the 3 x 3 nodes around its nearest, the Gaussian's weight times its own) of
    samples in any arrangement, added a batch at a time: the numerator and denominator, or the
    denominator alone (``count`` 1: the clipped samples' weights,
    :func:`~hbis_torch.reconstruct.classical.raw_burst.joint_demosaick_sr`).

    The same sums as ``splat``'s in a third of its time: the Gaussian's nine weights are the
    products of three along each axis (in float32; the sums in float64, :data:`SPLAT_DTYPE`), and
    the sums have a frame of two nodes around the grid, where the taps beyond it land (no test
    per tap).

    Parameters
    ----------
    shape : (rows, cols)
        The output grid, (S H, S W).
    sigma : float
        The Gaussian, output px (at most 0.6: the 3 x 3 footprint).
    count : int
        2: the numerator and the denominator; 1: the denominator alone.
    """

    def __init__(self, shape: tuple[int, int], sigma: float, count: int = 2):
        rows, cols = shape
        self.shape, self.stride = (rows, cols), cols + 4
        self.c = -1.0 / (2 * sigma * sigma)
        self.sums = [torch.zeros((rows + 4) * (cols + 4), dtype=SPLAT_DTYPE) for _ in range(count)]

    def add(self, values: Tensor | None, x: Tensor, y: Tensor, weights: Tensor) -> None:
        """Samples (N,): values (None with ``count`` 1) and weights, grid coordinates ``x``, ``y``
        (node (i, j) at x = j, y = i) float64."""
        rows, cols = self.shape
        xi, yi = torch.round(x), torch.round(y)
        (x_lo, x_hi), (y_lo, y_hi) = torch.aminmax(xi), torch.aminmax(yi)
        # samples whose nearest node is two or more beyond the grid reach no node of it (where
        # there are any, or non-finite positions, they are masked: weight 0, at the frame)
        near = None
        if not (x_lo >= -1 and x_hi <= cols and y_lo >= -1 and y_hi <= rows):
            near = (xi >= -1) & (xi <= cols) & (yi >= -1) & (yi <= rows)
        fx, fy = (x - xi).to(torch.float32), (y - yi).to(torch.float32)
        if near is not None:
            fx.masked_fill_(~near, 0.0)
            fy.masked_fill_(~near, 0.0)
            xi, yi = xi.nan_to_num_(0).clamp_(-1, cols), yi.nan_to_num_(0).clamp_(-1, rows)
        # the flat index of the node up and left of the nearest (the first tap): each tap adds
        # at the same index into the sums seen from its own offset (a view), no index per tap
        first = yi.add_(1).mul_(self.stride).add_(xi.add_(1)).to(torch.int64)
        del xi, yi
        w = weights.to(SPLAT_DTYPE) if near is None else weights.to(SPLAT_DTYPE) * near
        parts = [w] if len(self.sums) == 1 else [values.to(SPLAT_DTYPE) * w, w]
        # the node at (xi + d) is d - f from the sample: the Gaussian along each axis
        # (in float32, then in the sums' dtype: a product of two dtypes costs as much as three of one)
        gx = [torch.exp((d - fx).square_().mul_(self.c)).to(SPLAT_DTYPE) for d in (-1.0, 0.0, 1.0)]
        gy = [torch.exp((d - fy).square_().mul_(self.c)).to(SPLAT_DTYPE) for d in (-1.0, 0.0, 1.0)]
        size = len(self.sums[0]) - 2 * self.stride - 2
        g = torch.empty_like(gx[0])
        term = torch.empty_like(gx[0])
        for a in range(3):
            for b in range(3):
                torch.mul(gy[a], gx[b], out=g)
                for total, part in zip(self.sums, parts):
                    total.narrow(0, a * self.stride + b, size).index_add_(0, first, torch.mul(part, g, out=term))

    def result(self, k: int, release: bool = False) -> Tensor:
        """Sum ``k`` (0 the numerator, 1 the denominator; 0 the denominator with ``count`` 1) on
        the grid, (rows, cols) float64; ``release`` frees the framed sum (no more samples can be
        added to it)."""
        rows, cols = self.shape
        out = self.sums[k].view(rows + 4, cols + 4)[2:-2, 2:-2].contiguous()
        if release:
            self.sums[k] = None
        return out


# Samples splatted at a time (a band of rows of every frame: the frames overlay the same scene,
# so a band's scatter-adds meet the same few rows of the output grid). The green of a 2000 x 1500
# burst of 16 frames at S = 2, positions and splat: 4.6-4.9 s CPU in bands of 2^20 samples,
# 3.3-3.4 s of 2^18, 3.4-3.6 s of 2^17, 3.8 s of 2^16 (the splat alone kept falling; the
# positions' calls cost more).
BAND_SAMPLES = 1 << 18
# The splat's sums: float64, as splat.splat's. In float32 (a quarter less time) a few nodes of a
# 1024 x 768 burst at S = 2 crossed fill_holes' threshold the other way (6 of 9.4 million output
# values moved, by up to 0.006).
SPLAT_DTYPE = torch.float64


def bands(frames: int, rows: int, cols: int) -> list[slice]:
    """Slices of rows of a colour plane (rows, cols) whose band of every frame holds about
    :data:`BAND_SAMPLES` samples."""
    step = max(1, BAND_SAMPLES // max(frames * cols, 1))
    return [slice(r, min(r + step, rows)) for r in range(0, rows, step)]


def sample_weights_of_colour(per_sample: Tensor | None, cell: Tensor | None, clipped: Tensor | None,
                             sensor: Tensor | None, where, rows=slice(None), which: str = "kept") -> Tensor:
    """The weights (len(where) F, r, W / 2) float32 of a colour's samples in a band of rows of its
    pattern positions' grids (``where``, (row, column) in the 2 x 2 pattern): of the unclipped
    samples (``"kept"``: 0 for clipped ones, ``clipped`` (F, H, W) bool) or of the clipped ones
    (``"lost"``); 0 at the sensor's stuck pixels (``sensor`` (H, W), 0 or 1). From the samples'
    weights ``per_sample`` (F, H, W), or else the 2 x 2 cells' ``cell`` (F, H / 2, W / 2).
    """
    parts = []
    for dv, du in where:
        w = per_sample[:, dv::2, du::2][:, rows].to(torch.float32) if per_sample is not None else cell[:, rows]
        if clipped is not None:
            hit = clipped[:, dv::2, du::2][:, rows]
            w = w * (hit if which == "lost" else hit.logical_not())
        if sensor is not None:
            w = w * sensor[dv::2, du::2][rows]
        parts.append(w)
    return torch.cat(parts) if len(parts) > 1 else parts[0]


class PlanePositions:
    """The positions of the samples at some pattern positions (a colour's), each pattern
    position's a grid of half the frames' size (pitch 2 px), computed where read from the
    burst's (a :class:`~hbis_torch.reconstruct.positions.BurstPositions`): frame ``p F + k`` is
    frame k's samples at pattern position ``where[p]``. ``half``: in the half-size grid's pixels
    (``(x + 0.5) / 2 - 0.5``), as :func:`~hbis_torch.reconstruct.classical.raw_burst.sharp_green`
    hands them to the burst path; else in the reference's px.

    Indexed as :class:`~hbis_torch.reconstruct.positions.BurstPositions`: ``[j]`` (h, w, 2),
    ``[frames, rows]`` (f, r, w, 2), float64, slices with step 1 for the frames.
    """

    dtype = torch.float64
    computed_where_read = True

    def __init__(self, positions, where: list[tuple[int, int]], half: bool = True):
        F, H, W, _ = positions.shape
        self.positions, self.where, self.count, self.half = positions, where, F, half
        self.shape = (len(where) * F, H // 2, W // 2, 2)

    def __len__(self) -> int:
        return self.shape[0]

    def __getitem__(self, index) -> Tensor:
        index = index if isinstance(index, tuple) else (index,)
        if len(index) > 2:
            raise TypeError("PlanePositions takes up to two indices (frames, rows)")
        frames, rows = (index + (slice(None),))[:2]
        if not isinstance(frames, slice):
            return self[slice(int(frames), int(frames) + 1), rows][0]
        if not isinstance(rows, slice):
            return self[frames, slice(int(rows), int(rows) + 1)][:, 0]
        picked = range(self.shape[0])[frames]
        sub = range(self.shape[1])[rows]
        if picked.step != 1:
            raise TypeError("PlanePositions takes frames with a step of 1")
        parts = []
        for p, (dv, du) in enumerate(self.where):
            first, last = max(picked.start, p * self.count), min(picked.stop, (p + 1) * self.count)
            if first >= last:
                continue
            full_rows = slice(2 * sub.start + dv, 2 * sub.stop + dv, 2 * sub.step) if len(sub) else slice(0, 0)
            band = self.positions[slice(first - p * self.count, last - p * self.count), full_rows, slice(du, None, 2)]
            # (a whole positions tensor gives a view of itself: not written over)
            parts.append(band.add(0.5).div_(2).sub_(0.5) if self.half else band)
        if not parts:
            return torch.empty((0, len(sub), self.shape[2], 2), dtype=torch.float64)
        return parts[0] if len(parts) == 1 else torch.cat(parts)


def blur_pair(*images: Tensor, sigma: float) -> Tensor:
    """The whole-image blur of :func:`~hbis_torch.reconstruct.classical.holes.fill_holes` of
    ``images`` (each (rows, cols); ``num`` and ``den``) in float32: (len(images), rows, cols)
    float32. As there, the sampled taps' convolution up to
    :data:`~hbis_torch.reconstruct.classical.holes.SEPARABLE_MAX_SIGMA`, else the FFT's Gaussian,
    all images in one batch."""
    from hbis_torch.reconstruct.classical.holes import SEPARABLE_MAX_SIGMA, _gaussian_blur, _separable_blur

    both = torch.empty((len(images),) + tuple(images[0].shape), dtype=torch.float32)
    for part, image in zip(both, images):  # not stacked in float64 first: 0.7 GB at 8000 x 6000
        part.copy_(image)
    return (_separable_blur if sigma <= SEPARABLE_MAX_SIGMA else _gaussian_blur)(both, sigma)


def plane_from_sums(acc: "Splat", lost_acc: "Splat | None") -> tuple[Tensor, Tensor | None]:
    """A colour's plane from its splat's sums (both released): num / den with the holes filled
    (:func:`~hbis_torch.reconstruct.classical.holes.fill_holes`, over num's memory; its blurs of
    the whole image, where the holes are many, in float32 with both sums in one batch,
    :func:`blur_pair`: two thirds of the time; the holes and the typical weight are still found on
    the float64 sums, whose values come in few distinct sums of the splat's weights that float32's
    rounding would tip across the threshold), and where the clipped samples, splatted alone in
    ``lost_acc`` (None: none clipped), carry the most of a node's weight, the mask of the nodes that
    go to the clip level (the unclipped samples' share of the weight below :data:`CLIPPED_SHARE`;
    its holes filled from around them). Returns (plane (S H, S W) float64, mask or None)."""
    from hbis_torch.reconstruct.classical.holes import fill_holes

    num, den = acc.result(0, release=True), acc.result(1, release=True)
    missing = lost_acc.result(0, release=True) if lost_acc is not None else None
    den_blurs: dict = {}  # den's whole-image blurs, which the clipped share below reads again

    def plane_blur(n, d, sigma):
        blurred = blur_pair(n, d, sigma=sigma)
        if missing is not None:
            den_blurs[sigma] = blurred[1].clone()
        return blurred

    plane = fill_holes(num, den, in_place=True, blur=plane_blur)
    del num
    if missing is None:
        return plane, None
    # where den's blur is known, the total's is den's plus the clipped samples' (a blur is
    # linear: one FFT, not two)
    missing_blurs = {sigma: blur_pair(missing, sigma=sigma)[0] for sigma in den_blurs}
    total = missing.add_(den)

    def share_blur(n, d, sigma):
        if sigma not in den_blurs:
            return blur_pair(n, d, sigma=sigma)
        return torch.stack((den_blurs[sigma], den_blurs[sigma] + missing_blurs[sigma]))

    share = fill_holes(den, total, in_place=True, blur=share_blur)
    return plane, share < CLIPPED_SHARE


def guided_difference(plane: Tensor, green: Tensor, strength: float, eps: float, change: Tensor | None = None,
                      rows: int = 1024) -> Tensor:
    """A colour's difference from green moved, in place, ``strength`` of the way to the guided
    filter of it (He et al., "Guided image filtering", IEEE TPAMI 35(6), 2013: in each 3 x 3
    window the difference is fitted as ``a green + b``, ``a = cov / (var + eps)``, and the
    windows' fits are averaged: ``kornia.filters.guided_blur`` with ``reflect`` borders), in
    bands of ``rows`` rows in float32 (a halo of 2 rows: the same values as the whole plane's):
    the noise of few samples a node averages out where green is flat, and the differences keep
    green's edges.

    Parameters
    ----------
    plane : Tensor, shape (S H, S W), float64
        The difference, written over.
    green : Tensor, shape (S H, S W)
        The guide (plus ``change``).
    strength : float
        0 to 1 (0: ``plane`` as it is).
    eps : float
        The regularisation (a variance of ``green``).
    change : Tensor, shape (S H, S W), optional
        Added to ``green`` (the green's sharpening: the sharp green guides).
    rows : int

    Returns
    -------
    Tensor
        ``plane``.
    """
    if strength <= 0:
        return plane
    from kornia.filters import guided_blur

    height = plane.shape[0]
    above = None  # the halo above a band as it was before the band above it was written over
    for top in range(0, height, rows):
        lo, hi, n = max(top - 2, 0), min(top + rows + 2, height), min(rows, height - top)
        g, p = green[lo:hi].to(torch.float32, copy=True), plane[lo:hi].to(torch.float32)
        if change is not None:
            g += change[lo:hi]
        if above is not None:
            p[:top - lo] = above
        above = p[top - lo + n - 2:top - lo + n].clone()
        q = guided_blur(g[None, None], p[None, None], 3, eps, border_type="reflect")[0, 0]
        part = plane[top:top + n]
        part.add_(q[top - lo:top - lo + n].double().sub_(part).mul_(strength))
    return plane
