"""The lens blur of a burst, measured on its own straight edges (a slanted-edge fit on every edge).

A burst's frames sample the scene at many sub-pixel offsets. Around a straight edge, every
frame's pixels, placed at their measured positions in the reference frame, trace the edge's
profile finely, as the slanted-edge method (ISO 12233) does with a tilted target. Each short
straight edge is fitted, on the raw samples (no reconstruction, no regularisation between), with
the model

    value(p) = c0 + c1 * E(n . p - t),   E = step * pixel * Gaussian(sigma),

the step blurred by the pixel's area projected on the edge's normal ``n`` (two boxes of widths
aperture x abs(cos theta) and aperture x abs(sin theta), in closed form) and by a Gaussian lens of
standard deviation ``sigma`` (LR px). Scenes have soft edges as well as sharp ones (shadows,
defocus, texture), and a soft edge only ever adds to the fitted sigma. The lens is common to
every edge; the scene's softness varies from edge to edge. So the lens shows as a **pile-up of
the sharpest edges at one sigma**: the estimate is the median of the lowest tight group of
:func:`sharpest_group` (at least :data:`MIN_EDGES` edges, and a tenth of the accepted ones,
within :data:`GROUP_WIDTH`, starting among the lowest tenth: stray fits lie below, of noise or of
edges sharpened by the scene's own processing, as a camera's; a group above more strays keeps a
falling share of its weight, :func:`stray_share`, the rest going to the strays' own sigma,
:func:`undone`); where the sharpest edges spread
instead (a soft scene: a raster enlarged, a photograph's own blur; or sharp scenes whose own
processing sharpened some edges more than others), the lens is at most the sharpest edges' blur,
and that bound is undone (:func:`bound_to_undo`): through the same trust ramp, so a soft scene's
sharpest edges (from :data:`MAX_TRUSTED` on) have nothing undone, since the burst cannot tell its
lens from its scene there, and undoing blur that is not the lens costs several dB. For the same
reason a group softer than :data:`FULL_TRUST` has only a share of its blur undone, none from
:data:`MAX_TRUSTED` on (:func:`sigma_to_undo`).

An edge is accepted when its window holds one straight edge (the structure tensor's coherence),
its step stands :data:`MIN_CONTRAST_NOISE` times above the samples' noise, the fit explains the
samples to within the noise (and a share of the step, for registration errors; a larger share
where too few edges pass, :data:`CLUTTERED_RESIDUAL_STEP`), and sigma's own standard error is
small.

The estimate is what the burst path's Wiener filter undoes (``classical_sr(lens_sigma=)``);
``hbis reconstruct`` prints it, and ``--psf-sigma`` sets it instead.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

TILE_PX = 8
"""Side of the square tiles (reference LR px) that each give at most one edge point."""
HALF_ACROSS, HALF_ALONG = 3.5, 4.0
"""The window of samples around an edge point (LR px), across the edge and along it."""
MAX_EDGES = 80
"""Edge points fitted at most: the strongest coherent ones."""
MAX_FRAMES = 12
"""Frames an edge's fit takes at most, spread over the burst: a dozen sample its profile finely."""
MIN_COHERENCE = 0.7
"""The structure tensor's (l1 - l2) / (l1 + l2) over a tile: 1 for one straight edge."""
MIN_CONTRAST_NOISE = 12.0
"""The step (c1) over the samples' noise that an edge needs."""
MAX_SIGMA_ERROR = 0.06
"""Largest standard error of an edge's sigma (LR px) that is accepted."""
MAX_RESIDUAL_NOISE = 2.0
MAX_RESIDUAL_STEP = 0.06
"""Largest RMS residual of an edge's fit: MAX_RESIDUAL_NOISE times the samples' noise plus
MAX_RESIDUAL_STEP times the step (registration errors of a few hundredths of a pixel leave
residuals in proportion to the step; a second edge or a thin line in the window leaves more)."""
CLUTTERED_RESIDUAL_STEP = 0.09
"""Where fewer than :data:`MIN_EDGES` edges pass the residual test, fits within
:data:`MAX_RESIDUAL_NOISE` noise's plus this share of the step are taken instead (windows where
other texture lies beside the edge: a busy scene seen at a coarse scale). On development bursts
(the training photographs at their own scale on a grid three times the frames', rendered apart
from the project, four bursts with 1 to 5 clean edges of 80) the lens they gave gained +0.19 to
+0.86 dB over undoing none, where the true lens gained +0.93 to +1.16; 2 x MAX_RESIDUAL_STEP
gained less (+0.16 to +0.50)."""
MIN_EDGES = 8
"""The fewest edges in the sharpest group (module docstring)."""
GROUP_SHARE = 0.1
"""The sharpest group holds at least this share of the accepted edges (at most
:data:`MAX_EDGES` are fitted, so a larger frame does not make a chance group easier)."""
GROUP_WIDTH = (0.05, 0.05)
"""The sharpest group's spread of sigma may reach a + b x its lowest sigma (LR px): edges that
share one lens agree to a few hundredths of a pixel (their fits' standard errors)."""
LOOSE_WIDTH = 1.5
"""A group spread up to this many times :data:`GROUP_WIDTH` still counts, with less weight
(:func:`sharpest_group`); edges spread evenly over a range (a soft scene) do not reach it."""
GROUP_START, GROUP_START_SHARE = 3, 0.1
"""The sharpest group may lie above up to a = max(GROUP_START, GROUP_START_SHARE x the accepted)
sharper fits: stray fits may lie below the lens (noise; an edge the scene's own processing
sharpened, as a camera's does), and their number grows with the edges fitted. A group above more
strays than that keeps a share of its weight, falling linearly to none at 2a strays
(:func:`stray_share`): a count of a few strays varies by about its square root from burst to
burst, so an all-or-nothing limit gives two nearly equal bursts answers a whole lens apart."""
MAX_SIGMA = 3.0
"""The largest sigma (LR px) a fit may reach."""
SCENE_MARGIN = 0.1
"""Sigma (LR px) taken off the sharpest group's in quadrature before it is undone: even a scene's
sharpest edges are a little soft, and undoing too much blur (ringing) costs far more than too
little (some blur left)."""
FULL_TRUST, MAX_TRUSTED = 0.5, 0.8
"""Sharpest edges that agree on a sigma up to FULL_TRUST (LR px) are taken for the lens; above
it, they may as well be a scene drawn uniformly soft (an enlarged raster, a print) as a lens out
of focus, which a burst cannot tell apart, and a share of the blur is undone that falls linearly
to nothing at MAX_TRUSTED (a calibrated ``--psf-sigma`` is undone whole): undoing a scene's own
softness costs several dB, undoing too little only leaves some blur, and a ramp keeps two nearly
equal bursts from getting answers a whole lens apart. A Gaussian of 0.8 LR px leaves 4 % of the
contrast at the pixel's Nyquist frequency."""
DOUBT_RAMP = GROUP_WIDTH[0]
"""Sigma (LR px) over which :attr:`LensEstimate.doubt` rises from 0 at :data:`FULL_TRUST` to 1:
the width within which edges of one lens agree, so two bursts whose sharpest edges agree to the
estimate's own precision get nearly the same doubt."""


class LensEstimate(NamedTuple):
    """What :func:`estimate_lens_sigma` measured.

    ``sharpest``: the sigma the sharpest edges agree on (LR px; None: too few clean edges, or
    they do not agree); ``group``: how many agree; ``agreement``: how well, in [0, 1]
    (:func:`sharpest_group`);
    ``sigma``: the lens blur to undo, LR px (``agreement`` x :func:`sigma_to_undo` of ``sharpest``;
    0 where it is None); ``edges``: the accepted edges;
    ``edge_sigmas``: each accepted edge's sigma (LR px), sorted; ``tried``: the edges fitted;
    ``cluttered``: the edges were taken with the looser residual test
    (:data:`CLUTTERED_RESIDUAL_STEP`), too few passing the usual one.
    """

    sharpest: float | None
    sigma: float
    group: int
    edges: int
    edge_sigmas: np.ndarray
    tried: int
    agreement: float = 1.0
    below: int = 0
    cluttered: bool = False

    @property
    def doubt(self) -> float:
        """In [0, 1]: 0 where the sharpest edges are sharp enough to be taken for the lens (or no
        group agrees), rising over :data:`DOUBT_RAMP` above :data:`FULL_TRUST` to 1, where only a
        share of their blur is undone (:func:`sigma_to_undo`): the classical image then keeps
        blur that may be the lens's or the scene's own, which the burst cannot tell apart. The
        learned method's adaptation reads it (:func:`~hbis_torch.reconstruct.learned.adapt.forward_blur`)."""
        if self.sharpest is None:
            return 0.0
        return min(max((self.sharpest - FULL_TRUST) / DOUBT_RAMP, 0.0), 1.0)

    def describe(self) -> str:
        """One line for the user."""
        if self.sharpest is None:
            if self.edges < MIN_EDGES:
                return (f"lens blur: not measured ({self.edges} clean straight edges of {self.tried} tried, "
                        f"{MIN_EDGES} needed); none undone (set one with --psf-sigma)")
            low = ", ".join(f"{v:.2f}" for v in self.edge_sigmas[:4])
            found = (f"the sharpest of {self.edges} straight edges do not agree on one lens ({low}, ... LR px): "
                     f"it is at most {np.median(self.edge_sigmas[:BOUND_EDGES]):.2f} LR px")
            if self.sigma == 0:
                return f"lens blur: {found}; none undone (set one with --psf-sigma)"
            return f"lens blur: {found}; undoing sigma {self.sigma:.2f} LR px (--psf-sigma sets it)"
        kind = "straight edges (beside other texture: too few clean ones)" if self.cluttered else "straight edges"
        found = f"{self.group} of {self.edges} {kind} agree on sigma {self.sharpest:.2f} LR px"
        strays = stray_share(self.below, self.edges) < 1
        if self.agreement < 1 and not strays:
            found = (f"the sharpest {self.group} of {self.edges} straight edges agree only loosely on sigma "
                     f"{self.sharpest:.2f} LR px")
        if strays:
            found += f", above {self.below} sharper fits (a burst's stray fits are about a tenth of its edges)"
        if self.sigma == 0 and self.sharpest < MAX_TRUSTED:
            return f"lens blur: {found}, within the scene's own margin ({SCENE_MARGIN} LR px); none undone"
        if self.sharpest >= MAX_TRUSTED:
            return (f"lens blur: not undone: {found}, softer than any focused lens (a scene without sharp "
                    "edges, or a lens out of focus); set one with --psf-sigma")
        if self.sharpest > FULL_TRUST or self.agreement < 1:
            soft = ", so soft that it may be the scene's own" if self.sharpest > FULL_TRUST else ""
            rest = ""
            if self.agreement < 1:
                rest = (f", the rest on the {self.below} sharper fits'" if self.below else
                        f", the rest on the sharpest {BOUND_EDGES}'")
            return (f"lens blur: {found}{soft}; undoing a share, sigma {self.sigma:.2f} LR px{rest} "
                    "(--psf-sigma sets it)")
        return f"lens blur: {found}; undoing sigma {self.sigma:.2f} LR px (--psf-sigma overrides)"


def stray_share(start: int, accepted: int) -> float:
    """The weight of a group above ``start`` sharper fits among ``accepted`` edges: 1 up to a
    (:data:`GROUP_START`), falling linearly to 0 at 2a."""
    a = max(GROUP_START, GROUP_START_SHARE * accepted)
    return min(max(2.0 - start / a, 0.0), 1.0)


def sharpest_group(sigmas: np.ndarray) -> tuple[float, int, float, int] | None:
    """The lowest tight group of ``sigmas`` (sorted, LR px): at least max(:data:`MIN_EDGES`,
    :data:`GROUP_SHARE` x their number) of them, starting among the lowest ones
    (:data:`GROUP_START`).

    Returns (median sigma, members, agreement, below), None where no group counts at all.
    ``agreement`` in [0, 1] is the group's weight: 1 where its spread is within
    :data:`GROUP_WIDTH`, falling linearly to 0 at :data:`LOOSE_WIDTH` times that width (edges
    that share one lens agree to their fits' errors, which are not much smaller than that width,
    so an all-or-nothing test gives two nearly equal bursts answers a whole lens apart), times
    :func:`stray_share` of the ``below`` sharper fits under it. The group of the highest weight
    counts, the lowest among equals.
    """
    size = max(MIN_EDGES, math.ceil(GROUP_SHARE * len(sigmas)))
    best = None
    for start in range(len(sigmas) - size + 1):
        share = stray_share(start, len(sigmas))
        if share == 0 or (best is not None and share <= best[2]):
            break  # no later group can weigh more
        group = sigmas[start:start + size]
        width = GROUP_WIDTH[0] + GROUP_WIDTH[1] * group[0]
        agreement = share * min(max((LOOSE_WIDTH - (group[-1] - group[0]) / width) / (LOOSE_WIDTH - 1), 0.0), 1.0)
        if agreement > 0 and (best is None or agreement > best[2]):
            members = np.count_nonzero(np.abs(sigmas - np.median(group)) <= width)
            best = (float(np.median(group)), int(members), agreement, start)
    return best


def edge_profile(d: np.ndarray, theta: float, sigma: float, aperture: float = 1.0) -> np.ndarray:
    """The response of a pixel to a unit step at signed distance ``d`` (LR px) from its centre.

    The step, blurred by the Gaussian lens, averaged over the pixel's area: along the edge's
    normal the area is two boxes, of widths aperture x abs(cos theta) and aperture x abs(sin
    theta), so the average is four terms of the blurred step's second antiderivative.

    Parameters
    ----------
    d : np.ndarray
        Distance of the pixel's centre from the edge along the edge's normal, LR px.
    theta : float
        The normal's angle to the pixel's x axis, radians.
    sigma : float
        The Gaussian lens's standard deviation, LR px (> 0).
    aperture : float
        The pixel's sensitive side, LR px (1: the whole pixel).

    Returns
    -------
    np.ndarray
        In [0, 1]: 0 far on the dark side, 1 far on the bright side (d > 0).
    """
    import torch

    from hbis_torch.reconstruct.edge_fit import profile

    d = torch.as_tensor(np.asarray(d, dtype=np.float64))
    return profile(d, torch.tensor(float(theta), dtype=torch.float64), torch.tensor(float(sigma), dtype=torch.float64),
                   aperture, derivatives=False).numpy()


def _edge_points(reference: np.ndarray, noise: float) -> list[tuple[float, float, float]]:
    """Points (x, y, normal's angle) on strong straight edges of ``reference``: in each
    :data:`TILE_PX` tile, the pixel of the steepest gradient, where the local structure tensor
    says one straight edge; strongest first, at most :data:`MAX_EDGES`.

    The structure tensor is computed only at tile peaks, strongest first, until enough edges are
    found (:func:`_structure_at`): over a whole 12 MP frame its three smoothed products cost
    seconds, and a few hundred peaks are read."""
    import torch
    from hbis_torch.gaussian_filter import gaussian_filter

    # frame-sized arrays in torch's memory (as capture.burst.luminance's: NumPy's huge pages
    # fault in slower than the arithmetic on them takes)
    smooth = gaussian_filter(reference, 0.7, output=torch.empty(reference.shape, dtype=torch.float64).numpy())
    gy, gx = (g.numpy() for g in torch.gradient(torch.from_numpy(smooth)))
    del smooth
    magnitude = np.hypot(gx, gy, out=torch.empty(reference.shape, dtype=torch.float64).numpy())
    T, m = TILE_PX, TILE_PX  # a margin of a tile: room for the motions and the window
    H, W = reference.shape
    rows, cols = (H - 2 * m) // T, (W - 2 * m) // T
    if rows < 1 or cols < 1:
        return []
    tiles = magnitude[m:m + rows * T, m:m + cols * T].reshape(rows, T, cols, T).transpose(0, 2, 1, 3)
    flat = tiles.reshape(rows, cols, T * T)
    best = flat.argmax(axis=2)
    ys = (m + np.arange(rows)[:, None] * T + best // T).ravel()
    xs = (m + np.arange(cols)[None, :] * T + best % T).ravel()
    peak = np.take_along_axis(flat, best[..., None], axis=2).ravel()
    # A step of height c blurred to about a pixel has a peak gradient near c / 2.5 after the
    # smoothing: the step must stand MIN_CONTRAST_NOISE noise's above the floor.
    strong = peak > MIN_CONTRAST_NOISE * noise / 2.5
    order = np.argsort(-np.where(strong, peak, -1), kind="stable")[:int(strong.sum())]
    out = []
    for start in range(0, len(order), 4 * MAX_EDGES):
        batch = order[start:start + 4 * MAX_EDGES]
        coherence, angle = _structure_at(gx, gy, ys[batch], xs[batch])
        for i in np.flatnonzero(coherence > MIN_COHERENCE)[:MAX_EDGES - len(out)]:
            out.append((float(xs[batch[i]]), float(ys[batch[i]]), float(angle[i])))
        if len(out) == MAX_EDGES:
            break
    return out


def _structure_at(gx: np.ndarray, gy: np.ndarray, ys: np.ndarray, xs: np.ndarray):
    """The structure tensor of the gradients (gx, gy) (H, W), smoothed by a Gaussian of 1.5 px
    (scipy.ndimage's ``gaussian_filter``, as :mod:`hbis_torch.gaussian_filter` sums it), at the N
    pixels (ys, xs) at least its radius (6 px) inside the frame: its coherence (l1 - l2) / (l1 + l2)
    and its dominant direction's angle (radians), each (N,). Equal to the whole frame's filtered
    tensor read at those pixels: the filter of a window of the radius around a pixel reads nothing
    the whole frame's would not."""
    from hbis_torch.gaussian_filter import gaussian_filter

    radius = int(4.0 * 1.5 + 0.5)  # gaussian_filter's own reach at truncate=4
    offsets = np.arange(-radius, radius + 1)
    rows, cols = ys[:, None, None] + offsets[None, :, None], xs[:, None, None] + offsets[None, None, :]
    wx, wy = gx[rows, cols], gy[rows, cols]
    jxx, jyy, jxy = (gaussian_filter(a, (0, 1.5, 1.5))[:, radius, radius] for a in (wx * wx, wy * wy, wx * wy))
    root = np.sqrt((jxx - jyy) ** 2 + 4 * jxy * jxy)
    coherence = root / np.maximum(jxx + jyy, 1e-30)
    return coherence, [0.5 * math.atan2(2 * b, a - c) for a, c, b in zip(jxx, jyy, jxy)]


def _samples(frames, positions, weights, x: float, y: float, theta: float):
    """Every frame's samples within :data:`HALF_ACROSS` LR px of the edge point (x, y) across the
    edge and :data:`HALF_ALONG` along it: positions (N, 2) relative to the point, and values (N,)."""
    F, H, W = frames.shape[:3]
    reach = int(math.ceil(math.hypot(HALF_ACROSS, HALF_ALONG))) + 2
    normal = np.array([math.cos(theta), math.sin(theta)])
    along = np.array([-normal[1], normal[0]])
    xy, values = [], []
    # where each frame's pixel (y, x) lies, relative
    shift = np.asarray(positions[:, int(y), int(x)]) - np.array([x, y])
    block = _block(positions, shift, x, y, reach, H, W)
    for k in np.unique(np.linspace(0, F - 1, min(F, MAX_FRAMES)).round().astype(int)):
        d = shift[k]
        r0, r1 = max(int(math.floor(y - d[1])) - reach, 0), min(int(math.ceil(y - d[1])) + reach + 1, H)
        c0, c1 = max(int(math.floor(x - d[0])) - reach, 0), min(int(math.ceil(x - d[0])) + reach + 1, W)
        if r1 <= r0 or c1 <= c0:
            continue
        if block is not None:
            (R0, C0), window = block
            window = window[k, r0 - R0:r1 - R0, c0 - C0:c1 - C0]
        else:
            window = positions[k, r0:r1, c0:c1]
        p = np.asarray(window).reshape(-1, 2) - np.array([x, y])
        inside = ((np.abs(p @ normal) < HALF_ACROSS) & (np.abs(p @ along) < HALF_ALONG)
                  & (weights[k, r0:r1, c0:c1].reshape(-1) > 0.5))
        xy.append(p[inside])
        values.append(frames[k, r0:r1, c0:c1].reshape(-1)[inside])
    return np.concatenate(xy), np.concatenate(values)


def _block(positions, shift: np.ndarray, x: float, y: float, reach: int, H: int, W: int):
    """Lazy positions (a burst's BurstPositions) of every frame over the rows and columns that all
    frames' windows around (x, y) span, in one call: ((first row, first column), (F, rows, cols,
    2) array); None for an array (indexed as it is) or where the frames' windows lie far apart."""
    if not getattr(positions, "computed_where_read", False) or not np.isfinite(shift).all():
        return None
    r0, r1 = max(int(math.floor(y - shift[:, 1].max())) - reach, 0), min(int(math.ceil(y - shift[:, 1].min())) + reach + 1, H)
    c0, c1 = max(int(math.floor(x - shift[:, 0].max())) - reach, 0), min(int(math.ceil(x - shift[:, 0].min())) + reach + 1, W)
    if r1 <= r0 or c1 <= c0 or (r1 - r0) * (c1 - c0) > 16 * (2 * reach + 2) ** 2:
        return None
    return (r0, c0), np.asarray(positions[:, r0:r1, c0:c1])


def _fit_edges(samples: list, thetas: list, noise: float, aperture: float) -> list:
    """Fit every edge's samples at once: the module docstring's model, solved by
    :func:`~hbis_torch.reconstruct.edge_fit.fit_edges` for all edges together.

    ``samples``: each edge's (positions (N, 2) relative to its point, values (N,)), as
    :func:`_samples` gives them; ``thetas``: each edge's normal's angle (radians) to start from.
    Returns, for each edge, (sigma, its standard error, c1, RMS residual in noise units), or None
    where the edge has too few samples on a side or its fit leaves the window's middle."""
    import torch

    from hbis_torch.reconstruct.edge_fit import fit_edges

    fitted, start = [], []
    for (xy, values), theta in zip(samples, thetas):
        proj = xy @ np.array([math.cos(theta), math.sin(theta)])
        low, high = values[proj < -1.5], values[proj > 1.5]
        if len(values) >= 40 and len(low) >= 10 and len(high) >= 10:
            lo, hi = float(np.median(low)), float(np.median(high))  # the start: a step through the middle
            fitted.append(len(start))
            start.append([lo, hi - lo, 0.0, theta, 0.4])
        else:
            fitted.append(None)
    if not start:
        return [None] * len(samples)
    kept = [k for k, f in enumerate(fitted) if f is not None]
    n = max(len(samples[k][1]) for k in kept)
    xy, values = torch.zeros((len(kept), 2, n), dtype=torch.float64), torch.zeros((len(kept), n), dtype=torch.float64)
    valid = torch.zeros((len(kept), n), dtype=torch.bool)
    for i, k in enumerate(kept):  # the edges padded to the most samples, the padding not valid
        m = len(samples[k][1])
        xy[i, :, :m], values[i, :m] = torch.from_numpy(samples[k][0].T), torch.from_numpy(samples[k][1])
        valid[i, :m] = True
    start = torch.tensor(start, dtype=torch.float64)
    theta = start[:, 3]
    inf, ones = torch.full_like(theta, math.inf), torch.ones_like(theta)
    lower = torch.stack([-inf, -inf, -2 * ones, theta - 0.5, 0.02 * ones], 1)
    upper = torch.stack([inf, inf, 2 * ones, theta + 0.5, MAX_SIGMA * ones], 1)
    q, rms, error = fit_edges(xy, values, valid, start, lower, upper, noise, aperture)
    out = []
    for f in fitted:
        # None where the edge left the window's middle: one side barely sampled
        out.append(None if f is None or abs(float(q[f, 2])) > 1.5 else
                   (float(q[f, 4]), float(error[f]), float(q[f, 1]), float(rms[f])))
    return out


def estimate_lens_sigma(frames, positions, weights, reference: int, noise: float,
                        aperture: float = 1.0) -> LensEstimate:
    """The Gaussian lens blur of a burst, from its straight edges (module docstring).

    Parameters
    ----------
    frames : array, shape (F, H, W), float32
        The brightness-corrected grey frames.
    positions : array, shape (F, H, W, 2), float64, or BurstPositions
        Each pixel's (x, y) in the reference frame, LR px (a burst's lazy positions are read a
        window at a time).
    weights : array, shape (F, H, W)
        The samples' weights (robustness x trust); samples under 0.5 are left out.
    reference : int
        The reference frame's index (its edges are the ones looked for).
    noise : float
        The noise standard deviation of one sample (frames' units).
    aperture : float
        The pixel's sensitive side, LR px.

    Returns
    -------
    LensEstimate
    """
    import torch

    frames, weights = np.asarray(frames), np.asarray(weights)
    if not getattr(positions, "computed_where_read", False):  # a BurstPositions is read a window at a time
        positions = np.asarray(positions)
    noise = max(float(noise), 1e-4)

    reference_frame = torch.empty(frames.shape[1:3], dtype=torch.float64).numpy()  # (as _edge_points')
    reference_frame[...] = frames[reference]
    points = _edge_points(reference_frame, noise)
    del reference_frame
    samples = []
    for x, y, theta in points:
        xy, values = _samples(frames, positions, weights, x, y, theta)
        samples.append((xy, values.astype(np.float64)))
    fits = _fit_edges(samples, [theta for _, _, theta in points], noise, aperture)
    sigmas, cluttered = _accepted(fits, noise, MAX_RESIDUAL_STEP), False
    if len(sigmas) < MIN_EDGES:
        loose = _accepted(fits, noise, CLUTTERED_RESIDUAL_STEP)
        if len(loose) >= MIN_EDGES:
            sigmas, cluttered = loose, True
    found = sharpest_group(sigmas) if len(sigmas) >= MIN_EDGES else None
    if found is None:
        bound = bound_to_undo(sigmas) if len(sigmas) >= MIN_EDGES else 0.0
        return LensEstimate(None, bound, 0, len(sigmas), sigmas, len(points), 0.0, cluttered=cluttered)
    sharpest, group, agreement, below = found
    return LensEstimate(sharpest, undone(sigmas, sharpest, agreement, below), group, len(sigmas), sigmas,
                        len(points), agreement, below, cluttered)


def _accepted(fits: list, noise: float, residual_step: float) -> np.ndarray:
    """The sigmas (sorted, LR px) of the :func:`_fit_edges` ``fits`` that pass the module
    docstring's tests, with ``residual_step`` the share of the step the residual may add."""
    sigmas = []
    for fit in fits:
        if fit is None:
            continue
        s, error, c1, rms = fit
        contrast = abs(c1) / noise
        if error < MAX_SIGMA_ERROR and contrast > MIN_CONTRAST_NOISE and \
                rms < MAX_RESIDUAL_NOISE + residual_step * contrast:
            sigmas.append(s)
    return np.sort(np.array(sigmas))


def undone(sigmas: np.ndarray, sharpest: float, agreement: float, below: int) -> float:
    """The lens blur undone (LR px) for a group of :func:`sharpest_group`: its
    :func:`sigma_to_undo` with the group's weight ``agreement``, and the rest of the weight on the
    ``below`` accepted fits sharper than the group (the median of their sigmas, through
    :func:`sigma_to_undo`, at most the group's); where there are none, on :func:`bound_to_undo`
    (the sharpest edges, the group's own lowest: at most the group's), as for edges that do not
    agree at all, so that a group's weight falling to nothing moves the answer by little.

    A group loses weight because its edges spread or because sharper fits lie below it. Those
    fits are noise, edges the scene's own processing sharpened, or edges at the lens itself
    while the group's carry the scene's own softness as well (photographs rendered at their own
    scale at S = 2): either way the lens is at most about theirs, and undoing that much rather
    than nothing keeps what a sharper lens would gain. It never undoes more than the group alone
    would."""
    group = sigma_to_undo(sharpest)
    fallback = min(sigma_to_undo(float(np.median(sigmas[:below]))) if below else bound_to_undo(sigmas), group)
    return agreement * group + (1 - agreement) * fallback


BOUND_EDGES = 3
"""The sharpest edges whose median sigma bounds the lens where no group agrees
(:func:`bound_to_undo`): one edge alone may be a stray fit."""


def bound_to_undo(sigmas: np.ndarray) -> float:
    """The lens blur undone (LR px) where the sharpest edges do not agree on one: the median of the
    :data:`BOUND_EDGES` sharpest accepted fits (``sigmas``, sorted) bounds the lens from above,
    through :func:`sigma_to_undo` (less the scene's margin, and the trust ramp, so a soft scene's
    edges have nothing undone).

    On development bursts (the training photographs at their own scale, through a renderer
    written apart from the project, 16 bursts at S = 2 and 3 with a lens of 0.3 LR px and the same
    16 without one), whose own sharpening spreads their sharpest edges below and around the lens,
    it changed two with the lens, where undoing nothing left +1.14 / +1.56 dB to the true lens:
    +0.32 / +0.49 dB; and one without, +0.03 dB."""
    return sigma_to_undo(float(np.median(sigmas[:BOUND_EDGES]))) if len(sigmas) else 0.0


def sigma_to_undo(sharpest: float) -> float:
    """The lens blur (LR px) undone for sharpest edges that agree on ``sharpest`` (LR px): less
    :data:`SCENE_MARGIN` in quadrature, and a share of it falling from 1 at :data:`FULL_TRUST` to
    0 at :data:`MAX_TRUSTED`."""
    share = min(max((MAX_TRUSTED - sharpest) / (MAX_TRUSTED - FULL_TRUST), 0.0), 1.0)
    return share * math.sqrt(max(sharpest**2 - SCENE_MARGIN**2, 0.0))


def burst_lens(grey, positions, weights, reference: int, notes: list | None = None) -> LensEstimate:
    """What a burst's deblurring undoes when no lens is given: :func:`burst_lens_estimate` (its
    ``sigma``, LR px, 0 where it cannot say), its line (:meth:`LensEstimate.describe`) added to
    ``notes``.

    Parameters
    ----------
    grey, positions, weights, reference
        As :func:`burst_lens_estimate` takes them.
    notes : list, optional

    Returns
    -------
    LensEstimate
    """
    estimate = burst_lens_estimate(grey, positions, weights, reference)
    if notes is not None:
        notes.append(estimate.describe())
    return estimate


def burst_lens_estimate(grey, positions, weights, reference: int) -> LensEstimate:
    """:func:`estimate_lens_sigma` on a burst's grey (or luminance) frames, with the samples' noise
    measured on the reference frame: the median of Immerkaer's operator
    (:func:`hbis_torch.sensor.noise.immerkaer`) over all its pixels (edges and texture are a
    minority of pixels, so the median stays with the noise).

    Parameters
    ----------
    grey : Tensor, shape (F, H, W), float32
        The frames' luminance (``reconstruct.burst._luma``).
    positions : Tensor, shape (F, H, W, 2), float64, or BurstPositions
    weights : Tensor, shape (F, H, W)
    reference : int

    Returns
    -------
    LensEstimate
    """
    grey = grey.numpy()
    noise = 1.4826 * float(np.median(_immerkaer_magnitude(grey[reference]), overwrite_input=True)) / 6.0
    return estimate_lens_sigma(grey, positions, weights.numpy(), reference, noise)


# Rows of a frame :func:`_immerkaer_magnitude` takes at a time: a 12 MP frame's float64
# temporaries are 96 MB each of fresh pages, which cost more to fault in than the arithmetic.
NOISE_PIECE_SAMPLES = 1 << 16


def _immerkaer_magnitude(frame: np.ndarray) -> np.ndarray:
    """``abs(immerkaer(frame))`` in float64, flattened ((H - 2) (W - 2),): computed a piece of
    :data:`NOISE_PIECE_SAMPLES` samples' rows at a time, each piece with its two neighbouring
    rows (the operator's reach), so the same values as on the whole frame."""
    import torch

    from hbis_torch.sensor.noise import immerkaer

    H, W = frame.shape
    out = torch.empty((max(H - 2, 0), max(W - 2, 0)), dtype=torch.float64).numpy()  # (as _edge_points')
    rows = max(1, NOISE_PIECE_SAMPLES // max(W, 1))
    for r in range(0, H - 2, rows):
        np.abs(immerkaer(frame[r:r + rows + 2].astype(np.float64)), out=out[r:r + rows])
    return out.reshape(-1)
