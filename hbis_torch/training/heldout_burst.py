"""The held-out matrix's burst rows: bursts the training never saw, from a renderer of their own.

The training's bursts (:mod:`hbis_torch.training.burst_data`) come from
:func:`hbis_torch.simulate.burst.simulate_burst`: the scene blurred by a Gaussian, averaged over
an S x S box on the output grid, then sampled where the motion puts each pixel, with Gaussian
noise. These bursts share none of that but the motion's convention (frame px -> reference px):

* **scenes**: the held-out photographs (:data:`hbis_torch.training.heldout.PHOTOS`), resized onto
  the output grid with scikit-image's anti-aliased resize;
* **the pixel**: every frame pixel averages the scene over its own footprint, traced through the
  frame's homography (a (2S)^2-point quadrature of the square, each point a bilinear read of the
  output grid), so rotated and zoomed frames integrate rotated and scaled squares; the bilinear
  reads soften the scene by about half an output pixel (at S = 2, still frames weigh the output
  pixels 1, 7, 7, 1 / 16 per axis), a little lens blur of their own;
* **the lens**: none, or a uniform disc (defocus) rather than a Gaussian;
* **the noise**: Poisson-Gaussian (shot noise of a full well, read noise), drawn with numpy,
  quantised to 8 or 10 bits; vignetting-free;
* **the motion**: drawn here (:func:`motions_for`), moving objects by a separate layer.

A cell is a condition of :data:`BURST_CONDITIONS` x a photograph x S: :func:`make_burst` renders
its frames and truth; training/eval_matrix.py ``--bursts`` assembles them as a user's burst is
assembled and scores both methods against the truth.
"""

from __future__ import annotations

import dataclasses

import numpy as np


@dataclasses.dataclass(frozen=True)
class BurstCondition:
    """One held-out setting of a burst."""

    name: str
    frames: int = 12
    max_shift_px: float = 1.5
    rotation_deg: float = 0.0
    zoom: float = 0.0
    full_well_e: float = 5_000.0
    read_noise_e: float = 3.0
    bit_depth: int = 8
    disc_radius_px: float = 0.0  # defocus: a uniform disc of this radius, LR px
    moving_object: bool = False
    brightness: float = 0.0  # largest change of gain (and a tenth of it as offset)


BURST_CONDITIONS = (
    BurstCondition("12 frames, shifts to 1.5 px"),
    BurstCondition("30 frames, shifts to 3 px", frames=30, max_shift_px=3.0),
    BurstCondition("5 frames (few)", frames=5),
    BurstCondition("rotation 1 deg, zoom 1 %", rotation_deg=1.0, zoom=0.01),
    BurstCondition("moving object in half the frames", moving_object=True),
    BurstCondition("brightness changes 10 %", brightness=0.1),
    BurstCondition("defocus disc 0.7 px", disc_radius_px=0.7),
    BurstCondition("low light (500 e-, 5 e- read)", full_well_e=500.0, read_noise_e=5.0),
    BurstCondition("clean (50k e-, 10 bit)", full_well_e=50_000.0, read_noise_e=2.0, bit_depth=10),
)


def truth_for(photo_name: str, scale: int, size: int) -> np.ndarray:
    """The photograph's centre, resized (anti-aliased) onto the output grid, (S size, S size)
    float64 in [0, 1]; the photograph's own pixel is about 1.5 output pixels."""
    from skimage.transform import resize

    from hbis_torch.simulate.rasters import photo

    image = photo(photo_name).astype(np.float64)
    side = min(min(image.shape), int(round(1.5 * scale * size)))
    y0, x0 = (image.shape[0] - side) // 2, (image.shape[1] - side) // 2
    return resize(image[y0:y0 + side, x0:x0 + side], (scale * size, scale * size), anti_aliasing=True)


def motions_for(cond: BurstCondition, size: int, rng: np.random.Generator) -> np.ndarray:
    """(frames, 3, 3) homographies frame px -> reference px, frame 0 the identity: shifts uniform
    in +-max_shift_px, rotations and zooms uniform within the condition's, about the centre."""
    c = (size - 1) / 2
    out = [np.eye(3)]
    for _ in range(cond.frames - 1):
        a = np.deg2rad(rng.uniform(-cond.rotation_deg, cond.rotation_deg))
        z = 1 + rng.uniform(-cond.zoom, cond.zoom)
        tx, ty = rng.uniform(-cond.max_shift_px, cond.max_shift_px, 2)
        r = z * np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
        m = np.eye(3)
        m[:2, :2] = r
        m[:2, 2] = np.array([tx, ty]) + np.array([c, c]) - r @ np.array([c, c])
        out.append(m)
    return np.stack(out)


def _pixel_average(scene: np.ndarray, motion: np.ndarray, scale: int, size: int) -> np.ndarray:
    """Each frame pixel's average of ``scene`` (the output grid) over its footprint through
    ``motion``: a (2S)^2-point quadrature of the pixel's square, bilinear reads."""
    from scipy.ndimage import map_coordinates

    q = 2 * scale
    offsets = (np.arange(q) + 0.5) / q - 0.5
    v, u = np.mgrid[0:size, 0:size].astype(np.float64)
    total = np.zeros((size, size))
    for dv in offsets:
        for du in offsets:
            x, y, w = motion @ np.stack(((u + du).ravel(), (v + dv).ravel(), np.ones(u.size)))
            U, V = scale * (x / w + 0.5) - 0.5, scale * (y / w + 0.5) - 0.5  # on the output grid
            total += map_coordinates(scene, [V.reshape(size, size), U.reshape(size, size)], order=1, mode="nearest")
    return total / q**2


def make_burst(cond: BurstCondition, photo_name: str, scale: int, size: int, seed: int):
    """The frames and truth of one burst cell.

    Parameters
    ----------
    cond : BurstCondition
    photo_name : str
        One of :data:`hbis_torch.training.heldout.PHOTOS`.
    scale : int
        S.
    size : int
        Side of the frames, LR px.
    seed : int
        Seed of the motion, the moving object and the noise.

    Returns
    -------
    frames : ndarray, shape (frames, size, size), uint8 or uint16
    truth : ndarray, shape (S size, S size), float32 in [0, 1]
        The scene on the reference frame's output grid (what the reconstruction should show).
    bit_depth : int
    """
    from scipy.ndimage import convolve

    rng = np.random.default_rng(seed)
    truth = truth_for(photo_name, scale, size)
    motions = motions_for(cond, size, rng)
    lens = truth
    if cond.disc_radius_px > 0:
        r = cond.disc_radius_px * scale
        n = int(np.ceil(r))
        yy, xx = np.mgrid[-n:n + 1, -n:n + 1]
        disc = (xx**2 + yy**2 <= r * r).astype(np.float64)
        lens = convolve(truth, disc / disc.sum(), mode="nearest")
    moved = None
    if cond.moving_object:  # a bright square of a third of the view, elsewhere in half the frames
        moved = lens.copy()
        side = scale * size // 3
        v0, u0 = scale * size // 6, scale * size // 6
        moved[v0 + side // 2:v0 + side // 2 + side, u0 + side // 2:u0 + side // 2 + side] = 0.9
    white = 2**cond.bit_depth - 1
    frames = []
    for k, motion in enumerate(motions):
        scene = moved if moved is not None and k % 2 == 1 else lens
        signal = _pixel_average(scene, motion, scale, size)
        if cond.brightness and k:
            signal = (1 + rng.uniform(-cond.brightness, cond.brightness)) * signal \
                + rng.uniform(-cond.brightness, cond.brightness) / 10
        electrons = rng.poisson(np.clip(signal, 0, None) * cond.full_well_e) + rng.normal(0, cond.read_noise_e,
                                                                                         signal.shape)
        level = np.clip(np.round(electrons / cond.full_well_e * white), 0, white)
        frames.append(level.astype(np.uint8 if cond.bit_depth <= 8 else np.uint16))
    return np.stack(frames), truth.astype(np.float32), cond.bit_depth
