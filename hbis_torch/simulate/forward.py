"""Forward model of the fovea: noise-free frames of a scan and their ground truth.

Physics. Frame k sees the scene S through the landing map L_k of its phases: the geometric image
on the sensor is ``S(L_k(x))`` at sensor position x (pixels). The lens blurs it with its PSF and
each pixel integrates it over its aperture, so the pixel (u, v) reads

    I_k(u, v) = [(S o L_k) * K](u, v),      K = PSF * aperture (sensor plane, shift invariant).

Writing ``S o L_k = (S o L_ref) o w_k`` with ``w_k = L_ref^-1 o L_k`` (frame-k pixels to
reference-frame pixels, a near-translation by a fraction of a pixel whose Jacobian differs from
the identity by about 1e-4 over a scan), and since a convolution commutes with a translation,

    I_k(u, v) = [T * K](q_k(u, v)),         T = S o L_ref,  q_k = w_k (the sample positions),

to first order in that 1e-4. So the renderer

1. samples the scene once on a fine grid of the reference frame's sensor plane (spacing
   ``1 / (h r)`` pixels, r = max(2, ceil(oversample / h)), aligned so that every r-th point is a
   ground-truth pixel centre), through the exact landing map at the reference phases;
2. blurs it in the frequency domain (DCT-II: the grid's mirror-image extension, so the PSF's
   long tails, about 1 % of its energy beyond 4 pixels, see a continuation of the scene rather
   than the far side of the grid) with the exact transfer of the lens PSF (Airy or defocused)
   and the pixel aperture: once with the sensor's square aperture (side sqrt(fill) p) for the
   frames, once with the aperture of the ideal pitch-p/h sensor for the ground truth;
3. reads the ground truth at the HR pixel centres (every r-th grid point, no interpolation) and
   each frame pixel at its sample position q_k(u, v) by cubic B-spline interpolation of the
   blurred grid (the spline's prefilter is folded into the Fourier-domain blur; its error is
   fourth order, about 3e-4 of a component with 9 grid points per period; torch's bicubic
   grid_sample, a = -0.75, is only first-order accurate and was ten times worse).

The grid is band-limited by construction: :meth:`Scene.sample` averages the scene over each grid
cell, the same scene for the frames and the truth. Large regions are done in tiles with margins.
tests/test_simulate_forward.py checks the whole model against brute-force integration.

Float32 is used for the scene grid, the FFTs and the interpolation (geometry is float64); the
``dtype`` argument runs it in float64, and the tests bound the difference.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from hbis_torch.checks import check_h, check_phases, check_roi
from hbis_torch.config import FoveaSystem
from hbis_torch.errors import HbisInputError
from hbis_torch.optics import landing_at, landing_on_grid, sample_positions
from hbis_torch.simulate.psf import blur_transfer, dct_frequencies, defocus_waves
from hbis_torch.simulate.scenes import Scene
from hbis_torch.simulate.sensor import SensorModel


@dataclass
class RenderedScan:
    """Noise-free result of :func:`render_scan`.

    Attributes
    ----------
    irradiance : Tensor, shape (F, H, W), float32
        Frames before noise, in [0, 1] (1 fills the well).
    truth : Tensor, shape (h*H, h*W), float32
        Ground truth in [0, 1] on the output grid (docs/data.md).
    positions : Tensor, shape (F, H, W, 2), float64, or None
        Roi-local sample positions q_k(u, v) - (u0, v0) of the rendered phases.
    scene : Scene
        The scene as placed on the object plane.
    """

    irradiance: Tensor
    truth: Tensor
    positions: Tensor | None
    scene: Scene


def grid_factor(h: int, oversample: int = 8) -> int:
    """r: fine-grid points per ground-truth pixel, max(2, ceil(oversample / h))."""
    return max(2, math.ceil(oversample / h))


def place_scene(scene: Scene, system: FoveaSystem, reference_phases, roi) -> Scene:
    """The scene itself if it has a centre, else centred on the view of the roi's centre pixel."""
    if scene.center_mm is not None:
        return scene
    u0, v0, width, height = roi
    centre = landing_at(
        system,
        torch.tensor(u0 + (width - 1) / 2, dtype=torch.float64),
        torch.tensor(v0 + (height - 1) / 2, dtype=torch.float64),
        float(reference_phases[0]),
        float(reference_phases[1]),
    )
    return scene.placed_at(centre.tolist())


def bspline_prefilter(shape: tuple[int, int], dtype=torch.float32) -> Tensor:
    """1 / (b(wy) b(wx)) on DCT-II frequencies, b(w) = (2 + cos w) / 3: turns samples into cubic
    B-spline coefficients (with mirror boundaries, as the DCT blur already has). Returns the
    separable factors, (Ny, 1) and (1, Nx)."""
    wy = 2 * math.pi * torch.from_numpy(dct_frequencies(shape[0], 1.0))
    wx = 2 * math.pi * torch.from_numpy(dct_frequencies(shape[1], 1.0))
    return (3.0 / (2 + torch.cos(wy))).to(dtype)[:, None], (3.0 / (2 + torch.cos(wx))).to(dtype)[None, :]


def _dct2(x: Tensor) -> Tensor:
    import scipy.fft

    return torch.from_numpy(scipy.fft.dctn(x.numpy(), type=2, norm="ortho", workers=1))


def _idct2(x: Tensor) -> Tensor:
    import scipy.fft

    return torch.from_numpy(scipy.fft.idctn(x.numpy(), type=2, norm="ortho", workers=1))


def bspline_sample(coeffs: Tensor, ix: Tensor, iy: Tensor) -> Tensor:
    """Evaluate the cubic B-spline with coefficients ``coeffs`` (Ny, Nx) at fractional grid
    indices (ix, iy) (any equal shapes, float64; at least 1 from the first and 2 from the last
    index). Returns values of that shape in ``coeffs.dtype``.

    Uses the linear-interpolation form of the cubic B-spline (Sigg and Hadwiger, GPU Gems 2,
    ch. 20): per axis the four weights pair up into two linear fetches, so one bilinear
    ``grid_sample`` of four points per query does the 16-tap sum.
    """
    shape = ix.shape
    ny, nx = coeffs.shape

    def split(i):
        base = torch.floor(i)
        t = (i - base).to(coeffs.dtype)  # the weights need no more than the grid's precision
        base = base.to(coeffs.dtype)
        s = 1 - t
        w0, w1, w2, w3 = s * s * s / 6, (3 * t * t * t - 6 * t * t + 4) / 6, (-3 * t * t * t + 3 * t * t + 3 * t + 1) / 6, t * t * t / 6
        g0, g1 = w0 + w1, w2 + w3
        return (base - 1 + w1 / g0, base + 1 + w3 / g1), (g0, g1)

    (x0, x1), (gx0, gx1) = split(ix.reshape(-1))
    (y0, y1), (gy0, gy1) = split(iy.reshape(-1))
    xs = torch.stack((x0, x1, x0, x1))
    ys = torch.stack((y0, y0, y1, y1))
    grid = torch.stack((2 * xs / (nx - 1) - 1, 2 * ys / (ny - 1) - 1), -1)[None].to(coeffs.dtype)
    fetched = F.grid_sample(coeffs[None, None], grid, mode="bilinear", align_corners=True)[0, 0]
    weights = torch.stack((gx0 * gy0, gx1 * gy0, gx0 * gy1, gx1 * gy1)).to(coeffs.dtype)
    return (fetched * weights).sum(0).reshape(shape)


def _fast_len(n: int) -> int:
    from scipy.fft import next_fast_len

    return int(next_fast_len(int(n), real=True))



def _axis(lo: float, hi: float, first_centre: float, step: float):
    """Grid indices m (relative to the first HR centre) covering [lo, hi], FFT-friendly count."""
    m_lo = math.floor((lo - first_centre) / step)
    m_hi = math.ceil((hi - first_centre) / step)
    count = _fast_len(m_hi - m_lo + 1)
    coords = first_centre + (m_lo + np.arange(count)) * step
    return coords, -m_lo  # grid coordinates and the index of the first HR centre


def render_scan(
    scene: Scene,
    system: FoveaSystem,
    phases_deg,
    reference_index: int,
    h: int,
    roi=None,
    sensor: SensorModel = SensorModel(),
    oversample: int = 8,
    margin_px: float = 4.0,
    max_grid: int = 1536,
    exact_positions: bool = False,
    return_positions: bool = True,
    positions: Tensor | None = None,
    dtype=torch.float32,
) -> RenderedScan:
    """Noise-free frames of a scan, and the ground truth at the reference phases.

    Parameters
    ----------
    scene : Scene
        The object-plane scene (centred on the roi's view when its ``center_mm`` is None).
    system : FoveaSystem
    phases_deg : array-like, shape (F, 2)
        Phases at which the frames are taken (degrees), in scan order.
    reference_index : int
        Frame whose phases define the output grid (the scan's initial phases).
    h : int
        Resolution improvement factor: the truth has shape (h*H, h*W).
    roi : (u0, v0, width, height) or None
        Pixels of each frame (None: the whole sensor).
    sensor : SensorModel
        Fill factor and defocus are used here (noise is applied by :func:`expose`).
    oversample : int
        Fine-grid points per sensor pixel, at least (see :func:`grid_factor`).
    margin_px : float
        Extra grid around what is sampled, pixels (absorbs the blur and the FFT's wrap-around).
    max_grid : int
        Largest fine grid per tile and axis; larger regions are split into tiles.
    exact_positions : bool
        Trace every pixel for the sample positions instead of spline interpolation (< 1e-6 px).
    return_positions : bool
        Keep the (F, H, W, 2) sample positions in the result.
    positions : Tensor, shape (F, H, W, 2), or None
        Sample positions already computed for these phases and roi (roi-local, as
        :func:`sample_positions` returns them); None computes them.
    dtype : torch.dtype
        float32 (default) or float64 for the scene grid, FFTs and interpolation.

    Returns
    -------
    RenderedScan
    """
    phases = check_phases(phases_deg)
    h = check_h(h)
    n_frames = phases.shape[0]
    if not 0 <= int(reference_index) < n_frames:
        raise HbisInputError(f"reference index {reference_index} is not a frame index (0..{n_frames - 1})")
    roi = check_roi(system.camera, roi)
    u0, v0, width, height = roi
    reference = phases[int(reference_index)]
    scene = place_scene(scene, system, reference, roi)

    r = grid_factor(h, oversample)
    step = 1.0 / (h * r)  # grid spacing, sensor pixels
    cam = system.camera
    aperture = math.sqrt(sensor.fill_factor)
    w20 = defocus_waves(sensor.defocus_um, cam.f_number, cam.wavelength_nm)
    pad = margin_px + 2.0  # frames sample within about a pixel of their own position
    tile = max(16, int(max_grid * step - 2 * pad))

    irradiance = torch.empty(n_frames, height, width, dtype=torch.float32)
    truth = torch.empty(h * height, h * width, dtype=torch.float32)
    given = positions
    if given is not None and tuple(given.shape) != (n_frames, height, width, 2):
        raise HbisInputError(f"positions must have shape {(n_frames, height, width, 2)}, got {tuple(given.shape)}")
    positions = torch.empty(n_frames, height, width, 2, dtype=torch.float64) if return_positions else None
    from hbis_torch.progress import progress

    bar = progress(total=-(-height // tile) * -(-width // tile), desc="simulate", unit="tile")
    for tv in range(v0, v0 + height, tile):
        for tu in range(u0, u0 + width, tile):
            tw, th = min(tile, u0 + width - tu), min(tile, v0 + height - tv)
            if given is None:
                q = sample_positions(system, phases, reference_index, (tu, tv, tw, th),
                                     exact=exact_positions, local=False)
            else:
                q = given[:, tv - v0:tv - v0 + th, tu - u0:tu - u0 + tw].double() + torch.tensor(
                    [u0, v0], dtype=torch.float64)
            gu, iu = _axis(min(float(q[..., 0].min()), tu - 0.5) - margin_px,
                           max(float(q[..., 0].max()), tu + tw - 0.5) + margin_px,
                           tu - 0.5 + 0.5 / h, step)
            gv, iv = _axis(min(float(q[..., 1].min()), tv - 0.5) - margin_px,
                           max(float(q[..., 1].max()), tv + th - 0.5) + margin_px,
                           tv - 0.5 + 0.5 / h, step)
            landing = landing_on_grid(system, gu, gv, float(reference[0]), float(reference[1]),
                                      origin_mm=scene.center_mm, dtype=dtype)
            grid = scene.sample(landing, step * system.object_pixel_mm, relative=True).to(dtype)
            spectrum = _dct2(grid)
            transfer = dict(shape=grid.shape, spacing_px=step, pitch_um=cam.pixel_pitch_um,
                            f_number=cam.f_number, wavelength_nm=cam.wavelength_nm,
                            w20_waves=w20, dtype=dtype)
            by, bx = bspline_prefilter(grid.shape, dtype)
            low_transfer = blur_transfer(aperture_px=aperture, **transfer) * by * bx
            coeffs = _idct2(spectrum * low_transfer)
            high = _idct2(spectrum * blur_transfer(aperture_px=aperture / h, **transfer))

            ys, xs = (tv - v0) * h, (tu - u0) * h
            truth[ys:ys + h * th, xs:xs + h * tw] = high[iv:iv + r * h * th:r, iu:iu + r * h * tw:r].float()

            values = bspline_sample(coeffs, (q[..., 0] - gu[0]) / step, (q[..., 1] - gv[0]) / step)
            irradiance[:, tv - v0:tv - v0 + th, tu - u0:tu - u0 + tw] = values.float()
            if positions is not None:
                positions[:, tv - v0:tv - v0 + th, tu - u0:tu - u0 + tw] = q
            bar.update()
    bar.close()
    if positions is not None:
        positions -= torch.tensor([u0, v0], dtype=torch.float64)
    return RenderedScan(irradiance.clamp_(0.0, 1.0), truth.clamp_(0.0, 1.0), positions, scene)
