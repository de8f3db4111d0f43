"""Hand-held bursts at real sizes, rendered apart from the training's simulator.

The project's second burst renderer (the first, :mod:`hbis_torch.training.heldout_burst`, makes
small square bursts; the training's is :mod:`hbis_torch.simulate.burst`). It makes what a person
gets from a phone held in the hand: frames of W x H pixels (640 x 480 by default, not square),
each turned, zoomed, tilted and sheared a little, blurred by the lens, noisy, 16-bit.

* **The scene** (:func:`collage`): the held-out photographs
  (:data:`hbis_torch.simulate.rasters.HELD_OUT_PHOTOS`, from scikit-image, no download) side by
  side in rows, each enlarged :data:`PHOTO_PX` = 1.25 times onto the output grid (a photograph's
  pixel is 1.25 output pixels at every S), so the truth has the photographs' own detail
  everywhere rather than one photograph blown up S times. The scene reaches :data:`MARGIN_PX` LR
  pixels beyond the reference frame on every side, so turned frames see scene, not a border.
* **The lens**: a Gaussian of ``blur_sigma_px`` LR pixels (recorded, for a blur-estimate test).
* **The pixel**: every frame pixel averages the scene over its own square footprint traced through
  the frame's motion: a 2 x 2 quadrature of the square, each point reading the scene already
  averaged over its quarter of the square (a box of S/2 output pixels, applied with the lens in
  the Fourier domain), by a cubic spline. For a frame that only moves, this is the exact average
  over the pixel; a turn or a zoom shapes the four quarters' places, not their sizes (at most 1 %
  off here).
* **The noise**: Poisson (a full well of ``full_well_e`` electrons, 5000 by default: 1 % at mid
  grey) plus Gaussian read noise, quantised to 16 bits.
* **The motion** (:data:`MOTIONS`): per frame, a homography frame px -> reference px, pixel
  centres at integers (the convention of :mod:`hbis_torch.reconstruct.positions`), frame 0 the
  reference (the identity); for ``rolling_shutter`` a shift per row added after it
  (:attr:`HandheldBurst.row_shift`); a textured object that moves on its own between every two
  frames; a gain and offset per frame; for ``shaken``, a similarity's motion and a quarter of the
  frames besides the reference smeared while the shutter was open (the scene blurred before the
  lens: along a line of :data:`SHAKE_PX` LR px in a random direction, or by a Gaussian of
  :data:`SHAKE_SIGMA_PX`, in turn; :attr:`HandheldBurst.shaken`).

:func:`render_burst` returns a :class:`HandheldBurst`: the frames (F, H, W) uint16, the truth
(S H, S W) float32 on the reference frame's output grid (the scene itself, without the lens),
the true motions, the row shifts, the gains and the lens's sigma. training/eval_handheld.py scores
the project and its peer on these bursts against the truth.
"""

from __future__ import annotations

import dataclasses
import functools

import numpy as np

#: The motions of a burst: each alone, and all of them at once.
MOTIONS = ("translation", "similarity", "homography", "rolling_shutter", "moving_object", "brightness", "all",
           "shaken")
#: Output pixels per photograph pixel in the scene.
PHOTO_PX = 1.25
#: How far (LR px) the scene reaches beyond the reference frame on every side.
MARGIN_PX = 24
#: Quadrature points per axis of a pixel's footprint.
QUADRATURE = 2
#: Largest shift of a frame, LR px (uniform in +-).
MAX_SHIFT_PX = 2.0
#: Largest turn (degrees) of the ``similarity`` motion, and its largest zoom (relative).
MAX_ROTATION_DEG, MAX_ZOOM = 1.0, 0.005
#: Largest displacement (LR px) that the perspective of the ``homography`` motion gives a corner.
MAX_PERSPECTIVE_PX = 2.0
#: Largest row-dependent shift (LR px) of the ``rolling_shutter`` motion, top row against bottom row.
MAX_SHEAR_PX = 2.0
#: Largest relative change of gain of the ``brightness`` motion, and of the offset (of white).
MAX_GAIN, MAX_OFFSET = 0.07, 0.01
#: The ``shaken`` motion's smear: a line of this length (LR px, drawn between) or a Gaussian of
#: this sigma (LR px, drawn between), in turn.
SHAKE_PX, SHAKE_SIGMA_PX = (2.0, 4.0), (0.6, 1.2)


@dataclasses.dataclass
class HandheldBurst:
    """One rendered burst and everything true about it.

    Attributes
    ----------
    frames : np.ndarray, shape (F, H, W), uint16
        The captured frames, 16 bits used.
    truth : np.ndarray, shape (S H, S W), float32 in [0, 1]
        The scene on the reference frame's grid refined S times (output pixel (i, j) is centred at
        reference px ((j + 0.5) / S - 0.5, (i + 0.5) / S - 0.5)), without the lens's blur.
    motions : np.ndarray, shape (F, 3, 3), float64
        Homography of each frame, frame px (u, v) -> reference px; frame 0 the identity.
    row_shift : np.ndarray, shape (F, H, 2), float64
        Shift (dx, dy) in reference px added to the homography's point for each frame row
        (rolling shutter; zeros otherwise): frame px (u, v) lies at ``motions[k](u, v) +
        row_shift[k, v]`` in the reference (:meth:`flow`).
    gain_offset : np.ndarray, shape (F, 2), float64
        (g, o) per frame: the frame's signal is ``g * s + o`` where the reference's is ``s``.
    object_offset : np.ndarray, shape (F, 2), float64
        Where the moving object is in each frame, against where it is in the reference, in
        output px (dx, dy); zeros without an object.
    object_box : tuple of int or None
        (x0, y0, side) of the object's square in the reference, in truth px; None without one.
    blur_sigma_px : float
        The lens's Gaussian sigma, LR px.
    scale : int
    motion : str
    clean : np.ndarray or None, shape (F, H, W), float32
        The frames before noise and quantisation (only when asked for).
    """

    frames: np.ndarray
    truth: np.ndarray
    motions: np.ndarray
    row_shift: np.ndarray
    gain_offset: np.ndarray
    object_offset: np.ndarray
    object_box: tuple | None
    blur_sigma_px: float
    scale: int
    motion: str
    clean: np.ndarray | None = None
    shaken: tuple = ()  # the frames the ``shaken`` motion smeared

    def flow(self, k: int) -> np.ndarray:
        """Where each pixel centre of frame ``k`` lies in the reference: (H, W, 2) (x, y), reference px."""
        H, W = self.frames.shape[1:]
        v, u = np.mgrid[0:H, 0:W].astype(np.float64)
        x, y = _apply(self.motions[k], u, v)
        return np.stack((x + self.row_shift[k, :, None, 0], y + self.row_shift[k, :, None, 1]), -1)

    def oracle_motions(self) -> np.ndarray:
        """(F, 3, 3) homographies frame px -> reference px as near the truth as a homography
        gets: the true ones, or, with a rolling shutter, the least-squares homography
        (scikit-image) through the true flow at a grid of 32 x 24 pixels that spans the frame.

        The flow is smooth (a homography plus a shift a row), so the grid holds it; scikit-image's
        fit takes the full SVD of a (2N, 9) matrix, whose (2N, 2N) factor costs seconds a frame
        for N in the thousands (every 8th pixel of 640 x 480: 2.5 s, 740 MB)."""
        if not np.any(self.row_shift):
            return self.motions.copy()
        from skimage.transform import ProjectiveTransform

        out = self.motions.copy()
        H, W = self.frames.shape[1:]
        rows = np.linspace(0, H - 1, min(H, 24)).round().astype(int)
        cols = np.linspace(0, W - 1, min(W, 32)).round().astype(int)
        v, u = np.meshgrid(rows, cols, indexing="ij")
        src = np.stack((u.ravel(), v.ravel()), -1).astype(np.float64)
        for k in range(1, len(out)):
            dst = self.flow(k)[v, u].reshape(-1, 2)
            if hasattr(ProjectiveTransform, "from_estimate"):  # scikit-image >= 0.26
                fit = ProjectiveTransform.from_estimate(src, dst)
                ok = bool(fit)
            else:  # pragma: no cover - older scikit-image
                fit = ProjectiveTransform()
                ok = fit.estimate(src, dst)
            if ok:
                out[k] = fit.params / fit.params[2, 2]
        return out

    def stack_gain_offset(self) -> np.ndarray:
        """(F, 2) the stack's convention: (g', o') with ``g' * frame + o'`` matching the reference."""
        g, o = self.gain_offset[:, 0], self.gain_offset[:, 1]
        return np.stack((1.0 / g, -o / g), -1)


def _apply(m: np.ndarray, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Homography ``m`` applied to points (u, v) (any equal shapes)."""
    w = m[2, 0] * u + m[2, 1] * v + m[2, 2]
    return (m[0, 0] * u + m[0, 1] * v + m[0, 2]) / w, (m[1, 0] * u + m[1, 1] * v + m[1, 2]) / w


@functools.lru_cache(maxsize=8)
def _enlarged(name: str) -> np.ndarray:
    """The photograph ``name`` enlarged :data:`PHOTO_PX` times (cubic spline), float64 in [0, 1]."""
    from skimage.transform import rescale

    from hbis_torch.simulate.rasters import photo

    out = np.clip(rescale(photo(name).astype(np.float64), PHOTO_PX, order=3, anti_aliasing=False), 0, 1)
    out.flags.writeable = False
    return out


def collage(height: int, width: int, rng: np.random.Generator, photos=None) -> np.ndarray:
    """The held-out photographs side by side in rows, each enlarged :data:`PHOTO_PX` times.

    Parameters
    ----------
    height, width : int
        Size of the scene, output px.
    rng : numpy.random.Generator
        Picks the photographs' order, their crops and whether each is mirrored.
    photos : sequence of str, optional
        Names in :data:`hbis_torch.simulate.rasters.PHOTOS` (default the held-out ones).

    Returns
    -------
    np.ndarray, shape (height, width), float64 in [0, 1]
    """
    from hbis_torch.simulate.rasters import HELD_OUT_PHOTOS

    big = [_enlarged(n) for n in (photos or HELD_OUT_PHOTOS)]
    row_h = min(min(b.shape[0] for b in big), height)
    out = np.empty((height, width))
    y = 0
    while y < height:
        h = min(row_h, height - y)
        x = 0
        while x < width:
            b = big[int(rng.integers(len(big)))]
            y0 = int(rng.integers(0, b.shape[0] - h + 1))
            tile = b[y0:y0 + h]
            if rng.random() < 0.5:
                tile = tile[:, ::-1]
            w = min(tile.shape[1], width - x)
            out[y:y + h, x:x + w] = tile[:, :w]
            x += w
        y += h
    return out


def draw_motion(motion: str, frames: int, width: int, height: int, rng: np.random.Generator):
    """The true motion of a burst.

    Returns
    -------
    motions : np.ndarray, shape (F, 3, 3)
        Frame px -> reference px; frame 0 the identity.
    row_shift : np.ndarray, shape (F, height, 2)
    gain_offset : np.ndarray, shape (F, 2)
    moving : bool
        Whether a moving object is in the scene.
    """
    if motion not in MOTIONS:
        raise ValueError(f"motion must be one of {', '.join(MOTIONS)}, got {motion!r}")
    every = motion == "all"
    cx, cy = (width - 1) / 2, (height - 1) / 2
    centre, uncentre = np.eye(3), np.eye(3)
    centre[:2, 2], uncentre[:2, 2] = (-cx, -cy), (cx, cy)
    motions = np.repeat(np.eye(3)[None], frames, 0)
    row_shift = np.zeros((frames, height, 2))
    gain_offset = np.tile([1.0, 0.0], (frames, 1))
    t = (np.arange(height) - cy) / height  # -0.5 .. 0.5 down the frame
    for k in range(1, frames):
        m = np.eye(3)
        if motion in ("similarity", "homography", "shaken") or every:
            turn = MAX_ROTATION_DEG if motion != "homography" else MAX_ROTATION_DEG / 2
            a = np.deg2rad(rng.uniform(-turn, turn))
            z = 1 + rng.uniform(-MAX_ZOOM, MAX_ZOOM)
            m[:2, :2] = z * np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
        if motion == "homography" or every:  # a corner moves by up to MAX_PERSPECTIVE_PX
            p, q = rng.uniform(-1, 1, 2) * MAX_PERSPECTIVE_PX / (cx * cx + cy * cy)
            m = m @ np.array([[1, 0, 0], [0, 1, 0], [p, q, 1.0]])
        m = uncentre @ m @ centre
        m = m / m[2, 2]
        m[:2, 2] += rng.uniform(-MAX_SHIFT_PX, MAX_SHIFT_PX, 2)
        motions[k] = m
        if motion == "rolling_shutter" or every:  # a shear and a bend across the rows
            a, b = rng.uniform(-1, 1, 2) * MAX_SHEAR_PX / 2, rng.uniform(-1, 1, 2) * MAX_SHEAR_PX / 2
            row_shift[k] = a[None] * t[:, None] + b[None] * (t[:, None] ** 2 - 1 / 12) * 2
            row_shift[k, :, 1] *= 0.25  # the readout runs down the rows: the rows mostly slide sideways
        if motion == "brightness" or every:
            gain_offset[k] = 1 + rng.uniform(-MAX_GAIN, MAX_GAIN), rng.uniform(-MAX_OFFSET, MAX_OFFSET)
    return motions, row_shift, gain_offset, motion == "moving_object" or every


def _smears(frames: int, scale: int, rng: np.random.Generator) -> dict:
    """The ``shaken`` motion's smears: {frame: kernel on the scene's grid (``scale`` px a LR px),
    normalised}, a quarter of the frames besides the reference, a line and a Gaussian in turn."""
    chosen = sorted(rng.choice(np.arange(1, frames), size=max(1, (frames - 1) // 4), replace=False).tolist())
    out = {}
    for i, k in enumerate(chosen):
        if i % 2 == 0:  # a line in a random direction, sampled finely and binned onto the grid
            length, angle = rng.uniform(*SHAKE_PX) * scale, rng.uniform(0, np.pi)
            t = np.linspace(-0.5, 0.5, 64 * int(np.ceil(length)) + 1) * length
            half = int(np.ceil(length / 2)) + 1
            kernel = np.zeros((2 * half + 1, 2 * half + 1))
            np.add.at(kernel, (np.round(half + t * np.sin(angle)).astype(int), np.round(half + t * np.cos(angle))
                               .astype(int)), 1.0)
        else:
            sigma = rng.uniform(*SHAKE_SIGMA_PX) * scale
            half = int(np.ceil(3 * sigma))
            axis = np.exp(-0.5 * (np.arange(-half, half + 1) / sigma) ** 2)
            kernel = np.outer(axis, axis)
        out[k] = kernel / kernel.sum()
    return out


def _filtered(scene: np.ndarray, scale: int, blur_sigma_px: float) -> np.ndarray:
    """B-spline coefficients (order 3) of ``scene`` (output grid) under the lens's Gaussian and a
    box of S / QUADRATURE output px (one quadrature point's share of a pixel), in the Fourier domain."""
    import scipy.fft
    from scipy.ndimage import spline_filter

    fy = scipy.fft.fftfreq(scene.shape[0])[:, None]
    fx = scipy.fft.rfftfreq(scene.shape[1])[None]
    box = scale / QUADRATURE
    sigma = blur_sigma_px * scale
    otf = np.sinc(box * fy) * np.sinc(box * fx) * np.exp(-2 * np.pi**2 * sigma**2 * (fx**2 + fy**2))
    out = scipy.fft.irfft2(scipy.fft.rfft2(scene, workers=-1) * otf, s=scene.shape, workers=-1)
    return spline_filter(out, order=3, mode="mirror")


def render_burst(motion: str = "all", scale: int = 2, frames: int = 16, width: int = 640, height: int = 480,
                 blur_sigma_px: float = 0.3, full_well_e: float = 5000.0, read_noise_e: float = 3.0,
                 seed: int = 0, noise: bool = True, keep_clean: bool = False) -> HandheldBurst:
    """Render one hand-held burst (module docstring).

    Parameters
    ----------
    motion : str
        One of :data:`MOTIONS`.
    scale : int
        S: the truth is the reference frame's grid refined S times.
    frames : int
        F >= 2; frame 0 is the reference.
    width, height : int
        Frame size, LR px.
    blur_sigma_px : float
        The lens's Gaussian sigma, LR px (0: none).
    full_well_e, read_noise_e : float
        Electrons at white, and the read noise's sigma in electrons.
    seed : int
        The scene depends on (seed, S); the motion and the noise on (seed, motion, S, F).
    noise : bool
        False: the frames are the noise-free signal, quantised.
    keep_clean : bool
        Also return the noise-free frames (float32) in :attr:`HandheldBurst.clean`.

    Returns
    -------
    HandheldBurst
    """
    from scipy.ndimage import map_coordinates

    if frames < 2 or scale < 1 or width < 8 or height < 8 or blur_sigma_px < 0:
        raise ValueError("need frames >= 2, scale >= 1, frames of 8 x 8 px or more and a blur sigma >= 0")
    S, m = int(scale), MARGIN_PX
    rng = np.random.default_rng([seed, MOTIONS.index(motion), S, frames])
    motions, row_shift, gain_offset, moving = draw_motion(motion, frames, width, height, rng)
    smears = _smears(frames, S, rng) if motion == "shaken" else {}
    scene = collage(S * (height + 2 * m), S * (width + 2 * m), np.random.default_rng([seed, S]))

    object_offset, object_box, layer = np.zeros((frames, 2)), None, None
    if moving:  # a square of another collage, a fifth of the frame wide, moving 2-4 LR px a frame
        side = S * (width // 5)
        layer = collage(side, side, np.random.default_rng([seed, S, 1]))[::-1].copy()
        x0, y0 = S * (m + width // 3), S * (m + height // 3)
        object_box = (x0 - S * m, y0 - S * m, side)
        step = rng.uniform(2, 4) * S * np.array([np.cos(a := rng.uniform(0, 2 * np.pi)), np.sin(a)])
        wobble = rng.normal(0, S, (frames, 2))
        object_offset = np.round(np.arange(frames)[:, None] * step[None] + wobble - wobble[0])

    def scene_of(k):
        if layer is None:
            return scene
        out = scene.copy()
        dx, dy = (int(d) for d in object_offset[k])
        out[y0 + dy:y0 + dy + side, x0 + dx:x0 + dx + side] = layer
        return out

    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    offsets = (np.arange(QUADRATURE) + 0.5) / QUADRATURE - 0.5
    coeffs = None
    signals = np.empty((frames, height, width), np.float32)
    for k in range(frames):
        if k in smears:  # this frame's own scene, smeared
            from scipy.ndimage import convolve

            coeffs = _filtered(convolve(scene_of(k), smears[k], mode="mirror"), S, blur_sigma_px)
        elif coeffs is None or layer is not None or k - 1 in smears:
            coeffs = _filtered(scene_of(k), S, blur_sigma_px)
        total = np.zeros((height, width))
        for dv in offsets:
            rows = np.clip(np.round(v + dv).astype(int), 0, height - 1)  # the row being read
            for du in offsets:
                x, y = _apply(motions[k], u + du, v + dv)
                x, y = x + row_shift[k, rows, 0], y + row_shift[k, rows, 1]
                X, Y = S * (x + 0.5) - 0.5 + S * m, S * (y + 0.5) - 0.5 + S * m  # on the scene's grid
                total += map_coordinates(coeffs, [Y, X], order=3, prefilter=False, mode="mirror")
        g, o = gain_offset[k]
        signals[k] = np.clip(g * total / QUADRATURE**2 + o, 0, 1)
    white = 65535
    out = np.empty(signals.shape, np.uint16)
    if noise:  # frame by frame (a 12 MP burst's noise at once took 6 GB), the same draws as all at once
        shot = np.empty(signals.shape, np.int64 if full_well_e * 2 > 2**31 else np.int32)
        for k in range(frames):
            shot[k] = rng.poisson(signals[k].astype(np.float64) * full_well_e)
        for k in range(frames):
            level = (shot[k] + rng.normal(0, read_noise_e, signals.shape[1:])) / full_well_e * white
            out[k] = np.clip(np.round(level), 0, white)
        del shot
    else:
        for k in range(frames):
            out[k] = np.clip(np.round(signals[k].astype(np.float64) * white), 0, white)
    truth = scene_of(0)[S * m:S * (m + height), S * m:S * (m + width)].astype(np.float32)
    return HandheldBurst(out, truth, motions, row_shift, gain_offset, object_offset, object_box,
                         float(blur_sigma_px), S, motion, signals if keep_clean else None, tuple(sorted(smears)))
