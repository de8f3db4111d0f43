"""The burst lattice's holes filled from the samples around them: each sample read as the
bilinear interpolation of its four nearest nodes, solved by least squares with a ridge towards
the splat's image, and taken where the splat left a node (almost) no sample of its own.

The splat (:func:`~hbis_torch.reconstruct.classical.splat.splat_on_lattice`) moves each sample to
its nearest node and fills the nodes no sample reaches from their neighbours. A burst's random
shifts often cluster: with 8 frames at S = 2 a whole row or column of node classes may get hardly
a sample of its own, and those nodes are then interpolations, which the Wiener filter reads as
samples and sharpens. A sample that lies between nodes still says something about every node
around it; fitting the nodes to all the samples where they lie (as iterative back-projection
does [1]_, but on the lattice, before any deblurring, so the lens estimate never enters) recovers
it. The ridge keeps nodes the samples hardly constrain near the splat's value, and the fit is
spread with the splat's 3-tap kernel, so the Wiener filter's model of the lattice still holds.

Every node takes some of the fit (:func:`fill_holes_from_samples`), in proportion as its splat
weight falls below twice the typical node's: a hole takes all of it, a typical node half. The
splat puts each sample on its nearest node, a jitter of a quarter of an output pixel that the
Wiener filter's model does not hold, and the fit has none. Fitting every node fully gained more
with the lens's estimate or the true lens (development bursts of two renderers, 640 x 480, S = 2
to 4), but lost up to 1.1 dB where the lens undone was 40 % too large: a fitted lattice is
sharper than the splat's, and deblurring too much lens then over-sharpens it. Twice the typical
weight keeps most of the gain and loses at most 0.6 dB there (``training/dev_hole_share.py``).
A node of more than twice the typical weight keeps the splat's value to the bit.

Only the nodes within :data:`SOLVE_RADIUS` of a node that takes the fit are solved for, the
others held at the splat's value, and only the samples around them are read: a node's fitted
value hardly depends on nodes farther away (the ridge and its neighbours' samples hold them).
With 16 frames of 640 x 480 at S = 2 that is most of the lattice; a burst of many frames, whose
nodes are mostly above twice the typical weight, reads far fewer. Every sample is still read once
for the ridge's scale (:func:`data_weights`).

Shapes: lattices (rows, cols) in HR px; the normal equations on the lattice framed by one node
each way, (rows + 2, cols + 2). Everything in float32: a node's sums add a few dozen samples, and
the conjugate gradients stop at a relative residual of :data:`TOLERANCE`, far above float32's
rounding (tests/test_lattice_fit.py checks the fit against float64).

References
----------
.. [1] M. Irani and S. Peleg, "Improving resolution by image registration", CVGIP: Graphical Models
   and Image Processing 53(3), 1991, pp. 231-239.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from hbis_torch.reconstruct.classical.lattice import PIECE_SAMPLES

# A node takes the fit in proportion as its splat weight falls below this share of the typical
# node's (fully at 0). Chosen on development bursts of two renderers (training/dev_hole_share.py):
# 0.5, only the holes, gained least with the lens's estimate; every node gained most but lost up to
# 1.1 dB with a lens over-estimated by 40 %; 2 lost at most 0.6 dB there.
HOLE_SHARE = 2.0
# Lattices of more nodes than this (a 2048 x 2048 frame at S = 2) are not fitted: the normal
# equations and the solve hold a dozen lattice-sized float32 arrays.
MAX_FIT_NODES = 1 << 24
# The ridge's weight, as a share of a node's typical data weight (the median over nodes of the sum
# of w beta^2 of the samples around it, on a subset of them: :func:`fit_lattice`). Chosen on
# development bursts (training simulator).
RIDGE = 0.3
# Only the nodes within this many nodes of a hole are solved for; the others keep the splat's
# value (where the ridge pulls them anyway), so only the samples around the holes are read. On
# development bursts (training simulator, S = 2 to 4, the lens estimated and given 40 % too large)
# the output moved from the whole lattice's solve by at most 3e-4 of full scale on ten uncontrived
# bursts (2e-3 at a radius of 1) and 1.5e-3 on four with clustered shifts, no PSNR by 0.001 dB.
SOLVE_RADIUS = 3
# Conjugate-gradient steps at most, and the relative residual they stop at.
ITERATIONS = 30
TOLERANCE = 1e-3
# The stencil's offsets (dx, dy) kept: the other four are their mirror images (the matrix is
# symmetric: node a's weight on node a + o is node a + o's on node a).
HALF_STENCIL = ((0, 0), (1, 0), (0, 1), (1, 1), (-1, 1))
_CORNERS = ((0, 0), (1, 0), (0, 1), (1, 1))


def fill_holes_from_samples(image: Tensor, den: Tensor, typical: float, batches, kernel_sigma: float,
                            shared: dict | None = None) -> Tensor:
    """The splat's image with its holes taken from :func:`fit_lattice`.

    Parameters
    ----------
    image : Tensor, shape (rows, cols), float32
        The splat's image (holes filled from neighbours); overwritten where it changes.
    den : Tensor, shape (rows, cols)
        The splat's weight at each node.
    typical : float
        The typical node's weight (:func:`~hbis_torch.reconstruct.classical.holes.typical_weight`).
    batches, kernel_sigma, shared
        As :func:`fit_lattice`'s.

    Returns
    -------
    Tensor, shape (rows, cols): ``image`` itself, unchanged where no node's weight is below
    :data:`HOLE_SHARE` times the typical one or the lattice is larger than :data:`MAX_FIT_NODES`.
    """
    if image.numel() > MAX_FIT_NODES:
        return image
    share = den.to(image.dtype).div(HOLE_SHARE * typical).neg_().add_(1).clamp_(0, 1)
    if not bool((share > 0).any()):
        return image
    fitted = fit_lattice(image, batches, kernel_sigma, solve=_near(share > 0, SOLVE_RADIUS), shared=shared)
    return image.addcmul_(share, fitted.sub_(image))


def _near(nodes: Tensor, radius: int) -> Tensor:
    """The framed lattice's nodes (rows + 2, cols + 2) within ``radius`` nodes (a square) of
    ``nodes`` (rows, cols), bool."""
    return _dilate(torch.nn.functional.pad(nodes, (1, 1, 1, 1)), radius)


def fit_lattice(image: Tensor, batches, kernel_sigma: float, ridge: float = RIDGE,
                iterations: int = ITERATIONS, dtype=torch.float32, solve: Tensor | None = None,
                shared: dict | None = None) -> Tensor:
    """The lattice whose bilinear interpolation fits the samples, spread like the splat's image.

    Parameters
    ----------
    image : Tensor, shape (rows, cols)
        The splat's image on the lattice (holes filled): the ridge's target.
    batches : callable
        () -> iterable of :class:`~hbis_torch.reconstruct.classical.lattice.NodeBatch` (each
        sample's nearest node and its offset from it, its value and weight).
    kernel_sigma : float
        The splat Gaussian (HR px): the fitted nodes are spread with its normalised 3-tap kernel.
    ridge : float
        The ridge's weight relative to a node's typical data weight (> 0).
    iterations : int
        Conjugate-gradient steps at most.
    dtype : torch.dtype
        Of the sums and the solve (float64 in the tests).
    solve : Tensor, shape (rows + 2, cols + 2), bool, optional
        The framed lattice's nodes solved for (default: all); the others keep the splat's value
        and only the samples near the solved nodes are read in full (every sample gives the
        ridge's scale, :func:`data_weights`). Where the spread solution is used, its nodes'
        neighbours must be solved too.
    shared : dict, optional
        What depends on the samples' places and weights alone (the matrix A^T W A, the ridge's
        weight), kept here by the first call and read by the next ones, whose samples lie where
        the first's do with other values (a colour burst's channels): they sum only A^T W v.
        The same bits as without it.

    Returns
    -------
    Tensor, shape (rows, cols), in ``image``'s dtype
    """
    rows, cols = image.shape
    # a sample's bilinear corners are its nearest node's neighbours; where that reads every node
    # (16 frames of 640 x 480 at S = 2), no sample's node is looked up to test it (a tenth of the sums' time)
    read = None if solve is None else _dilate(solve, 1)
    read = None if read is not None and bool(read.all()) else read
    prior = torch.nn.functional.pad(image.to(dtype)[None, None], (1, 1, 1, 1), mode="replicate")[0, 0]
    if shared and "stencil" in shared:  # another channel of the same samples
        rhs, stencil, lam = _right_hand_side(batches, (rows, cols), dtype, read), shared["stencil"], shared["lam"]
    else:
        rhs, stencil = normal_equations(batches, (rows, cols), dtype, read)
        diagonal = _every_samples_diagonal(batches, (rows, cols), dtype, read, stencil[0])
        data = diagonal[diagonal > 0]
        if data.numel() == 0:  # no sample of any weight: nothing to fit (a copy: callers may write to it)
            return image.clone()
        # (a flat stride through the framed lattice: with an even width, only its even columns)
        lam = ridge * float(data[:: max(1, data.numel() // 100_000)].median())
        if shared is not None:
            shared.update(stencil=stencil, lam=lam)
    solve = torch.ones(prior.shape, dtype=torch.bool) if solve is None else solve
    rhs.add_(prior, alpha=lam)
    fitted = _conjugate_gradients(stencil, lam, rhs, prior, iterations, solve.to(dtype))
    return _spread(fitted, kernel_sigma).to(image.dtype)


def _dilate(nodes: Tensor, radius: int) -> Tensor:
    """``nodes`` (rows, cols) bool and the nodes within ``radius`` of them (a square): shifted
    ORs, about a hundredth of the time of a max pool."""
    out = nodes.clone()
    for axis in (0, 1):
        grown = out.clone()
        for step in range(1, radius + 1):
            size = out.shape[axis] - step
            grown.narrow(axis, step, size).logical_or_(out.narrow(axis, 0, size))
            grown.narrow(axis, 0, size).logical_or_(out.narrow(axis, step, size))
        out = grown
    return out


def normal_equations(batches, shape: tuple[int, int], dtype=torch.float32,
                     read: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """A^T W v and A^T W A of the samples, A the bilinear interpolation from the framed lattice.

    ``read`` (rows + 2, cols + 2), bool: only the samples whose nearest node it marks are added
    (default: all). Each sample's terms are added to the cell it lies in (one scatter of the
    :data:`_TERMS` rows: a third of the time of a scatter per term), then each term moves to the
    cell's corner it belongs to.

    Returns
    -------
    rhs : Tensor, shape (rows + 2, cols + 2)
    stencil : Tensor, shape (5, rows + 2, cols + 2)
        Node a's weight on node a + o for the offsets o of :data:`HALF_STENCIL`.
    """
    framed = (shape[0] + 2, shape[1] + 2)
    rhs = torch.zeros(framed, dtype=dtype)
    stencil = torch.zeros((len(HALF_STENCIL), *framed), dtype=dtype)
    columns = range(len(_TERMS))
    _add_at_corners(_cell_sums(batches, shape, dtype, columns, read), columns,
                    lambda target: rhs if target is None else stencil[target])
    return rhs, stencil


def _right_hand_side(batches, shape: tuple[int, int], dtype, read: Tensor | None) -> Tensor:
    """:func:`normal_equations`' ``rhs`` alone (the same sums, in the same order)."""
    rhs = torch.zeros((shape[0] + 2, shape[1] + 2), dtype=dtype)
    columns = range(len(_CORNERS))  # (the right-hand side's terms come first in _TERMS)
    _add_at_corners(_cell_sums(batches, shape, dtype, columns, read), columns, lambda target: rhs)
    return rhs


def data_weights(batches, shape: tuple[int, int], dtype=torch.float32, read: Tensor | None = None) -> Tensor:
    """Each node's data weight, the sum of w beta^2 over every sample around it:
    :func:`normal_equations`' ``stencil[0]`` (the same sums, in the same order), from the
    :data:`_TERMS` of the diagonal alone, (rows + 2, cols + 2); ``read`` as
    :func:`normal_equations`' (then complete only at the nodes whose 3 x 3 neighbours it all marks)."""
    diagonal = torch.zeros((shape[0] + 2, shape[1] + 2), dtype=dtype)
    columns = [column for column, (target, _) in enumerate(_TERMS) if target == 0]
    _add_at_corners(_cell_sums(batches, shape, dtype, columns, read), columns, lambda target: diagonal)
    return diagonal


def _every_samples_diagonal(batches, shape: tuple[int, int], dtype, read: Tensor | None, summed: Tensor) -> Tensor:
    """:func:`data_weights` of every sample, given ``summed``, the diagonal of the samples ``read``
    marks (:func:`normal_equations`' ``stencil[0]``): the same bits, reading again only the samples
    near the nodes ``summed`` lacks some of.

    A node's diagonal adds the samples of the four cells it is a corner of, whose nearest nodes
    are its 3 x 3 neighbours: where ``read`` marks all of them, ``summed`` added the same samples
    in the same order. At 640 x 480 with 16 frames at S = 2 that is every node, and the second
    pass over the samples (about a sixth of the fit's time) is not made."""
    if read is None:
        return summed
    lacking = _dilate(~read, 1)
    if not bool(lacking.any()):
        return summed
    return torch.where(lacking, data_weights(batches, shape, dtype, _dilate(lacking, 1)), summed)


def _add_at_corners(cells: Tensor, columns, into) -> None:
    """Add each of :data:`_TERMS` ``columns``' cell sums (len(columns), rows + 2, cols + 2) to the
    node of its cell's corner in ``into(target)`` (the term's stencil row, or None: the right-hand
    side)."""
    for column, sums in zip(columns, cells):
        target, (ax, ay) = _TERMS[column]
        out = into(target)
        # a cell's corner (ax, ay) is the node ax, ay beyond the cell's own (its corner (0, 0))
        out[ay:, ax:] += sums[:out.shape[0] - ay, :out.shape[1] - ax]


def _cell_sums(batches, shape: tuple[int, int], dtype, columns, read: Tensor | None = None) -> Tensor:
    """The samples' :data:`_TERMS` ``columns`` summed per cell (the cell's corner (0, 0) on the
    framed lattice): (len(columns), rows + 2, cols + 2); ``read`` as :func:`normal_equations`'."""
    rows, cols = shape
    cells = torch.zeros(len(columns), (rows + 2) * (cols + 2), dtype=dtype)
    for batch in batches():
        if read is not None:
            batch = _samples_at(batch, read)
        for piece in _pieces(batch):
            base, terms = _cell_terms(piece, rows, cols, dtype, columns)
            cells.index_add_(1, base, terms)
    return cells.view(len(columns), rows + 2, cols + 2)


def _pieces(batch):
    """``batch`` in pieces of :data:`~hbis_torch.reconstruct.classical.lattice.PIECE_SAMPLES`
    samples, in order: the same sums in the same order, with float32 temporaries (256 kB each)
    that stay in the cache through the twenty or so passes over them (at 640 x 480 with 16
    frames the terms took 0.58 of the time of whole batches of a million samples; in pieces a
    quarter as large the calls' own cost shows)."""
    size = len(batch.values)
    if size <= PIECE_SAMPLES:
        yield batch
        return
    for start in range(0, size, PIECE_SAMPLES):
        part = slice(start, start + PIECE_SAMPLES)
        yield _take(batch, lambda field: field[part])


def _samples_at(batch, nodes: Tensor):
    """The samples of ``batch`` whose nearest node ``nodes`` (the framed lattice, bool) marks
    (those beyond the frame: as its edge's)."""
    rows, cols = nodes.shape[0] - 2, nodes.shape[1] - 2
    # int32 indices (a framed lattice of MAX_FIT_NODES fits): a third of int64's time
    index = batch.row.clamp(-1, rows).add_(1).mul_(cols + 2).add_(batch.col.clamp(-1, cols)).add_(1)
    kept = nodes.view(-1).index_select(0, index).nonzero().squeeze(1)
    if len(kept) == len(index):
        return batch
    return _take(batch, lambda field: field.index_select(0, kept))


def _take(batch, pick):
    """``batch`` with ``pick`` (Tensor -> Tensor) applied to each of its samples' fields."""
    weights = None if batch.weights is None else pick(batch.weights)
    return batch._replace(**{name: pick(getattr(batch, name)) for name in ("values", "col", "row", "dx", "dy")},
                          weights=weights)


def _pairs():
    """(stencil row, corner a, corner c), corners as indices into :data:`_CORNERS`, for every
    pair whose offset c - a is in :data:`HALF_STENCIL`."""
    out = []
    for a, (ax, ay) in enumerate(_CORNERS):
        for k, (ox, oy) in enumerate(HALF_STENCIL):
            if (ax + ox, ay + oy) in _CORNERS:
                out.append((k, a, _CORNERS.index((ax + ox, ay + oy))))
    return out


_PAIRS = _pairs()
# The columns a sample adds to its cell: (stencil row or None for the right-hand side, the corner
# whose node the term belongs to).
_TERMS = [(None, a) for a in _CORNERS] + [(k, _CORNERS[a]) for k, a, _ in _PAIRS]


def _cell_terms(batch, rows: int, cols: int, dtype, columns) -> tuple[Tensor, Tensor]:
    """Each sample's cell (flat framed index of its corner (0, 0), (N,) int64) and its
    :data:`_TERMS` ``columns`` (len(columns), N): w v beta_a for the four corners, w beta_a beta_c
    for the pairs."""
    base, beta, weight = _corners(batch, rows, cols, dtype)
    values = batch.values.to(dtype)
    terms = torch.empty(len(columns), len(weight), dtype=dtype)
    for row, column in enumerate(columns):
        if column < len(_CORNERS):
            torch.mul(beta[column], values, out=terms[row])
        else:
            _, a, c = _PAIRS[column - len(_CORNERS)]
            torch.mul(beta[a], beta[c], out=terms[row])
    terms.mul_(weight)
    return base, terms


def _corners(batch, rows: int, cols: int, dtype) -> tuple[Tensor, list, Tensor]:
    """Each sample's cell (the flat framed index of its corner (0, 0), (N,) int64; corner (ax, ay)
    is ``ax + ay (cols + 2)`` beyond it), its four corners' bilinear weights (in :data:`_CORNERS`'
    order, (N,) each) and the sample's weight (0 where a corner lies beyond the framed lattice)."""
    # sample = node - d with d in [-1/2, 1/2]: its corner (0, 0) is the node, or the one before
    # where d > 0; the fraction exact in float32 (no large coordinate is formed)
    dx, dy = batch.dx.to(dtype), batch.dy.to(dtype)
    after_x, after_y = dx > 0, dy > 0
    # int32 (a framed lattice of MAX_FIT_NODES fits): a third of int64's time
    x0 = batch.col.to(torch.int32) - after_x.to(torch.int32)
    y0 = batch.row.to(torch.int32) - after_y.to(torch.int32)
    fx = torch.where(after_x, 1 - dx, -dx)
    fy = torch.where(after_y, 1 - dy, -dy)
    inside = (x0 >= -1) & (x0 < cols) & (y0 >= -1) & (y0 < rows)
    weight = inside.to(dtype) if batch.weights is None else batch.weights.to(dtype) * inside
    # (int64 for the scatter: index_add_ takes int32 indices several times slower)
    base = y0.clamp_(-1, rows - 1).add_(1).mul_(cols + 2).add_(x0.clamp_(-1, cols - 1)).add_(1).to(torch.int64)
    gx, gy = 1 - fx, 1 - fy
    beta = [gx * gy, fx * gy, gx * fy, fx * fy]
    return base, beta, weight


def _apply(stencil: Tensor, diagonal: Tensor, g: Tensor) -> Tensor:
    """(A^T W A + lam I) g on the framed lattice (rows + 2, cols + 2); ``diagonal`` is
    ``stencil[0] + lam``."""
    out = torch.mul(g, diagonal)
    rows, cols = g.shape
    for k, (ox, oy) in enumerate(HALF_STENCIL[1:], start=1):
        # node a takes stencil[k][a] g[a + o]; node a + o takes stencil[k][a] g[a] (for the nodes
        # a whose a + o is on the lattice: the stencil is 0 for the others)
        a = (slice(max(0, -oy), rows - max(0, oy)), slice(max(0, -ox), cols - max(0, ox)))
        b = (slice(a[0].start + oy, a[0].stop + oy), slice(a[1].start + ox, a[1].stop + ox))
        out[a].addcmul_(stencil[k][a], g[b])
        out[b].addcmul_(stencil[k][a], g[a])
    return out


def _conjugate_gradients(stencil: Tensor, lam: float, rhs: Tensor, start: Tensor, iterations: int,
                         solve: Tensor) -> Tensor:
    """Solve (A^T W A + lam I) g = rhs for the nodes ``solve`` (1, else 0) marks, the others held
    at ``start``, by Jacobi-preconditioned conjugate gradients from ``start``, stopping at
    :data:`TOLERANCE` of the first residual. The dot products are summed in the lattice's dtype
    (torch's cascade sum: about 1e-7 of a float32 sum here, far below the tolerance; a sum into
    float64 took six times as long)."""
    g = start.clone()
    diagonal = stencil[0] + lam
    residual = (rhs - _apply(stencil, diagonal, g)).mul_(solve)
    inverse = solve / diagonal
    z = residual * inverse
    direction = z.clone()
    rz = float((residual * z).sum())
    first = math.sqrt(max(rz, 0.0))
    for _ in range(iterations):
        if rz <= (TOLERANCE * first) ** 2:
            break
        step = _apply(stencil, diagonal, direction).mul_(solve)
        alpha = rz / float((direction * step).sum())
        g.add_(direction, alpha=alpha)
        residual.sub_(step, alpha=alpha)
        torch.mul(residual, inverse, out=z)
        rz, previous = float((residual * z).sum()), rz
        direction.mul_(rz / previous).add_(z)
    return g


def _spread(framed: Tensor, kernel_sigma: float) -> Tensor:
    """The framed lattice (rows + 2, cols + 2) smoothed by the splat's normalised 3-tap kernel
    [a, 1, a] / (1 + 2a) per axis, a = exp(-1 / (2 sigma^2)): (rows, cols)."""
    a = math.exp(-1 / (2 * kernel_sigma * kernel_sigma))
    # shifted slices: a thirtieth of the time of conv2d with a 3 x 1 kernel
    rows = (framed[:-2] + framed[2:]).mul_(a).add_(framed[1:-1]).div_(1 + 2 * a)
    return (rows[:, :-2] + rows[:, 2:]).mul_(a).add_(rows[:, 1:-1]).div_(1 + 2 * a)
