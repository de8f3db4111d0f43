"""Sub-pixel registration of a stack of shifted frames against its reference frame.

The Risley scan moves the image by fractions of a pixel between frames. The tracer predicts that
motion (``prediction``); the data then corrects it, because motors miss their targets and the
optics are never exactly the model. The correction is a forward-compositional Lucas-Kanade fit
(Baker & Matthews 2004) of the reference, sampled through each frame's homography, to the frame,
with robust (Huber) weights so that a small occluder does not drag the estimate, and cubic
B-spline resampling (value and exact gradient) so that the warp itself does not bias the
sub-pixel answer (torch's bicubic kernel would, by about 0.04 px). The optics' prediction comes
in as homographies fitted with Kornia's DLT (:func:`homographies_from_positions`).

Frames are (F, H, W); pixel (u, v) is the centre of column u and row v. A homography ``H_k``
maps frame-k pixel coordinates to reference pixel coordinates: ``[u_r, v_r, 1] ~ H_k [u, v, 1]``.

Motion models, simplest first: ``translation`` (2 parameters), ``similarity`` (4: shift, rotation,
scale) and ``homography`` (8). With ``model="auto"`` the simplest model that explains the residual
is kept: a richer model is tried only when a score test on the simpler fit's residual says it
would pay (BIC over the effective number of independent residuals of the blurred frames) and
its extra motion is measurable (it moves some pixel by more than ``motion_tolerance_px``); it is
kept only if the full fit confirms both.

Every frame gets a confidence in [0, 1] and an ``ok`` flag; ``messages`` says why a frame was
flagged: too little texture to register, pixels that do not match (occlusion, a changed scene),
no convergence, or (given a prediction) a frame that sits where another frame of the plan should
be (frames out of order).
"""

from __future__ import annotations

import copy
import dataclasses
import functools
import math
import operator
from dataclasses import dataclass, field

import kornia
import torch
from torch import Tensor

from .errors import HbisInputError

MODELS = ("translation", "similarity", "homography")
N_PARAMS = {"translation": 2, "similarity": 4, "homography": 8}

# Thresholds behind the flags (px unless said otherwise).
PRECISION_SCALE_PX = 0.05  # confidence exp(-(precision / this)^2); "too little texture" above it
OCCLUSION_FRACTION = 0.10  # share of compared pixels in non-matching tiles that is reported
COARSE_POINTS = 256  # points of a fit's first Gauss-Newton step (see _LucasKanade)
MIN_CORRELATION = 0.5  # frame and reference correlate less than this at the compared points: another scene


@dataclass
class Registration:
    """Result of :func:`register_stack`.

    Attributes
    ----------
    homographies : Tensor, shape (F, 3, 3), float64
        Frame-k pixel coordinates -> reference pixel coordinates (identity for the reference).
    model : str
        The motion model used (``translation``, ``similarity`` or ``homography``).
    confidence : Tensor, shape (F,), float64 in [0, 1]
        How far to trust each frame's motion (1 for the reference).
    ok : Tensor, shape (F,), bool
        False for frames whose motion should not be used.
    messages : list of str
        One line per problem found, naming the frame.
    precision_px : Tensor, shape (F,), float64
        Expected standard error of the motion (px, RMS over the frame) from the fit's curvature.
    residual : Tensor, shape (F,), float64
        Robust scale of the aligned difference, in units of the frame's standard deviation.
    out_of_order : Tensor, shape (F,), bool
        Frames found nearer another frame's predicted position than their own (needs a
        prediction; all False without one).
    """

    homographies: Tensor
    model: str
    confidence: Tensor
    ok: Tensor
    messages: list[str] = field(default_factory=list)
    precision_px: Tensor | None = None
    residual: Tensor | None = None
    out_of_order: Tensor | None = None

    def displacement(self, u: float, v: float) -> Tensor:
        """(F, 2): where frame pixel (u, v) lands in the reference, minus (u, v), in px."""
        point = torch.tensor([[u, v]], dtype=torch.float64)
        return apply_homography(self.homographies, point)[:, 0] - point


def apply_homography(homographies: Tensor, points: Tensor) -> Tensor:
    """Map points through homographies.

    Parameters
    ----------
    homographies : Tensor, shape (F, 3, 3)
    points : Tensor, shape (F, N, 2) or (N, 2)
        (u, v) pixel coordinates.

    Returns
    -------
    Tensor, shape (F, N, 2), in the homographies' dtype.
    """
    points = points.to(homographies.dtype)
    ones = torch.ones(points.shape[:-1] + (1,), dtype=points.dtype)
    mapped = torch.cat((points, ones), -1) @ homographies.mT  # (F, N, 3)
    return mapped[..., :2] / mapped[..., 2:]


def homographies_from_positions(positions, step: int = 4) -> Tensor:
    """Least-squares homographies that best map each frame's pixel grid onto given positions.

    Parameters
    ----------
    positions : Tensor, shape (F, H, W, 2)
        Where pixel (u, v) of frame k lands, in reference pixel coordinates (for example
        :func:`hbis_torch.sr.classical.optical_sample_positions`).
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
    F, H, W, _ = positions.shape
    rows = torch.unique(torch.cat((torch.arange(0, H, step), torch.tensor([H - 1]))))
    cols = torch.unique(torch.cat((torch.arange(0, W, step), torch.tensor([W - 1]))))
    vv, uu = torch.meshgrid(rows.double(), cols.double(), indexing="ij")
    src = torch.stack((uu, vv), -1).reshape(1, -1, 2).expand(F, -1, -1)
    dst = positions[:, rows][:, :, cols].reshape(F, -1, 2)
    # Condition the DLT: centre and scale both point sets the same way.
    norm = _normaliser(H, W, torch.float64).expand(F, 3, 3)
    h_n = kornia.geometry.homography.find_homography_dlt(
        apply_homography(norm, src), apply_homography(norm, dst)
    )
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
    elif model == "homography":
        m[:, 0, 0] += p[:, 2]
        m[:, 0, 1] += p[:, 3]
        m[:, 1, 0] += p[:, 4]
        m[:, 1, 1] += p[:, 5]
        m[:, 2, 0], m[:, 2, 1] = p[:, 6], p[:, 7]
    return m


def _embedding(model: str) -> Tensor:
    """(8, k) matrix E with warp_jacobian(model) = warp_jacobian("homography") @ E."""
    e = torch.zeros(8, N_PARAMS[model], dtype=torch.float64)
    e[0, 0] = e[1, 1] = 1.0
    if model == "similarity":
        e[2, 2] = e[5, 2] = 1.0  # scale: (x, y)
        e[3, 3], e[4, 3] = -1.0, 1.0  # rotation: (-y, x)
    elif model == "homography":
        e = torch.eye(8, dtype=torch.float64)
    return e


_EMBEDDING = {m: _embedding(m) for m in MODELS}


def _warp_jacobian(x: Tensor, y: Tensor, model: str) -> tuple[list[Tensor], list[Tensor]]:
    """d(x', y')/dp at the identity, as two lists of k tensors shaped like x (normalised units)."""
    one, zero = torch.ones_like(x), torch.zeros_like(x)
    jx, jy = [one, zero], [zero, one]
    if model == "similarity":
        jx += [x, -y]
        jy += [y, x]
    elif model == "homography":
        jx += [x, y, zero, zero, -x * x, -x * y]
        jy += [zero, zero, x, y, -x * y, -y * y]
    return jx, jy


def _check_frames(frames) -> Tensor:
    if not isinstance(frames, Tensor):
        try:
            frames = torch.as_tensor(frames)
        except (TypeError, ValueError, RuntimeError) as exc:
            raise HbisInputError(f"frames must be a (F, H, W) array of numbers: {exc}") from None
    if frames.ndim != 3:
        raise HbisInputError(f"frames must have shape (F, H, W), got {tuple(frames.shape)}")
    F, H, W = frames.shape
    if F < 1 or H < 16 or W < 16:
        raise HbisInputError(f"frames must be at least one 16 x 16 frame, got shape {(F, H, W)}")
    if frames.dtype == torch.bool or frames.is_complex():
        raise HbisInputError(f"frames must be real numbers, got dtype {frames.dtype}")
    # A finite sum means finite values (one reduction); only an inf sum needs the full check.
    if frames.is_floating_point() and not (torch.isfinite(frames.sum()) or torch.isfinite(frames).all()):
        raise HbisInputError("frames contain non-finite values (NaN or inf)")
    return frames


def _check_prediction(prediction, F: int) -> Tensor | None:
    if prediction is None:
        return None
    prediction = torch.as_tensor(prediction, dtype=torch.float64)
    if prediction.shape != (F, 3, 3):
        raise HbisInputError(
            f"prediction must have shape ({F}, 3, 3) (one homography per frame), "
            f"got {tuple(prediction.shape)}"
        )
    if not torch.isfinite(prediction).all():
        raise HbisInputError("prediction contains non-finite values")
    if bool((prediction[:, 2, 2].abs() < 1e-12).any()) or bool(
        (torch.linalg.det(prediction).abs() < 1e-12).any()
    ):
        raise HbisInputError("prediction contains a singular homography")
    return prediction / prediction[:, 2:3, 2:3]


# --------------------------------------------------------------------------- resampling

def _fast_fft_size(n: int) -> int:
    """The smallest integer >= n whose only prime factors are 2, 3 and 5."""
    while True:
        m = n
        for p in (2, 3, 5):
            while m % p == 0:
                m //= p
        if m == 1:
            return n
        n += 1


@functools.lru_cache(maxsize=32)
def _frequency_filters(Hp: int, Wp: int, blur: tuple, dtype) -> tuple[Tensor, ...]:
    """Responses on the (Hp, Wp // 2 + 1) rfft2 grid, cached per size and blur: the blur (the
    Gaussian exp(-sigma^2 w^2 / 2) for ``blur = ("gaussian", sigma)``, or a symmetric sampled
    kernel's exact response for ``blur = ("kernel", k_0, ..., k_r)``), the cubic B-spline's
    sampled kernel [1, 4, 1] / 6 ((4 + 2 cos w) / 6 per axis, never below 1/3), and the
    derivatives d/du, d/dv (i w per axis). Callers must not modify them."""
    wy = 2 * math.pi * torch.fft.fftfreq(Hp, dtype=dtype)[:, None]
    wx = 2 * math.pi * torch.fft.rfftfreq(Wp, dtype=dtype)[None, :]
    if blur[0] == "gaussian":
        response = torch.exp(-0.5 * blur[1] ** 2 * (wx * wx + wy * wy))
    else:
        taps = torch.tensor(blur[1:], dtype=dtype)  # k_0, k_1, ..., k_r
        j = torch.arange(1, len(taps), dtype=dtype)
        response = ((taps[0] + 2 * (taps[1:] * torch.cos(wx[..., None] * j)).sum(-1))
                    * (taps[0] + 2 * (taps[1:] * torch.cos(wy[..., None] * j)).sum(-1)))
    spline = (4 + 2 * torch.cos(wx)) * (4 + 2 * torch.cos(wy)) / 36
    return response, spline, 1j * wx * torch.ones_like(wy), 1j * wy * torch.ones_like(wx)


def _padded_spectrum(images: Tensor, blur_sigma: float, kernel: Tensor | None):
    """rfft2 of the mirror-padded images times the blur's response, (F, Hp, Wp // 2 + 1), with
    the filters of :func:`_frequency_filters`, the padded size and the crop back to (H, W).

    The pad is wide enough that filtering equals mirrored-border convolution to about 3e-5 (the
    B-spline inverse decays as 0.268^n, 1e-5 after 8 px; the Gaussian within 3 sigma), and a
    little wider at the far sides to reach a size the FFT is fast at (factors 2, 3, 5).
    """
    F, H, W = images.shape
    radius = int(math.ceil(3 * blur_sigma)) if kernel is None else (len(kernel) - 1) // 2
    pad = min(8 + radius, H - 1, W - 1)
    extra_h = min(_fast_fft_size(H + 2 * pad) - H - 2 * pad, H - 1 - pad)
    extra_w = min(_fast_fft_size(W + 2 * pad) - W - 2 * pad, W - 1 - pad)
    padded = torch.nn.functional.pad(images[:, None], (pad, pad + extra_w, pad, pad + extra_h), mode="reflect")[:, 0]
    Hp, Wp = padded.shape[-2:]
    blur = ("gaussian", float(blur_sigma)) if kernel is None else ("kernel", *kernel[radius:].tolist())
    filters = _frequency_filters(Hp, Wp, blur, images.dtype)
    spectrum = torch.fft.rfft2(padded) * filters[0]
    crop = (slice(None), slice(pad, pad + H), slice(pad, pad + W))
    return spectrum, filters, (Hp, Wp), crop


def prefilter(images: Tensor, blur_sigma: float = 0.0, kernel: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """Gaussian-blurred images and their cubic B-spline coefficients, both (F, H, W).

    Both filters are applied at once in the Fourier domain on mirror-padded images: the
    Gaussian exp(-sigma^2 w^2 / 2), and the inverse of the B-spline's sampled kernel
    [1, 4, 1] / 6, whose response (4 + 2 cos w) / 6 never falls below 1/3.

    Parameters
    ----------
    images : Tensor, shape (F, H, W)
    blur_sigma : float
        Standard deviation of the Gaussian in px (0: no blur).
    kernel : Tensor, shape (2 r + 1,), optional
        A symmetric sampled kernel to blur with instead of the Gaussian (applied separably,
        through its exact frequency response: the same as convolution with mirrored borders).

    Returns
    -------
    blurred : Tensor, shape (F, H, W)
    coefficients : Tensor, shape (F, H, W)
        ``bspline_sample(coefficients, p)`` interpolates the blurred frames at points p.
    """
    spectrum, (_, spline, *_), size, crop = _padded_spectrum(images, blur_sigma, kernel)
    blurred = torch.fft.irfft2(spectrum, s=size)[crop]
    coefficients = torch.fft.irfft2(spectrum / spline, s=size)[crop].contiguous()
    return blurred, coefficients


def _reference_splines(reference: Tensor, kernel: Tensor) -> tuple[Tensor, Tensor]:
    """What the fit needs of the reference (H, W), blurred by ``kernel``, from one FFT.

    Returns
    -------
    coefficients : Tensor, shape (3, H, W)
        Cubic B-spline coefficients of the blurred reference and of its exact derivatives d/du
        and d/dv (so that one fetch interpolates value and gradient at any point).
    strength : Tensor, shape (H, W)
        Squared gradient of the coefficients at the pixels: where to compare. (The coefficients
        are the blurred reference sharpened by the spline's prefilter; on bench_registration's
        stacks choosing points by their gradient was as accurate as by the blurred image's
        central differences, and it needs no extra transform.)
    """
    spectrum, (_, spline, d_u, d_v), size, crop = _padded_spectrum(reference[None], 0.0, kernel)
    coef = spectrum / spline
    parts = torch.fft.irfft2(torch.cat((coef, coef * d_u, coef * d_v)), s=size)[crop].contiguous()
    return parts, parts[1] ** 2 + parts[2] ** 2


def bspline_sample(coefficients: Tensor, points: Tensor) -> Tensor:
    """Evaluate cubic B-spline images at fractional pixel points.

    Cubic B-spline interpolation, unlike torch's bicubic (Keys, a = -0.75), has no first-order
    error, so a sub-pixel warp does not bias the registration (about 1e-4 px instead of 0.04 px
    on content at a tenth of the sampling rate). Each 4 x 4 B-spline sum is computed as four
    bilinear fetches (Sigg & Hadwiger, GPU Gems 2, ch. 20), all by ``grid_sample``.

    Parameters
    ----------
    coefficients : Tensor, shape (F, H, W)
        From :func:`prefilter`.
    points : Tensor, shape (F, N, 2)
        (u, v) pixel coordinates; the image is mirrored about its border pixels.

    Returns
    -------
    Tensor, shape (F, N), in the coefficients' dtype.
    """
    F = coefficients.shape[0]
    n = points.shape[1]
    got, (gu0, gu1, gv0, gv1) = _bilinear_fetches(coefficients[:, None], points)
    got = got.view(F, 4, n)
    return gv0 * (gu0 * got[:, 0] + gu1 * got[:, 1]) + gv1 * (gu0 * got[:, 2] + gu1 * got[:, 3])


def _bilinear_fetches(images: Tensor, points: Tensor) -> tuple[Tensor, tuple[Tensor, ...]]:
    """The four bilinear fetches behind a cubic B-spline evaluation, and their weights.

    A 4 x 4 B-spline sum is four bilinear fetches at shifted positions (Sigg & Hadwiger,
    GPU Gems 2, ch. 20). ``images`` (B, C, H, W) and ``points`` (B, n, 2) (u, v) px give the
    fetches (B, C, 4 n), fetch j of point i at index j n + i, and their weights
    ``(gu0, gu1, gv0, gv1)``, each (B, n), in the images' dtype.
    """
    B, C, H, W = images.shape
    n = points.shape[1]
    dtype = images.dtype
    # Both axes at once, (B, n, 2): the weights of the two fetches along each axis and their
    # positions already in grid_sample's [-1, 1] coordinates (align_corners=True).
    i = torch.floor(points)
    f = (points - i).to(dtype)  # the sub-pixel part, exact even when the coordinate is large
    i = i.to(dtype)
    f2 = f * f
    f3 = f2 * f
    w1 = (4 - 6 * f2 + 3 * f3) / 6
    g0 = (1 - f) ** 3 / 6 + w1
    g1 = 1 - g0
    scale = torch.tensor([2.0 / (W - 1), 2.0 / (H - 1)], dtype=dtype)
    p0 = (i - 1 + w1 / g0) * scale - 1
    p1 = (i + 1 + f3 / (6 * g1)) * scale - 1
    # The four fetches: (u0, v0), (u1, v0), (u0, v1), (u1, v1).
    u = torch.stack((p0[..., 0], p1[..., 0]), 1).repeat(1, 2, 1)
    v = torch.stack((p0[..., 1], p1[..., 1]), 1).repeat_interleave(2, 1)
    grid = torch.stack((u, v), -1)  # (B, 4, n, 2)
    got = torch.nn.functional.grid_sample(
        images, grid.view(B, 1, 4 * n, 2), mode="bilinear", padding_mode="reflection", align_corners=True,
    )
    gu0, gu1, gv0, gv1 = g0[..., 0], g1[..., 0], g0[..., 1], g1[..., 1]
    return got.view(B, C, 4 * n), (gu0, gu1, gv0, gv1)


# --------------------------------------------------------------------------- Lucas-Kanade


@functools.lru_cache(maxsize=8)
def gaussian_kernel(sigma: float, dtype=torch.float64) -> Tensor:
    """Sampled, normalised 1-D Gaussian of standard deviation ``sigma`` px, radius ceil(2 sigma),
    shape (2 r + 1,); ``[1]`` for sigma = 0.

    The frames are blurred at the compared points by direct (2 r + 1)^2 sums, so the radius is
    what a registration costs per point; the reference is blurred by the same truncated kernel,
    so the two stay matched. On bench_registration's stacks radius 2 (sigma = 1) was as accurate
    as radius 3 (mean error 0.0031 / 0.0024 / 0.0043 px at 128^2 / 256^2 / 512^2, against
    0.0032 / 0.0036 / 0.0051). Cached: callers must not modify the result."""
    radius = int(math.ceil(2 * sigma))
    if radius == 0:
        return torch.ones(1, dtype=dtype)
    x = torch.arange(-radius, radius + 1, dtype=torch.float64)
    k = torch.exp(-0.5 * (x / sigma) ** 2)
    return (k / k.sum()).to(dtype)


def _spline_fetch(coefficients: Tensor, points: Tensor) -> Tensor:
    """Evaluate C cubic B-spline images (C, H, W) at every frame's points (F, N, 2) -> (C, F, N).

    The same four-bilinear-fetch evaluation as :func:`bspline_sample`, for C images shared by
    every frame and with fewer operations: the fit calls it with value and gradient channels at
    once, and its cost at small frames is mostly per operation. ``points`` are float64 (u, v) px, so that the
    sub-pixel part stays exact at any frame size; the rest is in the coefficients' dtype.
    Coefficients outside the image read as 0 (the cheapest padding): the values are exact at
    points at least 2 px inside the image, and the fit compares no others.
    """
    C, H, W = coefficients.shape
    F, N = points.shape[:2]
    dtype = coefficients.dtype
    i = torch.floor(points)
    f = (points - i).to(dtype)
    f2 = f * f
    w1 = (0.5 * f - 1).mul_(f2).add_(2 / 3)  # (4 - 6 f^2 + 3 f^3) / 6
    g0 = (1 - f) ** 3 / 6 + w1  # weight of the lower fetch
    g1 = 1 - g0
    # Fetch positions in grid_sample's [-1, 1] (align_corners=True), (2, F, N, 2): lower, upper.
    scale = _grid_scale(W, H, dtype)
    at = (torch.stack((w1 / g0 - 1, 1 + f2 * f / (6 * g1))) + i.to(dtype)) * scale - 1
    # The four fetches (u0, v0), (u1, v0), (u0, v1), (u1, v1): index [v fetch, u fetch].
    grid = torch.stack((at[None, :, ..., 0].expand(2, 2, F, N), at[:, None, ..., 1].expand(2, 2, F, N)), -1)
    got = torch.nn.functional.grid_sample(coefficients[None], grid.view(1, 1, 4 * F * N, 2), mode="bilinear",
                                          padding_mode="zeros", align_corners=True).view(C, 4, F, N)
    weights = torch.stack((g0, g1))  # (2, F, N, 2): [fetch, ..., axis]
    # The four fetches' weights (v weight times u weight), in the fetches' order: (4, F, N).
    weights = (weights[:, None, ..., 1] * weights[None, ..., 0]).view(4, F, N)
    return (got * weights).sum(1)


@functools.lru_cache(maxsize=16)
def _grid_scale(W: int, H: int, dtype) -> Tensor:
    """(2,) factors from px to grid_sample's align_corners=True coordinates, cached (callers
    must not modify them)."""
    return torch.tensor([2.0 / (W - 1), 2.0 / (H - 1)], dtype=dtype)


@dataclass
class _Fit:
    homographies: Tensor  # (F, 3, 3) frame -> reference, float64
    residual: Tensor  # (F, N) aligned difference at the solution (0 where not compared)
    weights: Tensor  # (F, N) robust weights (0 where not compared)
    slope: Tensor  # (F, N, 2) d reference value / d frame motion (normalised units), at the solution
    rss: Tensor  # (F,) weighted sum of squared residuals
    n_valid: Tensor  # (F,) pixels compared
    mismatch_fraction: Tensor  # (F,) compared pixels in tiles that do not match (occlusion)
    mismatch_points: Tensor  # (F, N) bool: those points
    covariance: Tensor  # (F, k, k) of the normalised parameters
    converged: Tensor  # (F,) bool
    sigma: Tensor  # (F,) robust residual scale
    correlation: Tensor  # (F,) correlation of frame and reference at the compared points


class _LucasKanade:
    """Forward-compositional Gauss-Newton fit of every frame's homography against the reference.

    Each frame is compared with the reference at a fixed set of its own pixels p (the share of
    pixels where the blurred reference has its strongest gradient): the reference, sampled where
    the frame's homography sends p, must match the frame there up to a gain and an offset,
    ``ref(H_k p) = gain_k frame_k(p) + offset_k``. Only the reference is ever interpolated (a
    cubic B-spline), and the frames are read at the points alone, so a fit costs in proportion
    to the number of points, not to the number of frame pixels.

    The reference's gradient is the exact derivative of its interpolant (B-spline coefficients of
    the Fourier derivative, fetched with the value), so the Gauss-Newton steps converge in about
    one step; an earlier bilinear gradient of central differences converged only linearly. The
    first steps use a few of the points (``coarse``), so the full set usually needs one
    evaluation. The warp update is parametrised in normalised coordinates (centred, half-size 1)
    so that the normal equations stay well conditioned for every model.
    """

    huber = 1.345  # Huber's constant: 95% efficiency on Gaussian residuals
    tile_ratio = 4.0  # a tile this many times worse than the median tile does not match

    def __init__(self, coefficients: Tensor, samples: Tensor, points: Tensor, margin: int):
        """``coefficients`` (3, H, W): B-spline coefficients of the blurred reference and of its
        exact d/du and d/dv (:func:`_reference_splines`); ``samples`` (F, N): the blurred frames
        at ``points`` (N, 2), (u, v) integer pixel coordinates in float64."""
        H, W = coefficients.shape[-2:]
        self.H, self.W, self.margin, self.dtype = H, W, margin, coefficients.dtype
        self.coefficients = coefficients
        self.scale = max(H, W) / 2.0
        self.norm, self.norm_inv, self.eye3, self.corners_h, self.centre_h = _frame_constants(H, W)
        self._set_points(samples, points)
        # The first step of a fit only has to get near the solution: on large point sets it
        # is taken on every few points (at most COARSE_POINTS, plain least squares), and the
        # full, robust set then usually converges in one evaluation.
        step = len(points) // COARSE_POINTS
        self.coarse = None
        if step >= 2:
            self.coarse = copy.copy(self)
            self.coarse._set_points(samples[:, ::step], points[::step])

    def _set_points(self, samples: Tensor, points: Tensor) -> None:
        """What depends on the compared points (everything else is shared with ``coarse``)."""
        self.samples, self.points = samples, points
        self.points_h = torch.cat((points, torch.ones(len(points), 1, dtype=torch.float64)), -1)  # (N, 3)
        u, v = points[:, 0], points[:, 1]
        self.xy = ((u - (self.W - 1) / 2) / self.scale, (v - (self.H - 1) / 2) / self.scale)
        self._jacobian: dict[str, tuple[Tensor, Tensor]] = {}
        self._score_cache: tuple | None = None
        # 8 x 8 tiles over the frame, for the mismatch (occlusion) measure.
        self.n_tiles = 64
        self.tile_index = ((v * 8 / self.H).long() * 8 + (u * 8 / self.W).long())[None]

    def jacobian(self, model: str) -> tuple[Tensor, Tensor]:
        """d(x', y')/dp of the update warp at the points, two (N, k) tensors (normalised units)."""
        if model not in self._jacobian:
            jx, jy = _warp_jacobian(*self.xy, model)
            self._jacobian[model] = (torch.stack(jx, -1).to(self.dtype), torch.stack(jy, -1).to(self.dtype))
        return self._jacobian[model]

    def steepest(self, slope: Tensor, model: str) -> Tensor:
        """Steepest-descent images (F, N, k): minus d residual / d parameters."""
        if model == "translation":  # the warp's Jacobian is the identity
            return slope
        jx, jy = self.jacobian(model)
        return slope[..., :1] * jx + slope[..., 1:] * jy

    def residual(self, homographies: Tensor, samples: Tensor, keep: Tensor | None = None, robust: bool = True):
        """Aligned difference at the points, with robust weights, for the frames given.

        Each frame gets its own gain and offset (weighted least squares against the reference,
        refitted with the robust weights), so that exposure changes and an occluder that shifts
        the frame's mean do not leak into the motion.

        Returns
        -------
        r : Tensor, shape (F, N)
            gain * frame + offset - reference, 0 where not compared.
        mask : Tensor, shape (F, N), bool
            Points that land well inside the reference (and are in ``keep``, if given).
        w : Tensor, shape (F, N)
            Huber weights (0 where not compared).
        sigma : Tensor, shape (F,), or None
            Robust scale of r (None, and plain least-squares weights, if not ``robust``).
        slope : Tensor, shape (F, N, 2)
            Change of the reference value at the point per unit of frame motion (normalised
            units) along x and y: r changes by minus this.
        target : Tensor, shape (F, N)
            The reference at the points, through each frame's homography.
        """
        qh = homographies @ self.points_h.T  # (F, 3, N) float64
        q = (qh[:, :2] / qh[:, 2:]).mT.contiguous()  # (F, N, 2)
        u, v = q[..., 0], q[..., 1]
        m = self.margin
        mask = (u >= m) & (u <= self.W - 1 - m) & (v >= m) & (v <= self.H - 1 - m)
        if keep is not None:
            mask = mask & keep
        values = _spline_fetch(self.coefficients, q)  # value, d/du, d/dv: (3, F, N)
        target, t_uv = values[0], values[1:]
        w = mask.to(self.dtype)
        r = self._photometric(samples, target, w) * w
        sigma = None
        if robust:
            w, sigma = self._huber(r, mask)
            r = self._photometric(samples, target, w) * mask  # again, with an occluder's points down-weighted
            w, _ = self._huber(r, mask, sigma)
        # The reference's gradient at q, through dq/dp of the homography (the motion is a change
        # of p), times the normalised unit: how fast the reference value at q changes. dq/dp is
        # (H[i, j] - q_i H[2, j]) / (H[2] . [p, 1]); it is taken at the frame's centre: for a
        # scan's nearly affine motions it changes by at most 1.2e-4 of itself out to the corners
        # (the plan's homographies, full 960 x 1280 frame; 5e-5 on a 512^2 ROI).
        c = homographies @ self.centre_h  # (F, 3)
        jac = (homographies[:, :2, :2] - (c[:, :2, None] / c[:, 2:, None]) * homographies[:, 2:, :2])
        jac = jac * (self.scale / c[:, 2, None, None])
        slope = t_uv.permute(1, 2, 0) @ jac.to(self.dtype)
        return r, mask, w, sigma, slope, target

    def _photometric(self, values: Tensor, target: Tensor, w: Tensor) -> Tensor:
        """gain * values + offset - target, gain and offset fitted by weighted least squares."""
        sw = w.sum(-1).clamp_min(1e-12)
        wx = w * values
        mx, mt = wx.sum(-1) / sw, (w * target).sum(-1) / sw
        # Weighted (co)variances from the raw sums: the frames are normalised to unit spread, so
        # nothing cancels badly.
        var = (wx * values).sum(-1) - sw * mx * mx
        cov = (wx * target).sum(-1) - sw * mx * mt
        gain = torch.where(var > 1e-12, cov / var.clamp_min(1e-12), 1.0)
        return gain[:, None] * (values - mx[:, None]) + (mt[:, None] - target)

    def _huber(self, r: Tensor, mask: Tensor, sigma: Tensor | None = None) -> tuple[Tensor, Tensor]:
        if sigma is None:
            sigma = _robust_scale(r, mask)
        # Huber weights min(1, c sigma / |r|), 0 where not compared.
        w = ((self.huber * sigma[:, None]) / r.abs()).clamp_max(1.0) * mask
        return w, sigma

    def first_step(self, init: Tensor, samples: Tensor, model: str) -> Tensor:
        """One plain (not robust) Gauss-Newton step from ``init`` (F, 3, 3) on these (few)
        points; frames whose step is not finite or over 2 px stay where they were."""
        r, _, w, _, slope, _ = self.residual(init, samples, robust=False)
        sd = self.steepest(slope, model)
        hess, grad = _normal_equations(w, sd, r)
        dp = torch.linalg.solve(hess + 1e-12 * torch.eye(sd.shape[-1], dtype=torch.float64), grad)
        move = self.motion_px(dp, model)
        good = torch.isfinite(move) & (move <= 2.0)
        return torch.where(good[:, None, None], self.compose(init, dp.nan_to_num(0.0), model), init)

    def compose(self, homographies: Tensor, dp: Tensor, model: str) -> Tensor:
        """Forward composition H <- H W(dp), W in normalised coordinates; (F, 3, 3), (F, k)."""
        upd = homographies @ (self.update_basis(model) @ dp.T).permute(2, 0, 1).add_(self.eye3)
        return upd / upd[:, 2:3, 2:3]

    def update_basis(self, model: str) -> Tensor:
        """(3, 3, k): the warp update W(dp) = I + basis @ dp in pixel coordinates (the parameters
        are normalised: W is conjugated by the normaliser)."""
        return _update_basis(self.H, self.W, model)

    def corner_distance(self, a: Tensor, b: Tensor) -> Tensor:
        """Largest distance (px) between where homographies a and b (F, 3, 3) send the frame's
        corners, (F,)."""
        qa, qb = self.corners_h @ a.mT, self.corners_h @ b.mT  # (F, 4, 3)
        return (qa[..., :2] / qa[..., 2:] - qb[..., :2] / qb[..., 2:]).norm(dim=-1).amax(-1)

    def motion_px(self, dp: Tensor, model: str) -> Tensor:
        """Largest displacement (px) a small parameter step causes at the frame's corners, (F,)."""
        moves = _corner_jacobian(self.H, self.W, model) @ dp.T  # (8, F): dx at the 4 corners, then dy
        return torch.hypot(moves[:4], moves[4:]).amax(0)

    def fit(self, init: Tensor, model: str, iterations: int, tol: float,
            frames: Tensor | None = None, keep: Tensor | None = None) -> _Fit:
        """Refine ``init`` (F, 3, 3) so that the reference, sampled through each frame's
        homography, matches the frame.

        ``frames`` (F,) long, optional, picks the frames that ``init`` belongs to (default: all);
        ``keep`` (F, N) bool, optional, leaves out points (for example an occluded region).
        """
        samples = self.samples if frames is None else self.samples[frames]
        F, N = samples.shape
        k = N_PARAMS[model]
        eye = 1e-12 * torch.eye(k, dtype=torch.float64)
        Hk = init.clone()
        if self.coarse is not None and keep is None:
            Hk = self.coarse.first_step(Hk, self.coarse.samples if frames is None else self.coarse.samples[frames], model)
        converged = torch.zeros(F, dtype=torch.bool)
        # A frame whose step exceeds 2 px, or that wanders over 3 px from its start, has no basin
        # to converge in: it is left where it is (and flagged by the caller).
        diverged = torch.zeros(F, dtype=torch.bool)
        # Each frame's residual at its last evaluation; a converged frame moved less than
        # ``tol`` since (its last, small step is applied), so these are its statistics:
        # [r, mask, w, sigma, slope, target, normal matrix], each with the frames first.
        last: list[Tensor] = []
        for _ in range(iterations):
            todo = ~(converged | diverged)
            everyone = bool(todo.all())
            active = slice(None) if everyone else todo.nonzero()[:, 0]
            found = list(self.residual(Hk[active], samples[active], None if keep is None else keep[active]))
            ra, wa, ga = found[0], found[2], found[4]
            sd = self.steepest(ga, model)
            hess, grad = _normal_equations(wa, sd, ra)
            found.append(hess)
            if everyone:
                last = found
            else:
                for full, part in zip(last, found):
                    full[active] = part
            dp = torch.linalg.solve(hess + eye, grad)
            Hk[active] = self.compose(Hk[active], dp, model)
            move = self.motion_px(dp, model)
            converged[active] = move < tol
            wandered = self.corner_distance(Hk[active], init[active])
            diverged[active] = ~torch.isfinite(move) | (move > 2.0) | (wandered > 3.0)
            if bool((converged | diverged).all()):
                break
        r, mask, w, sigma, slope, target, hess = last
        n_valid = mask.sum(-1).double()
        r, w, sigma = r.double(), w.double(), sigma.double()
        rss = (w * r * r).sum(-1)
        # Noise-limited covariance: the robust scale, not the RSS, so that an occluder shows up
        # as a mismatch and not as a loss of precision.
        cov = torch.linalg.inv(hess + eye) * (sigma * sigma)[:, None, None]
        fraction, points = self.mismatch(r, mask)
        return _Fit(Hk, r, w, slope, rss, n_valid, fraction, points, cov, converged, sigma,
                    _correlation(samples, target, mask))

    def mismatch(self, r: Tensor, mask: Tensor) -> tuple[Tensor, Tensor]:
        """Points in tiles whose mean |residual| is far above the frame's typical tile.

        An occluder or a moving object is coherent in space, whereas the aliasing that differs
        between shifted frames is spread thinly over every edge. Returns the share of compared
        points in such tiles (F,) and the points themselves (F, N) bool.
        """
        F = r.shape[0]
        tiles = self.tile_index.expand(F, -1)
        count = torch.zeros(F, self.n_tiles, dtype=r.dtype).scatter_add_(1, tiles, mask.to(r.dtype))
        total = torch.zeros(F, self.n_tiles, dtype=r.dtype).scatter_add_(1, tiles, r.abs())
        used = count >= 8
        mean = torch.where(used, total / count.clamp_min(1), torch.full_like(total, float("nan")))
        typical = torch.nanmedian(mean, dim=1).values.nan_to_num(0.0)
        bad = used & (mean > self.tile_ratio * typical[:, None])
        if not bool(bad.any()):  # the usual case
            return torch.zeros(F, dtype=r.dtype), torch.zeros_like(mask)
        fraction = (count * bad).sum(1) / count.sum(1).clamp_min(1)
        # The points to leave out: bad tiles and their neighbours (an occluder's edge rarely
        # follows the tiles).
        grown = torch.nn.functional.max_pool2d(bad.reshape(F, 1, 8, 8).to(r.dtype), 3, 1, 1)
        return fraction, grown.reshape(F, -1).bool().gather(1, tiles) & mask

    def score_test(self, fit: _Fit, model: str, base: str, corr_area: float, use: Tensor) -> tuple[float, float]:
        """What one Gauss-Newton step of a richer ``model`` would gain over one of ``base``, the
        model of ``fit``, from ``fit``'s last evaluation.

        Both steps are taken, so that what is left of ``base``'s own convergence (less than the
        fit's tolerance) is not counted for the richer model.

        Returns (BIC gain summed over the frames in ``use`` (F,) bool, largest extra motion in px
        over them); the gain is compared with the extra parameters' penalty by the caller.
        """
        # Every model's warp is a linear map of the homography's parameters: one set of normal
        # equations serves every model tested against the same fit.
        def step(m: str) -> tuple[Tensor, Tensor]:
            """The step as homography parameters (F, 8), and the drop of the RSS it brings (F,)."""
            embed = _EMBEDDING[m]
            grad = grad8 @ embed
            dp = torch.linalg.solve(embed.T @ hess8 @ embed + 1e-12 * torch.eye(embed.shape[1], dtype=torch.float64), grad)
            return dp @ embed.T, (dp * grad).sum(-1).clamp_min(0)

        if self._score_cache is None or self._score_cache[0] is not fit or self._score_cache[1] != base:
            sd = self.steepest(fit.slope, "homography")
            hess8, grad8 = _normal_equations(fit.weights.to(sd.dtype), sd, fit.residual.to(sd.dtype))
            self._score_cache = (fit, base, hess8, grad8, step(base))
        _, _, hess8, grad8, (simple, drop_simple) = self._score_cache
        rich, drop = step(model)
        n_eff = (fit.n_valid / corr_area).clamp_min(1.0)
        gain = n_eff * torch.log((fit.rss - drop_simple).clamp_min(1e-300) / (fit.rss - drop).clamp_min(1e-300))
        return float(gain[use].sum()), float(self.motion_px(rich - simple, "homography")[use].max())


def _merge(fit: _Fit, part: _Fit, index: Tensor) -> _Fit:
    """``fit`` with the frames ``index`` replaced by those of ``part`` (fitted on them alone)."""
    out = _Fit(**{name: getattr(fit, name).clone() for name in fit.__dataclass_fields__})
    for name in fit.__dataclass_fields__:
        getattr(out, name)[index] = getattr(part, name)
    return out


def _correlation(a: Tensor, b: Tensor, mask: Tensor) -> Tensor:
    """Pearson correlation of a and b (F, N) over the points in ``mask`` (F, N), (F,) float64."""
    m = mask.double()
    n = m.sum(-1).clamp_min(1)
    a, b = a.double(), b.double()
    da = (a - (a * m).sum(-1, keepdim=True) / n[:, None]) * m
    db = (b - (b * m).sum(-1, keepdim=True) / n[:, None]) * m
    den = ((da * da).sum(-1) * (db * db).sum(-1)).sqrt()
    return torch.where(den > 0, (da * db).sum(-1) / den.clamp_min(1e-300), torch.zeros_like(den))


def _normal_equations(w: Tensor, sd: Tensor, r: Tensor) -> tuple[Tensor, Tensor]:
    """J^T W J (F, k, k) and J^T W r (F, k) for every frame, from one batched product, float64:
    weights (F, N), steepest-descent images (F, N, k), residuals (F, N). (Summed in the inputs'
    precision: float32 sums of a few thousand terms are good to 1e-6, far below what the motion
    needs.)"""
    k = sd.shape[-1]
    both = torch.cat((sd, r[..., None]), -1)  # (F, N, k + 1)
    product = ((w[..., None] * both).mT @ sd).double()  # (F, k + 1, k)
    return product[:, :k], product[:, k]


def _robust_scale(r: Tensor, mask: Tensor) -> Tensor:
    """Per-frame residual scale 1.4826 * median |r| over the compared pixels, (F,)."""
    # Every other point is plenty for a median, at half the cost.
    r, mask = r[:, ::2], mask[:, ::2]
    vals = torch.where(mask, r.abs(), torch.full_like(r, float("nan")))
    mad = torch.nanmedian(vals, dim=-1).values
    return (1.4826 * mad).nan_to_num(1.0).clamp_min(1e-12)


def _bic(fit: _Fit, k: int, corr_area: float, use: Tensor) -> float:
    """Bayesian information criterion of a fit, summed over the frames in ``use`` (lower is
    better), with the effective number of independent residuals n / corr_area."""
    n_eff = (fit.n_valid / corr_area).clamp_min(k + 1.0)
    per_frame = n_eff * torch.log(fit.rss.clamp_min(1e-300) / fit.n_valid.clamp_min(1)) + k * torch.log(n_eff)
    return float(per_frame[use].sum())


def _penalty(fit: _Fit, k_extra: int, corr_area: float, use: Tensor) -> float:
    n_eff = (fit.n_valid / corr_area).clamp_min(2.0)
    return float(k_extra * torch.log(n_eff[use]).sum())


def _strongest_points(strength: Tensor, margin: int, keep_fraction: float, max_points: int) -> Tensor:
    """Flat indices (N,), sorted, of pixels where ``strength`` (H, W) is high, at least
    ``margin`` px from the border: those above the (1 - ``keep_fraction``) quantile of the inner
    pixels (at least 64), thinned evenly to at most ``max_points``.

    Thinning a large strong set, rather than taking only the very strongest pixels, keeps the
    set's mix: on fine, aliased bars the strongest pixels are exactly those where the shifted
    frames disagree most. The quantile is read from a subsample of about 4k inner pixels.
    """
    H, W = strength.shape
    inner = strength[margin:H - margin, margin:W - margin]
    h, w = inner.shape
    values = inner.reshape(-1)
    n_keep = min(h * w, max(64, int(keep_fraction * h * w)))
    sub = values[::max(1, values.numel() // 4096)]
    threshold = torch.kthvalue(sub, max(1, min(len(sub), int(round(len(sub) * (1 - n_keep / (h * w))))))).values
    local = (values >= threshold).nonzero()[:, 0]
    if len(local) < min(64, h * w):
        local = torch.topk(values, min(64, h * w)).indices.sort().values
    if len(local) > max_points:
        local = local[torch.linspace(0, len(local) - 1, max_points).round().long()]
    return (local // w + margin) * W + local % w + margin


# --------------------------------------------------------------------------- coarse start


def phase_correlation_shifts(frames: Tensor, reference: Tensor) -> Tensor:
    """Coarse translation of each frame relative to the reference, (F, 2) px as (du, dv).

    Normalised cross-power spectrum of Hann-windowed frames; the integer peak is refined by a
    parabola through its neighbours. Good to a few tenths of a pixel, which is all the
    Lucas-Kanade refinement needs to start from any shift. The sign is the homography's: content
    at u in the frame sits at u + du in the reference.
    """
    F, H, W = frames.shape
    win = torch.outer(torch.hann_window(H, periodic=False, dtype=frames.dtype),
                      torch.hann_window(W, periodic=False, dtype=frames.dtype))
    a = torch.fft.rfft2((reference - reference.mean()) * win)
    b = torch.fft.rfft2((frames - frames.mean((-2, -1), keepdim=True)) * win)
    cross = a * b.conj()
    corr = torch.fft.irfft2(cross / cross.abs().clamp_min(1e-12), s=(H, W))
    idx = corr.reshape(F, -1).argmax(-1)
    iv, iu = idx // W, idx % W
    f = torch.arange(F)

    def parabola(minus, centre, plus):
        den = minus - 2 * centre + plus
        return torch.where(den.abs() > 1e-12, 0.5 * (minus - plus) / den, torch.zeros_like(den))

    c0 = corr[f, iv, iu]
    du = iu + parabola(corr[f, iv, (iu - 1) % W], c0, corr[f, iv, (iu + 1) % W])
    dv = iv + parabola(corr[f, (iv - 1) % H, iu], c0, corr[f, (iv + 1) % H, iu])
    du = torch.where(du > W / 2, du - W, du)
    dv = torch.where(dv > H / 2, dv - H, dv)
    return torch.stack((du, dv), -1)


def _translation(shifts: Tensor) -> Tensor:
    m = torch.eye(3, dtype=torch.float64).repeat(len(shifts), 1, 1)
    m[:, :2, 2] = shifts
    return m


# --------------------------------------------------------------------------- public entry


def _in_inference_mode(fn):
    """Run ``fn`` under ``torch.inference_mode`` (no autograd bookkeeping: at small frames the
    registration's cost is mostly per tensor operation, and this takes about a tenth off) and
    hand back ordinary tensors, which callers may modify in place."""
    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        with torch.inference_mode():
            result = fn(*args, **kwargs)
        tensors = {name: value.clone() for name, value in vars(result).items() if isinstance(value, Tensor)}
        return dataclasses.replace(result, **tensors)

    return wrapper


@_in_inference_mode
def register_stack(
    frames,
    reference_index: int,
    prediction=None,
    model: str = "auto",
    *,
    blur_sigma: float = 1.0,
    keep_fraction: float = 0.2,
    max_points: int = 1024,
    iterations: int = 30,
    tolerance_px: float = 1e-2,
    motion_tolerance_px: float = 0.01,
    min_confidence: float = 0.5,
    dtype=torch.float32,
) -> Registration:
    """Estimate each frame's motion relative to the reference frame.

    Parameters
    ----------
    frames : Tensor or array, shape (F, H, W)
        The stack, any real dtype. Each frame is normalised to zero mean and unit standard
        deviation first, so gain and offset need not match.
    reference_index : int
        Index of the reference frame (its homography is the identity).
    prediction : Tensor, shape (F, 3, 3), optional
        Predicted homographies (frame -> reference pixel coordinates) from the optics, for
        example ``homographies_from_positions(optical_sample_positions(stack))``. The data
        corrects them; without a prediction the motion starts from phase correlation, and frames
        out of order cannot be told.
    model : {"auto", "translation", "similarity", "homography"}
        Motion model of the data's correction (on top of the prediction, if any).
    blur_sigma : float
        Gaussian pre-filter (px) on every frame, against noise and the aliased content that
        differs between shifted frames. The default 1.0 was chosen on bench_registration's
        stacks (4 scenes x 128, 256, 512 px, h = 4, 40 dB): mean error 0.0036 px against
        0.0066 at 0.7 and 0.0036 at 1.4; the aliased bars gain most.
    keep_fraction : float in (0, 1]
        Share of reference pixels (strongest gradients) that take part in the fit.
    max_points : int
        At most this many of them (at least 64): they hold nearly all the information on the
        motion, and the fit's cost grows with their number, not with the frame size.
    iterations, tolerance_px : int, float
        Lucas-Kanade stops when an update moves no corner of the frame by more than
        ``tolerance_px``.
    motion_tolerance_px : float
        In ``auto`` mode, a richer model must move some pixel by more than this to be kept.
    min_confidence : float
        Frames below this confidence are marked not ok.
    dtype : torch.dtype
        Precision of the resampling (float32 by default; the normal equations are always solved
        in float64). float32 agrees with float64 to well below 1e-3 px (tests check it).

    Returns
    -------
    Registration
    """
    frames = _check_frames(frames)
    F, H, W = frames.shape
    try:
        if isinstance(reference_index, bool):
            raise TypeError
        ref = operator.index(reference_index)
    except TypeError:
        raise HbisInputError(f"reference_index must be an integer, got {reference_index!r}") from None
    if not 0 <= ref < F:
        raise HbisInputError(f"reference_index must lie in [0, {F - 1}], got {ref}")
    prediction = _check_prediction(prediction, F)
    if model != "auto" and model not in MODELS:
        raise HbisInputError(f"model must be 'auto' or one of {MODELS}, got {model!r}")
    if not (math.isfinite(blur_sigma) and 0 <= blur_sigma <= 5):
        raise HbisInputError(f"blur_sigma must be a number in [0, 5] px, got {blur_sigma!r}")
    if not 0 < keep_fraction <= 1:
        raise HbisInputError(f"keep_fraction must lie in (0, 1], got {keep_fraction!r}")
    if isinstance(max_points, bool) or not isinstance(max_points, int) or max_points < 64:
        raise HbisInputError(f"max_points must be an integer >= 64, got {max_points!r}")
    if dtype not in (torch.float32, torch.float64):
        raise HbisInputError(f"dtype must be torch.float32 or torch.float64, got {dtype!r}")

    # Photometric normalisation: every frame to zero mean and unit standard deviation.
    frames = frames.to(dtype)
    mean, spread = _mean_and_spread(frames)
    tiny = 1e-6 * max(1.0, float(mean.abs().max()))
    flat = spread < tiny
    spread = spread.clamp_min(tiny)
    reference = (frames[ref] - mean[ref]) / spread[ref]
    noise = noise_sigma(reference[None]).expand(F)  # the same sensor: one frame says enough
    kernel = gaussian_kernel(blur_sigma, dtype)
    radius = (len(kernel) - 1) // 2
    margin = max(2 + int(math.ceil(2 * blur_sigma)), radius)
    if min(H, W) <= 2 * margin + 8:
        raise HbisInputError(f"frames of {H} x {W} px are too small to register (blur_sigma={blur_sigma})")

    # The points: the reference's strongest gradients, away from the border.
    coefficients, strength = _reference_splines(reference, kernel)
    index = _strongest_points(strength, margin, keep_fraction, max_points)
    n_points = len(index)
    # Blurred residuals are correlated over about 4 pi sigma^2 pixels; what the statistics need
    # is how many of the compared points share one such area.
    corr_area = max(1.0, 4 * math.pi * blur_sigma ** 2 * n_points / ((H - 2 * margin) * (W - 2 * margin)))
    points = torch.stack((index % W, index // W), -1).double()  # (N, 2) as (u, v)
    # Every frame, blurred like the reference, at the points only (a patch each).
    patch = (torch.arange(-radius, radius + 1)[:, None] * W + torch.arange(-radius, radius + 1)[None, :]).reshape(-1)
    gathered = frames.reshape(F, -1).index_select(1, (index[:, None] + patch).reshape(-1))
    values = gathered.view(F, n_points, -1) @ torch.outer(kernel, kernel).reshape(-1)
    samples = (values - mean[:, None]) / spread[:, None]

    if prediction is not None:
        init = prediction.clone()
    else:
        # A central window of at most 256 x 256 px is plenty for a start within the fit's reach.
        v0, u0 = max(0, (H - 256) // 2), max(0, (W - 256) // 2)
        window = frames[:, v0:v0 + 256, u0:u0 + 256]
        init = _translation(phase_correlation_shifts(window, window[ref]))
    init[ref] = torch.eye(3, dtype=torch.float64)
    lk = _LucasKanade(coefficients, samples, points, margin)

    chosen = "translation" if model == "auto" else model
    fit = lk.fit(init, chosen, iterations, tolerance_px)
    # Occlusion: leave out the tiles that do not match and fit those frames again. Only frames
    # that converged: one that did not has no tiles that match for a reason (another scene, no
    # texture), and leaving out its worst tiles would only flatter its correlation.
    keep, mismatch = None, fit.mismatch_fraction
    redo = ((mismatch > 0) & fit.converged).nonzero()[:, 0]
    if len(redo):
        keep = ~fit.mismatch_points
        again = lk.fit(fit.homographies[redo], chosen, iterations, tolerance_px, redo, keep[redo])
        fit = _merge(fit, again, redo)
    # The model is chosen on the frames that registered sensibly (converged, and correlating
    # with the reference where compared), not on the failures flagged below.
    use = fit.converged & (fit.correlation >= MIN_CORRELATION) & ~flat
    use[ref] = False
    if model == "auto" and bool(use.any()):
        for richer in MODELS[1:]:
            extra = N_PARAMS[richer] - N_PARAMS[chosen]
            gain, moved = lk.score_test(fit, richer, chosen, corr_area, use)
            if gain <= _penalty(fit, extra, corr_area, use) or moved <= motion_tolerance_px:
                continue
            trial = lk.fit(fit.homographies, richer, iterations, tolerance_px, keep=keep)
            moved = float(lk_motion_difference(trial.homographies, fit.homographies, H, W, use))
            if _bic(trial, N_PARAMS[richer], corr_area, use) < _bic(fit, N_PARAMS[chosen], corr_area, use) \
                    and moved > motion_tolerance_px:
                chosen, fit = richer, trial

    fit.mismatch_fraction = mismatch
    # What noise alone leaves in the residual: two frames' noise, through the blur.
    blur_gain = 1.0 if blur_sigma < 0.5 else 1 / (2 * math.sqrt(math.pi) * blur_sigma)
    noise_residual = math.sqrt(2) * blur_gain * noise
    precision = _precision_px(fit, chosen, H, W, corr_area)
    confidence, messages = _assess(fit, precision, flat, noise_residual, ref, iterations)
    ok = confidence >= min_confidence
    Hk = fit.homographies.clone()
    # A frame that failed keeps its starting motion (the prediction, if any), not a wild guess.
    Hk[~ok] = init[~ok]
    Hk[ref] = torch.eye(3, dtype=torch.float64)
    for k in (~ok).nonzero()[:, 0].tolist():
        start = "predicted" if prediction is not None else "phase-correlation"
        messages.append(f"frame {k}: not registered (confidence {float(confidence[k]):.2f}); "
                        f"its {start} motion is kept")
    out_of_order = torch.zeros(F, dtype=torch.bool)
    if prediction is not None and F > 2:
        out_of_order, order_messages = _check_order(Hk, prediction, H, W, ref, ok)
        messages += order_messages
    precision[ref] = 0.0
    residual = fit.sigma.clone()
    residual[ref] = 0.0
    return Registration(Hk, chosen, confidence, ok, messages, precision, residual, out_of_order)


def _mean_and_spread(frames: Tensor) -> tuple[Tensor, Tensor]:
    """Per-frame mean and standard deviation (population) of (F, H, W), each (F,).

    One pass for the sum of squares (a dot product); frames whose variance is small next to
    their squared mean, where that shortcut cancels badly, are recomputed in two passes.
    """
    F = frames.shape[0]
    flat = frames.reshape(F, -1)
    mean = flat.mean(-1)
    var = (torch.linalg.vecdot(flat, flat) / flat.shape[1] - mean * mean).clamp_min(0)
    unsure = (var < 1e-3 * mean * mean).nonzero()[:, 0]
    if len(unsure):
        var[unsure] = (flat[unsure] - mean[unsure, None]).square().mean(-1)
    return mean, var.sqrt()


def noise_sigma(frames: Tensor) -> Tensor:
    """Robust per-frame noise level (F,), in the frames' units (Immerkaer 1996, median form).

    The 3 x 3 operator [[1, -2, 1], [-2, 4, -2], [1, -2, 1]] cancels smooth content; on white
    noise of level s its output has standard deviation 6 s. The median makes edges count little.
    """
    # The operator is [1, -2, 1] along rows times the same along columns: two second differences.
    d = frames[..., :-2] - 2 * frames[..., 1:-1] + frames[..., 2:]
    out = (d[..., :-2, :] - 2 * d[..., 1:-1, :] + d[..., 2:, :]).flatten(1)
    step = max(1, out.shape[1] // 2048)  # a couple of thousand values make a good median
    return 1.4826 * out[:, ::step].abs().median(-1).values / 6.0


def _assess(fit: _Fit, precision: Tensor, flat: Tensor, noise: Tensor, ref: int,
            iterations: int) -> tuple[Tensor, list[str]]:
    """Confidence (F,) in [0, 1] and one message per problem found.

    The confidence multiplies three factors: the expected error from the fit's curvature and
    the noise (exp(-(e / 0.05 px)^2): texture), the share of pixels in tiles that matched
    (occlusion), and, where the residual is more than noise explains, how well frame and
    reference correlate at the compared points (a different scene). A fit that did not
    converge counts half.
    ``precision`` (F,) is the expected error in px (:func:`_precision_px`) and ``noise`` (F,)
    the expected residual scale from noise alone.
    """
    F = len(flat)
    precision = precision.clone()
    mismatch = fit.mismatch_fraction
    residual = fit.sigma
    unexplained = residual > 2 * noise
    confidence = torch.exp(-((precision / PRECISION_SCALE_PX) ** 2))
    confidence = confidence * (1 - mismatch).clamp(0, 1)
    match = ((fit.correlation - MIN_CORRELATION) / (1 - MIN_CORRELATION)).clamp(0, 1)
    confidence = torch.where(unexplained, confidence * match, confidence)
    confidence = torch.where(fit.converged, confidence, 0.5 * confidence)
    confidence = torch.where(flat, torch.zeros_like(confidence), confidence)
    messages: list[str] = []
    if bool(flat[ref]):
        messages.append(f"reference frame {ref} is flat: there is nothing to register against")
        confidence[:] = 0.0
    # Plain Python lists from here: one conversion each instead of one tensor op per frame.
    is_flat, converged = flat.tolist(), fit.converged.tolist()
    other_scene = ((fit.correlation < MIN_CORRELATION) & unexplained).tolist()
    correlation, occluded, error = fit.correlation.tolist(), mismatch.tolist(), precision.tolist()
    for k in range(F):
        if k == ref or is_flat[ref]:
            continue
        if is_flat[k]:
            messages.append(f"frame {k} is flat (no image)")
        elif other_scene[k]:
            messages.append(f"frame {k} does not match the reference (correlation "
                            f"{correlation[k]:.2f} where they are compared): a different scene?")
        elif occluded[k] > OCCLUSION_FRACTION:
            messages.append(f"frame {k}: {100 * occluded[k]:.0f}% of its pixels do not match "
                            "the reference and were left out (occlusion or a moving object?)")
        elif error[k] > PRECISION_SCALE_PX:
            messages.append(f"frame {k}: too little texture above the noise to register "
                            f"(expected error {error[k]:.3f} px)")
        if not converged[k] and not is_flat[k]:
            messages.append(f"frame {k}: registration did not converge in {iterations} iterations")
    confidence[ref] = 1.0
    return confidence.clamp(0, 1), messages


def lk_motion_difference(a: Tensor, b: Tensor, H: int, W: int, use: Tensor | None) -> Tensor:
    """Distance (px) between where two sets of homographies send the frame's corners: the
    largest over the frames in ``use`` (F,) bool, or per frame (F,) when ``use`` is None."""
    corners = torch.tensor([[0, 0], [W - 1, 0], [0, H - 1], [W - 1, H - 1]], dtype=torch.float64)
    d = (apply_homography(a, corners) - apply_homography(b, corners)).norm(dim=-1).amax(-1)
    return d if use is None else d[use].max()


def _precision_px(fit: _Fit, model: str, H: int, W: int, corr_area: float) -> Tensor:
    """RMS over a 5 x 5 grid on the frame of the displacement's standard error, in px, (F,).

    The least-squares covariance assumes independent residuals; the blurred frames have
    residuals correlated over about ``corr_area`` pixels, so the variance is scaled by it.
    """
    jac = _grid_jacobian(H, W, model)  # (2 P, k)
    var = ((jac @ fit.covariance) * jac).sum(-1)  # (F, 2 P): variance of dx, dy at each point
    return torch.sqrt(var.clamp_min(0).mean(-1) * 2 * corr_area) * (max(H, W) / 2.0)


@functools.lru_cache(maxsize=16)
def _grid_jacobian(H: int, W: int, model: str) -> Tensor:
    """d(x', y')/dp of ``model`` at a 5 x 5 grid over the frame, stacked as (2 * 25, k)."""
    s = max(H, W) / 2.0
    x = torch.linspace(-(W - 1) / 2, (W - 1) / 2, 5, dtype=torch.float64) / s
    y = torch.linspace(-(H - 1) / 2, (H - 1) / 2, 5, dtype=torch.float64) / s
    x, y = (t.reshape(-1) for t in torch.meshgrid(x, y, indexing="ij"))
    jx, jy = _warp_jacobian(x, y, model)
    return torch.cat((torch.stack(jx, -1), torch.stack(jy, -1)))


def _check_order(measured: Tensor, predicted: Tensor, H: int, W: int, ref: int, ok: Tensor):
    """Registered frames whose measured position is nearer another frame's planned position
    than their own.

    Returns (out_of_order (F,) bool, messages).
    """
    centre = torch.tensor([(W - 1) / 2, (H - 1) / 2, 1.0], dtype=torch.float64)
    m, p = (h @ centre for h in (measured, predicted))  # (F, 3) each
    m, p = m[:, :2] / m[:, 2:], p[:, :2] / p[:, 2:]
    spacing = torch.cdist(p, p)
    spacing.fill_diagonal_(float("inf"))
    half_step = 0.5 * float(spacing.min())
    dist = torch.cdist(m, p)
    nearest, own, registered = dist.argmin(1).tolist(), dist.diagonal().tolist(), ok.tolist()
    flags = [False] * len(m)
    out = []
    for k, (j, d) in enumerate(zip(nearest, own)):
        if k == ref or not registered[k] or d <= half_step:
            continue
        if j != k:
            flags[k] = True
            out.append(f"frame {k} sits where frame {j} was planned "
                       f"({d:.3f} px from its own plan): frames out of order?")
        else:
            out.append(f"frame {k} is {d:.3f} px from its planned position")
    return torch.tensor(flags), out
