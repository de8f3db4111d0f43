"""Scene-adaptive choice of h: model only the detail a scene has.

A scan of factor h costs h*h frames. Whether a larger h pays depends on the scene: h adds the
frequencies between h/2 and the previous band edge (cycles per sensor pixel), which count only if
the scene has energy there, the optics pass it, and it stands above the noise. From one frame
(for example the reference frame of a first, coarse look) this module predicts the
reconstruction error of every h <= h_max on a common grid (the h_max one) and recommends the
smallest h within ``tolerance_db`` of the best.

Model (frequencies f in cycles per sensor pixel; spectra per unit area of that plane):

* scene: a power law P(f) = s^2 abs(f)^-beta, fitted to the frame's own spectrum inside the
  sensor's band (abs(f) < 1/2), where the frame is the scene through the optics O and the pixel
  aperture K (so P = (abs(frame)^2 - noise) / abs(O K)^2 there, in log-spaced rings);
* optics: the diffraction-limited OTF O(f), zero beyond p / (lambda F) (the "H" of the paper's
  section 2.2); pixel aperture K(f) = sinc(a fx) sinc(a fy), a = sqrt(fill factor);
* reconstruction at h from h*h frames: the Wiener (MMSE) estimate inside its band
  abs(fx), abs(fy) < h/2, nothing outside. The noise density depends on what the scan may spend:
  with ``budget="total"`` (default) the scan's total exposure is that of the first frame, split
  over h*h frames, so each frame's shot noise grows by h and the density stays sigma^2: a larger
  h buys resolution only. With ``budget="frame"`` every frame gets the first frame's exposure,
  the density falls as sigma^2 / h^2, and more frames always help (they also average noise);
* target: what a pitch-p/h_max sensor sees, W(f) = O(f) sinc(a fx / h_max) sinc(a fy / h_max).

The predicted mean squared error of h is the integral over the h_max band of the Wiener
estimate's error inside h's band, P abs(W)^2 ((b g - 1)^2 + b^2 g (1 - g)) with the Wiener gain
g = P abs(O K)^2 / (P abs(O K)^2 + n) (n the noise density) and b the bicubic resampling's gain onto
the h_max grid (for h = 1, which is not deblurred, P abs(b O K - W)^2 + b^2 n), and outside it
P abs(W)^2 + P abs(O K)^2: the detail h cannot represent, plus what of it the pixel passes and the
lattice aliases into the band. ``benchmarks/bench_adaptive_h.py`` checks the choice against reconstructions of
simulated stacks at every h.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import Tensor

from hbis_torch.errors import HbisInputError
from hbis_torch.reconstruct.classical import diffraction_otf, optics_cutoff
from hbis_torch.sensor.noise import noise_sigma

__all__ = ["BUDGETS", "HChoice", "predict_psnr", "recommend_h", "fit_scene_spectrum"]


@dataclass
class HChoice:
    """What :func:`recommend_h` found.

    Attributes
    ----------
    h : int
        Recommended resolution improvement factor (h*h frames).
    predicted_psnr_db : dict[int, float]
        Predicted PSNR (dB, data range 1) of the reconstruction at each h, on the h_max grid.
    h_max : int
    noise : float
        Noise standard deviation used (frame intensity units, [0, 1]).
    s2, beta : float
        The fitted scene spectrum s^2 abs(f)^-beta.
    """

    h: int
    predicted_psnr_db: dict[int, float] = field(default_factory=dict)
    h_max: int = 1
    noise: float = 0.0
    s2: float = 0.0
    beta: float = 2.0

    @property
    def frames(self) -> int:
        return self.h * self.h

    def report(self) -> str:
        best = max(self.predicted_psnr_db.values())
        lines = [f"recommended h = {self.h} ({self.frames} frames); scene spectrum ~ |f|^-{self.beta:.2f}, "
                 f"noise {self.noise:.4f}"]
        for h, p in self.predicted_psnr_db.items():
            mark = " <" if h == self.h else ""
            lines.append(f"  h={h}: {h * h:3d} frames, predicted {p:6.2f} dB ({p - best:+.2f}){mark}")
        return "\n".join(lines)


def _check_frame(frame) -> Tensor:
    if isinstance(frame, np.ndarray):
        frame = torch.from_numpy(np.ascontiguousarray(frame))
    frame = torch.as_tensor(frame)
    if frame.ndim == 3:
        frame = frame[0]
    if frame.ndim != 2 or min(frame.shape) < 16:
        raise HbisInputError(f"a frame of at least 16 x 16 px is needed, got shape {tuple(frame.shape)}")
    if frame.dtype == torch.bool or frame.is_complex():
        raise HbisInputError(f"the frame must hold real intensities, got {frame.dtype}")
    frame = frame.to(torch.float64)
    if not torch.isfinite(frame).all():
        raise HbisInputError("the frame contains non-finite values (NaN or inf)")
    return frame


def _apertures(fx: Tensor, fy: Tensor, cutoff: float, aperture: float):
    """Optics OTF and the sensor pixel's transfer at (fx, fy) cycles per sensor pixel."""
    optics = diffraction_otf(torch.sqrt(fx * fx + fy * fy) / cutoff)
    pixel = torch.sinc(aperture * fx) * torch.sinc(aperture * fy)
    return optics, pixel


def fit_scene_spectrum(image: Tensor, spacing: float, noise_density: float, cutoff: float,
                       aperture: float = 1.0) -> tuple[float, float]:
    """Fit s^2 abs(f)^-beta (f in cycles per sensor pixel) to an image of the scene.

    Parameters
    ----------
    image : Tensor, shape (rows, cols)
        Samples of the scene through the optics and the sensor pixel, ``spacing`` sensor pixels
        apart: one frame (spacing 1) or a pre-scan's lattice image (spacing 1/h0).
    noise_density : float
        The noise's power per unit area of the frequency plane (sigma^2 spacing^2).
    cutoff, aperture : float
        Optical cutoff (cycles per pixel) and pixel aperture side over the pitch.

    Returns
    -------
    s2, beta : float
        beta is kept within [1, 4]; an image with no signal above the noise gets a faint 1/f^2.
    """
    rows, cols = image.shape
    window = torch.outer(torch.hann_window(rows, periodic=False, dtype=image.dtype),
                         torch.hann_window(cols, periodic=False, dtype=image.dtype))
    x = (image - image.mean()) * window
    power = torch.fft.rfft2(x).abs() ** 2 / float((window ** 2).sum()) * spacing ** 2
    fy = torch.fft.fftfreq(rows, dtype=image.dtype)[:, None] / spacing
    fx = torch.fft.rfftfreq(cols, dtype=image.dtype)[None, :] / spacing
    optics, pixel = _apertures(fx, fy, cutoff, aperture)
    seen = ((optics * pixel) ** 2).expand(power.shape)
    rad = torch.sqrt(fx * fx + fy * fy).expand(power.shape)
    # Up to 0.45 of the sampling rate: above it the lattice's own aliasing dominates.
    edges = torch.logspace(math.log10(3.0 / (max(rows, cols) * spacing)), math.log10(0.45 / spacing), 13,
                           dtype=image.dtype)
    xs, ys = [], []
    for lo, hi in zip(edges[:-1], edges[1:]):
        ring = (rad >= lo) & (rad < hi) & (seen > 1e-3)
        if int(ring.sum()) < 4:
            continue
        level = float(power[ring].mean())
        if level > 2 * noise_density:
            xs.append(math.log(float(rad[ring].mean())))
            ys.append(math.log((level - noise_density) / float(seen[ring].mean())))
    if len(xs) < 3:
        return 1e-2 * noise_density, 2.0
    x_, y_ = torch.tensor(xs, dtype=torch.float64), torch.tensor(ys, dtype=torch.float64)
    slope = float(((x_ - x_.mean()) * (y_ - y_.mean())).sum() / ((x_ - x_.mean()) ** 2).sum())
    beta = min(max(-slope, 1.0), 4.0)
    return math.exp(float((y_ + beta * x_).mean())), beta


BUDGETS = ("total", "frame")


def cubic_transfer(nu: Tensor, a: float = -0.75) -> Tensor:
    """Transfer function of cubic-convolution interpolation (Keys' kernel with parameter a, as
    torch's bicubic resampling uses) at nu cycles per sample: the kernel's Fourier transform,
    by quadrature over its support [-2, 2]."""
    t = torch.linspace(0.0, 2.0, 401, dtype=torch.float64)
    d = t.abs()
    kernel = torch.where(d <= 1, (a + 2) * d ** 3 - (a + 3) * d ** 2 + 1,
                         torch.where(d < 2, a * d ** 3 - 5 * a * d ** 2 + 8 * a * d - 4 * a, torch.zeros_like(d)))
    weights = torch.full_like(t, t[1] - t[0])
    weights[0] = weights[-1] = 0.5 * float(t[1] - t[0])
    phase = torch.cos(2 * math.pi * nu.reshape(-1, 1) * t[None, :])
    return (2 * (phase * kernel * weights).sum(-1)).reshape(nu.shape)  # the kernel is even


def predict_psnr(s2: float, beta: float, noise: float, cutoff: float, h_max: int,
                 aperture: float = 1.0, budget: str = "total", grid: int = 192) -> dict[int, float]:
    """Predicted PSNR (dB) of the reconstruction at every h = 1..h_max, on the h_max grid.

    Parameters
    ----------
    s2, beta : float
        Scene spectrum s^2 abs(f)^-beta, f in cycles per sensor pixel.
    noise : float
        Noise standard deviation of one sample.
    cutoff : float
        Optical cutoff, cycles per sensor pixel.
    h_max : int
    aperture : float
        Pixel aperture side over the pitch, sqrt(fill factor).
    budget : {"total", "frame"}
        The scan's total exposure is the first frame's ("total") or every frame has it ("frame").
    grid : int
        Integration points per axis over the h_max band.
    """
    step = h_max / grid
    f = (torch.arange(grid, dtype=torch.float64) + 0.5) * step - h_max / 2
    fy, fx = torch.meshgrid(f, f, indexing="ij")
    optics, pixel = _apertures(fx, fy, cutoff, aperture)
    r = torch.sqrt(fx * fx + fy * fy).clamp_min(0.5 * step)
    scene = s2 * r ** (-beta)
    target = scene * (optics * torch.sinc(aperture * fx / h_max) * torch.sinc(aperture * fy / h_max)) ** 2
    seen = scene * (optics * pixel) ** 2
    wanted = optics * torch.sinc(aperture * fx / h_max) * torch.sinc(aperture * fy / h_max)
    out = {}
    for h in range(1, h_max + 1):
        density = noise ** 2 if budget == "total" else noise ** 2 / (h * h)
        inside = (fx.abs() < h / 2) & (fy.abs() < h / 2)
        # Compared on the h_max grid: the h grid's image is resampled (bicubic), which passes
        # its band with the gain b, below 1 near the band's edge.
        b1 = cubic_transfer(f / h)  # separable: one axis at a time
        b = torch.ones_like(fx) if h == h_max else b1[:, None] * b1[None, :]
        if h == 1:  # one frame, nothing to deblur: its blur and its noise stay
            kept = scene * (b * optics * pixel - wanted) ** 2 + b * b * density
        else:  # the Wiener estimate (gain g), resampled
            g = seen / (seen + density)
            kept = target * ((b * g - 1) ** 2 + b * b * g * (1 - g))
        # Outside the band: the detail is lost, and what the pixel passes of it aliases in.
        error = torch.where(inside, kept, target + seen)
        mse = float(error.sum()) * step * step
        out[h] = -10 * math.log10(max(mse, 1e-20))
    return out


def recommend_h(frames, system, positions=None, h_max: int | None = None, tolerance_db: float = 0.07,
                noise: float | None = None, fill_factor: float = 1.0, budget: str = "total") -> HChoice:
    """Recommend the smallest h whose predicted reconstruction is within ``tolerance_db`` of
    the best h <= h_max, from a first look at the scene.

    Parameters
    ----------
    frames : Tensor or array, shape (H, W) or (F, H, W)
        Intensities in [0, 1]: one frame, or the frames of a quick pre-scan (for example the
        2 x 2 scan of ``plan_scan(system, 2)``) with their ``positions``.
    system : hbis_torch.config.FoveaSystem
        Its optics set the cutoff; ``h_max`` defaults to the design's (floor of H, section 2.2).
    positions : Tensor or array, shape (F, H, W, 2), optional
        Where each pre-scan sample lies in the reference frame (``optical_sample_positions``).
        With them the spectrum is measured above the sensor's Nyquist frequency and the noise
        on the pre-scan's lattice; without them, from the first frame alone (its noise estimate,
        Immerkaer's, counts aliased detail as noise and so errs towards a smaller h).
    h_max : int, optional
    tolerance_db : float
        How much predicted PSNR may be given up for fewer frames. The model leaves out part of
        what larger h gain in practice (its gains run several times smaller than measured, see
        benchmarks/bench_adaptive_h.py), hence the small default. On that benchmark's 14 cases,
        0.1 dB left the aliased bars at 40 dB 0.60 dB below the best h; 0.07 dB (and 0.05) keeps
        every case within 0.5 dB for 117 frames in all instead of 107.
    noise : float, optional
        Noise standard deviation of a full-exposure frame, if known (a calibrated sensor).
    fill_factor : float
        Light-sensitive fraction of the pixel area, (0, 1].
    budget : {"total", "frame"}
        How exposure scales with the number of frames (see the module's notes). For a pre-scan
        taken at the same total exposure as the first look, its noise per frame is h0 times
        larger; it is scaled back.

    Returns
    -------
    HChoice
    """
    frames_t = torch.as_tensor(np.asarray(frames) if isinstance(frames, np.ndarray) else frames)
    if frames_t.ndim == 2:
        frames_t = frames_t[None]
    first = _check_frame(frames_t[0])
    if h_max is None:
        from hbis_torch.design import design

        h_max = design(system).h_max
    if isinstance(h_max, bool) or not isinstance(h_max, (int, np.integer)) or not 1 <= h_max <= 16:
        raise HbisInputError(f"h_max must be an integer from 1 to 16, got {h_max!r}")
    if not (math.isfinite(tolerance_db) and tolerance_db >= 0):
        raise HbisInputError(f"tolerance_db must be a number >= 0, got {tolerance_db!r}")
    if not 0 < fill_factor <= 1:
        raise HbisInputError(f"fill_factor must lie in (0, 1], got {fill_factor!r}")
    if budget not in BUDGETS:
        raise HbisInputError(f"budget must be one of {BUDGETS}, got {budget!r}")
    if noise is not None and not (math.isfinite(noise) and noise >= 0):
        raise HbisInputError(f"noise must be a number >= 0, got {noise!r}")
    cutoff = optics_cutoff(system)
    aperture = math.sqrt(fill_factor)
    if positions is not None:
        from hbis_torch.checks import as_float64_tensor
        from hbis_torch.reconstruct.classical import lattice_image, lattice_noise

        stack = as_float64_tensor(frames_t, "frames")
        positions = as_float64_tensor(positions, "positions")
        F, H, W = stack.shape
        if tuple(positions.shape) != (F, H, W, 2):
            raise HbisInputError(f"positions must have shape {(F, H, W, 2)}, got {tuple(positions.shape)}")
        h0 = max(1, int(round(math.sqrt(F))))
        image, den, _, typical = lattice_image(stack, positions, h0, 0.3)
        sample_noise = lattice_noise(image, 0.3, den > 0.5 * typical)
        if noise is None:  # back to a full-exposure frame's noise
            noise = sample_noise / h0 if budget == "total" else sample_noise
        s2, beta = fit_scene_spectrum(image, 1.0 / h0, sample_noise ** 2 / h0 ** 2, cutoff, aperture)
    else:
        if noise is None:
            noise = float(noise_sigma(first[None])[0])
        s2, beta = fit_scene_spectrum(first, 1.0, max(noise, 1e-4) ** 2, cutoff, aperture)
    noise = max(noise, 1e-4)
    psnr = predict_psnr(s2, beta, noise, cutoff, int(h_max), aperture, budget)
    best = max(psnr.values())
    h = min(k for k, v in psnr.items() if v >= best - tolerance_db)
    return HChoice(h=h, predicted_psnr_db=psnr, h_max=int(h_max), noise=noise, s2=s2, beta=beta)
