"""Test-time adaptation: the refiner fine-tuned on one burst's own frames before it refines it.

The shipped networks learned from simulated cameras; a real camera blurs, adds noise and
processes its frames in ways no simulator here reproduces. A burst carries its own check of that:
a frame left out of the reconstruction can be predicted from the others' image through the forward
model of observation space (the pixel's box and the lens, read where the frame's motion puts
each sample: :mod:`hbis_torch.observation.forward`), and compared with what the camera recorded
(the lens: validate's 0.2 LR px by default, whatever lens the classical image undid, but the lens
undone where the burst's edges were too soft for all of their blur to be undone; :func:`forward_blur`).
:func:`adapt_refiner` fine-tunes the network's last convolution for a few steps to make that
prediction better:

1. the frames are cut to one window of :data:`CROP_PX` LR px (the most textured of a few
   candidates, :func:`crop_box`); the frames besides the reference are dealt into :data:`FOLDS`
   groups (every fourth frame); each group's *input* is the classical image of the other
   frames' samples in the window, its *targets* the group's samples there (robustness-weighted,
   at least :data:`BORDER_PX` inside the window);
2. only the last convolution (``tail``) is fine-tuned, on the body's features computed once per
   group (:meth:`~hbis_torch.reconstruct.learned.network.HbisSRNet.features`): a step costs a
   convolution of 32 channels, not the network's forward and backward passes (measured on
   development bursts, never the held-out renderer: ``training/adapt_dev.py``,
   ``benchmarks/results/adapt_dev.json``);
3. the loss is the targets' weighted squared error, plus :data:`ANCHOR` times the mean squared
   change of the output from the unadapted network's. The anchor holds what the frames cannot
   see: without it the network learns a pixel-scale checkerboard that the pixel's box averages
   away (on the shared Emily sequence the left-out frames' error halved in the fit and
   ``hbis validate`` lost 1.6 dB);
4. Adam, at most :data:`STEPS` steps on every group but the first, each on a sub-window of at
   most :data:`WINDOW_PX` LR pixels; the first group is held out to stop early: every
   :data:`CHECK_EVERY` steps its error is measured, the weights that predict it best are
   kept (the unadapted network's, if none beats it), and the steps stop once
   :data:`PATIENCE` checks in a row found none better;
5. the whole adaptation is bounded in time: ``budget_s`` seconds (the learned method gives it
   :data:`BUDGET_X_CLASSICAL` times what its classical step took, at least
   :data:`BUDGET_MIN_S`); the steps stop when it is spent, but not before :data:`MIN_STEPS`
   (at least one check is made).

Everything here is float32: the loss compares intensities in [0, 1] with errors of 1e-4 and
more, far above float32's rounding (the prediction agrees with float64's to 1e-6: tested).

It is what the learned method does on a burst by default (``--no-adapt`` turns it off,
:func:`hbis_torch.reconstruct.learned.burst.learned_burst`); a Risley scan's frames are not
adapted to. Measured in docs/real-bursts.md.
"""

from __future__ import annotations

import copy
import dataclasses
import math
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from hbis_torch.reconstruct.learned.inputs import TILE_HALO, network_inputs, run_tiled
from hbis_torch.observation.forward import DEFAULT_BLUR_PX, pixel_kernel, sample_grid

FOLDS = 4
# The tail alone, on a window of CROP_PX chosen by texture, with WINDOW_PX steps: on eight
# 640 x 480 development bursts (training/adapt_dev.py, benchmarks/results/adapt_dev.json; never
# the held-out renderer) 30 steps at 1e-3 gained +1.07 dB over classical on the mean (+0.85 at
# worst; the network unadapted +0.47), 60 steps +1.08 and 40 steps at 1.5e-3 +1.09, in 1.6,
# 2.4 and 1.9 times the classical step's time. The kept step was 10 to 20 of 30 in all eight.
STEPS = 30
LEARNING_RATE = 1e-3
# Chosen with the forward model's blur from six settings (docs/real-bursts.md): a weaker anchor
# gains more on real and held-out bursts but loses up to 2 dB on the training's own simulator.
ANCHOR = 1.0
CHECK_EVERY = 5
# The steps stop once this many checks in a row found no better weights: the kept step was 5 to
# 30 of 30 on the development bursts, and the steps after the last gain buy nothing. On adapt_dev's
# eight bursts at S = 2 with 8 and 16 frames and at S = 3 and 4 with 16
# (benchmarks/results/adapt_dev_patience_*.json) it took 15 to 30 steps, not 30, for the same
# PSNR to 0.016 dB at worst (-0.0005 dB on the mean at worst).
PATIENCE = 2
WINDOW_PX = 64
CROP_PX = 192
BORDER_PX = 2.0
# The time the learned method gives the adaptation: this many times its classical step's
# (burst_sr alone: 0.5 to 0.7 of what ``reconstruct(stack, "classical")`` takes on a 640 x 480
# development burst, which also measures the positions and the robustness weights), and at
# least BUDGET_MIN_S: a burst of small frames, whose classical step takes a tenth of a second,
# still makes its STEPS (on the shared real sequences, on a loaded machine, a floor of 1 s left
# them 0 to 16 steps and learned - classical fell from +0.50 to +0.27 dB at S = 2). With the
# adapted network's pass over the whole image, the learned method then takes about 2 to 2.6
# times the classical reconstruction at 640 x 480 (the bound: 3).
BUDGET_X_CLASSICAL = 1.5
BUDGET_MIN_S = 5.0
# Steps the time budget cannot stop: two checks' worth. A step works on a window of WINDOW_PX
# whatever the burst's size (tens of ms), so a number of them bounds the work as the budget bounds
# the time. On a machine busy with other work the folds' classical images alone could spend the
# budget, and the burst got the unadapted network (a 640 x 480 burst run beside another job: "0 of
# 30 steps in 25.8 s, its time of 14.3 s spent", benchmarks/results/eval_third_renderer_no_margin.json;
# on the idle machine the same code makes its steps in about a second).
MIN_STEPS = 2 * CHECK_EVERY
# Validate's lens blur (LR px): real cameras blur beyond the pixel's box; a camera that does not
# (the project's own simulator) gets sharpened past the scene (docs/real-bursts.md, "Where it loses").
BLUR_PX = DEFAULT_BLUR_PX
# How far the forward model's blur goes from BLUR_PX towards the lens the classical image undid
# (0: BLUR_PX whatever the lens; 1: the lens undone where it is larger). Through BLUR_PX alone the
# frames of a soft lens read softer than predicted and the adaptation teaches the network to blur:
# with a lens of 0.6 LR px, 0.5 to 0.9 dB below the unadapted network on eight development bursts
# (``training/adapt_dev.py --lens 0.6 --lens-weights 0 ... 1``,
# benchmarks/results/adapt_dev_lens_weight_lens06.json), where 1 is level with it. Development
# bursts of three kinds chose 1, but on the held-out renderers, whose lens estimate mostly
# overstates the lens, 1 kept the classical image's over-sharpening and the learned method lost up
# to 1.1 dB of its lead over classical, gaining 0.26 dB only under the 0.6 LR px lens
# (docs/notes/2026-12-07-adaptation-lens-notes.md): the default stays 0.
# Where the lens estimate doubts (:attr:`~hbis_torch.reconstruct.lens_blur.LensEstimate.doubt`: the
# sharpest edges above FULL_TRUST, so the classical image undid only a share of their blur and
# keeps the rest, a soft lens's or a soft scene's), the weight rises to the doubt: through BLUR_PX
# the adaptation would blur the image further (the frames read softer than predicted), while the
# lens undone predicts them as the classical image stands and leaves the network's own
# sharpening. On development bursts (``training/adapt_dev.py --doubt``,
# benchmarks/results/adapt_dev_[no]doubt_*.json) adapted - classical went from -0.34 to -0.18 dB on
# the mean under a 0.6 LR px lens (four of eight bursts doubted) and from -0.20 to +0.13 under 0.7;
# on a scene itself blurred by 0.5 LR px its three doubted bursts kept less of a lead of several dB
# (+3.33 to +3.08 on the mean). None of the held-out renderers' bursts at their own lens (0.3 LR px)
# has its sharpest edges above FULL_TRUST, nor has any real sequence: none of them changes
# (docs/notes/2026-12-07-lens-doubt-notes.md).
LENS_WEIGHT = 0.0
SEED = 0


@dataclasses.dataclass
class Fold:
    """One group of left-out frames: the classical image of the others and the group's samples.

    Attributes
    ----------
    base : Tensor, shape (1, S^2, H, W)
        The other frames' classical image, space-to-depth (the network's ``base``).
    noise : Tensor, shape (1, 1, H, W)
        The network's noise map.
    points : Tensor, shape (N, 2)
        The group's samples' (u, v) on the reference frame, LR px.
    values, weights : Tensor, shape (N,)
        What the camera recorded there, and each sample's robustness weight.
    features : Tensor, shape (1, width, H, W), optional
        The network's features of ``base`` (what its last convolution sees), once computed.
    """

    base: Tensor
    noise: Tensor
    points: Tensor
    values: Tensor
    weights: Tensor
    features: Tensor | None = None


@dataclasses.dataclass
class Adaptation:
    """What :func:`adapt_refiner` did.

    Attributes
    ----------
    net : torch.nn.Module
        The kept weights (a copy: the network passed in is not changed).
    step : int
        The step whose weights were kept (0: the unadapted network).
    error_before, error_after : float
        The held-out group's weighted mean squared error with the unadapted and the kept network.
    error_classical : float
        The same for the classical image itself.
    steps_taken : int
        The steps made: fewer than asked where the checks stopped finding better weights
        (:data:`PATIENCE`) or the time budget ran out.
    out_of_time : bool
        Whether the time budget stopped the steps.
    seconds : float
        The adaptation's time, the folds' classical images included.
    """

    net: torch.nn.Module
    step: int
    error_before: float
    error_after: float
    error_classical: float
    steps_taken: int = 0
    seconds: float = 0.0
    out_of_time: bool = False


def pytorch_weights(onnx_path) -> Path | None:
    """The PyTorch checkpoint of an ONNX model: ``NAME.pt`` beside ``NAME.onnx`` (or
    ``NAME.int8.onnx``); None where there is none (a model file from elsewhere)."""
    path = Path(onnx_path)
    stem = path.name.removesuffix(".onnx").removesuffix(".int8")
    candidate = path.with_name(stem + ".pt")
    return candidate if candidate.is_file() else None


def load_refiner(checkpoint) -> torch.nn.Module:
    """The network of a training checkpoint (read with ``weights_only``: no pickled code runs)."""
    from hbis_torch.reconstruct.learned.network import build_net

    state = torch.load(checkpoint, map_location="cpu", weights_only=True)
    net = build_net(state["model_config"])
    net.load_state_dict(state["model"])
    return net.eval()


def crop_box(reference_frame: Tensor, side: int = CROP_PX) -> tuple[int, int, int, int]:
    """The window the adaptation works on: (row, col, rows, cols) of a ``side`` x ``side`` LR px
    window (the whole frame where it is smaller), the one with the most gradient energy in the
    reference frame among a grid of candidates half a window apart (a flat sky teaches nothing).

    Parameters
    ----------
    reference_frame : Tensor, shape (H, W)
    side : int
    """
    rows, cols = reference_frame.shape
    h, w = min(rows, side), min(cols, side)
    frame = reference_frame.double()
    energy = (frame[1:, 1:] - frame[:-1, 1:]) ** 2 + (frame[1:, 1:] - frame[1:, :-1]) ** 2
    total = F.pad(energy.cumsum(0).cumsum(1), (1, 0, 1, 0))  # summed-area table, (rows, cols)

    def starts(n, size):
        last = n - size
        return sorted({*range(0, last + 1, max(size // 2, 1)), last})

    def score(y, x):
        y1, x1 = min(y + h - 1, rows - 1), min(x + w - 1, cols - 1)
        return float(total[y1, x1] - total[y, x1] - total[y1, x] + total[y, x])

    best = max(((y, x) for y in starts(rows, h) for x in starts(cols, w)), key=lambda yx: score(*yx))
    return best[0], best[1], h, w


def crop_samples(frames: Tensor, positions: Tensor, weights: Tensor, box) -> tuple[Tensor, Tensor, Tensor]:
    """The frames' pixels in ``box`` (row, col, rows, cols) with their positions moved to the
    window's corner; samples that the motion puts outside the window get weight 0."""
    y0, x0, h, w = box
    f = frames[:, y0:y0 + h, x0:x0 + w].contiguous()
    p = positions[:, y0:y0 + h, x0:x0 + w] - torch.tensor([x0, y0], dtype=positions.dtype)
    outside = (p[..., 0] < -0.5) | (p[..., 0] > w - 0.5) | (p[..., 1] < -0.5) | (p[..., 1] > h - 0.5)
    return f, p.contiguous(), weights[:, y0:y0 + h, x0:x0 + w].masked_fill(outside, 0.0)


def folds_of(count: int, reference: int, usable) -> list[list[int]]:
    """The left-out groups: the usable frames besides the reference, dealt into at most
    :data:`FOLDS` groups (every FOLDS-th frame, so that each spans the burst); [] where fewer
    than two frames are usable (nothing to fit and check on)."""
    others = [k for k in range(count) if k != reference and usable[k]]
    groups = min(FOLDS, len(others))
    return [others[i::groups] for i in range(groups)] if groups >= 2 else []


def make_fold(held: list[int], frames: Tensor, positions: Tensor, weights: Tensor, scale: int,
              noise_params, classical) -> Fold:
    """A :class:`Fold`: the classical image of every frame but ``held`` and ``held``'s samples.

    ``classical(frames, positions, scale, weights)`` -> (S H, S W) Tensor is the classical step
    (:func:`hbis_torch.reconstruct.classical.burst.burst_sr`)."""
    count, rows, cols = frames.shape
    keep = [k for k in range(count) if k not in held]
    image = classical(frames[keep], positions[keep], scale, weights[keep]).numpy()
    base, noise = network_inputs(image, scale, noise_params)
    q, w = positions[held].reshape(-1, 2), weights[held].reshape(-1)
    inside = ((q[:, 0] >= BORDER_PX) & (q[:, 0] <= cols - 1 - BORDER_PX) & (q[:, 1] >= BORDER_PX)
              & (q[:, 1] <= rows - 1 - BORDER_PX) & (w > 0))
    return Fold(torch.from_numpy(base)[None], torch.from_numpy(noise)[None], q[inside].float(),
                frames[held].reshape(-1)[inside].float(), w[inside].float())


def forward_blur(lens_sigma: float, lens_doubt: float = 0.0) -> float:
    """The lens blur (LR px) of the adaptation's forward model when the classical image undid
    ``lens_sigma`` LR px: the larger of :data:`LENS_WEIGHT` and ``lens_doubt`` (the lens
    estimate's :attr:`~hbis_torch.reconstruct.lens_blur.LensEstimate.doubt`, in [0, 1]) of the
    way from :data:`BLUR_PX` to that lens, and :data:`BLUR_PX` where the lens is less."""
    weight = max(LENS_WEIGHT, min(max(float(lens_doubt), 0.0), 1.0))
    # (written so that a weight of 1 gives the lens itself to the bit, and 0 BLUR_PX)
    return max(BLUR_PX, weight * float(lens_sigma) + (1 - weight) * BLUR_PX)


class _Predictor:
    """The forward model on a window of the output: blur by the pixel's box and the lens
    (``blur_px``, LR px), read at the samples' positions (bicubic), as
    :func:`hbis_torch.observation.forward.predict_frame`."""

    def __init__(self, scale: int, blur_px: float = BLUR_PX):
        self.scale = scale
        self.kernel = torch.from_numpy(pixel_kernel(scale, 1.0, blur_px).astype(np.float32))
        # LR px of context a window needs for its samples' predictions to equal the whole
        # image's: the last convolution's 1, the blur's reach and the bicubic read's 2 output px
        self.halo = 1 + math.ceil((len(self.kernel) // 2 + 2) / scale)

    def __call__(self, output: Tensor, points: Tensor) -> Tensor:
        """output (1, 1, S h, S w) of a window whose corner is LR px (0, 0); points (N, 2) in the
        window's LR px -> (N,)."""
        kernel = self.kernel.to(output.dtype)
        r = len(kernel) // 2
        x = F.conv2d(F.pad(output, (r, r, 0, 0), mode="replicate"), kernel.view(1, 1, 1, -1))
        x = F.conv2d(F.pad(x, (0, 0, r, r), mode="replicate"), kernel.view(1, 1, -1, 1))
        rows, cols = output.shape[-2] // self.scale, output.shape[-1] // self.scale
        grid = sample_grid(points, self.scale, rows, cols)
        return F.grid_sample(x, grid.view(1, 1, -1, 2), mode="bicubic", padding_mode="border",
                             align_corners=False).view(-1)


def _halo(net: torch.nn.Module) -> int:
    """Context a window needs on each side for its centre to equal the whole image's, LR px."""
    return getattr(getattr(net, "architecture", None), "halo", TILE_HALO)


def _window(fold: Fold, y0: int, x0: int, size: tuple[int, int], halo: int):
    """The fold cut to an inner window (rows y0.., cols x0.., ``size`` LR px) with ``halo`` px of
    context: (base, features, the inner window's samples' points in the cut's px, their values
    and weights, the inner window's corner (row, col) in the cut, LR px)."""
    rows, cols = fold.base.shape[-2:]
    ya, xa = max(0, y0 - halo), max(0, x0 - halo)
    yb, xb = min(rows, y0 + size[0] + halo), min(cols, x0 + size[1] + halo)
    u, v = fold.points[:, 0], fold.points[:, 1]
    inside = (u >= x0) & (u <= x0 + size[1] - 1) & (v >= y0) & (v <= y0 + size[0] - 1)
    points = fold.points[inside] - torch.tensor([xa, ya], dtype=torch.float32)
    return (fold.base[..., ya:yb, xa:xb], fold.features[..., ya:yb, xa:xb], points, fold.values[inside],
            fold.weights[inside], (y0 - ya, x0 - xa))


def adapt_refiner(net: torch.nn.Module, frames: Tensor, positions: Tensor, weights: Tensor, scale: int,
                  noise_params: tuple[float, float], reference: int, classical, *, steps: int = STEPS,
                  seed: int = SEED, on_step=None, budget_s: float | None = None,
                  crop: int = CROP_PX, patience: int | None = PATIENCE,
                  min_steps: int | None = None, lens_sigma: float = 0.0, lens_doubt: float = 0.0) -> Adaptation | None:
    """Fine-tune a copy of ``net``'s last convolution to predict the burst's left-out frames (the module's recipe).

    Parameters
    ----------
    net : HbisSRNet
        The refiner for ``scale`` (not changed).
    frames : Tensor, shape (F, H, W), float32 in [0, 1]
        The brightness-corrected frames.
    positions : Tensor, shape (F, H, W, 2), float64, or BurstPositions
        Each sample's (u, v) on the reference frame, LR px (only the window's are read).
    weights : Tensor, shape (F, H, W), float32 or float64 in [0, 1]
        The robustness weights (0: a frame left out).
    scale : int
        S.
    noise_params : (float, float)
        The frames' noise (a, b).
    reference : int
    classical : callable
        ``classical(frames, positions, scale, weights)`` -> (S H, S W) Tensor.
    steps : int
        Adam steps at most.
    seed : int
        Seeds the windows' draw: the same burst, the same result (unless the budget stops it).
    on_step : callable, optional
        Called after each step (a progress bar's ``update``).
    budget_s : float, optional
        Seconds the whole adaptation may take (folds included): no step after the first
        ``min_steps`` starts after them. None: all ``steps``.
    crop : int
        Side of the window the adaptation works on, LR px (:func:`crop_box`).
    patience : int, optional
        Stop once this many checks in a row found no better weights (:data:`PATIENCE`; None: never).
    min_steps : int, optional
        Steps made whatever the clock says (default :data:`MIN_STEPS`).
    lens_sigma, lens_doubt : float
        The lens the classical image undoes, LR px, and the lens estimate's doubt, which
        :func:`forward_blur` reads.

    Returns
    -------
    Adaptation or None
        None where fewer than two frames besides the reference carry weight in the window.
    """
    started = time.perf_counter()
    min_steps = MIN_STEPS if min_steps is None else min_steps
    frames, positions, weights = crop_samples(frames, positions, weights, crop_box(frames[reference], crop))
    usable = [bool(weights[k].sum() > 0) for k in range(len(frames))]
    groups = folds_of(len(frames), reference, usable)
    if not groups:
        return None
    folds = [make_fold(g, frames, positions, weights, scale, noise_params, classical) for g in groups]
    with torch.no_grad():
        for fold in folds:
            fold.features = net.features(fold.base, fold.noise)
    check, train = folds[0], folds[1:]
    tail = copy.deepcopy(net.tail).train()
    predict = _Predictor(scale, forward_blur(lens_sigma, lens_doubt))
    halo = predict.halo
    rows, cols = check.base.shape[-2:]
    size = (min(rows, WINDOW_PX), min(cols, WINDOW_PX))
    generator = torch.Generator().manual_seed(seed)

    def output(layer, base: Tensor, features: Tensor) -> Tensor:
        return F.pixel_shuffle(base + layer(features), scale)

    # the held-out group is scored on one fixed window (the centre; the whole window up to
    # 2 x WINDOW_PX): the same samples at every check
    check_size = (min(rows, 2 * WINDOW_PX), min(cols, 2 * WINDOW_PX))
    check_window = _window(check, (rows - check_size[0]) // 2, (cols - check_size[1]) // 2, check_size, halo)

    def error(layer) -> float:
        base, features, points, values, w, _ = check_window
        with torch.no_grad():
            out = F.pixel_shuffle(base, scale) if layer is None else output(layer, base, features)
            return float(((predict(out, points) - values) ** 2 * w).sum() / w.sum().clamp_min(1e-12))

    with torch.no_grad():  # the unadapted network's output, which the anchor holds the adapted one near
        anchors = [output(net.tail, fold.base, fold.features) for fold in train]
    before = best_error = error(net.tail)
    best_state, best_step, taken, out_of_time = None, 0, 0, False
    optimiser = Adam(tail.parameters(), lr=LEARNING_RATE)
    for step in range(1, steps + 1):
        if budget_s is not None and step > min_steps and time.perf_counter() - started > budget_s:
            out_of_time = True
            break
        y0 = int(torch.randint(0, rows - size[0] + 1, (1,), generator=generator))
        x0 = int(torch.randint(0, cols - size[1] + 1, (1,), generator=generator))
        optimiser.zero_grad()
        loss = torch.zeros(())
        for fold, anchored in zip(train, anchors):
            base, features, points, values, w, (iy, ix) = _window(fold, y0, x0, size, halo)
            if len(values) == 0:
                continue
            out = output(tail, base, features)
            inner = out[..., iy * scale:(iy + size[0]) * scale, ix * scale:(ix + size[1]) * scale]
            anchor = anchored[..., y0 * scale:(y0 + size[0]) * scale, x0 * scale:(x0 + size[1]) * scale]
            fit = ((predict(out, points) - values) ** 2 * w).sum() / w.sum().clamp_min(1e-12)
            loss = loss + fit + ANCHOR * ((inner - anchor) ** 2).mean()
        if loss.requires_grad:
            loss.backward()
            optimiser.step()
        taken = step
        if step % CHECK_EVERY == 0 or step == steps:
            best_error, best_state, best_step = _keep_better(error(tail), tail, step, best_error, best_state, best_step)
        if on_step is not None:
            on_step()
        if patience is not None and step - best_step >= patience * CHECK_EVERY:
            break
    if out_of_time and taken % CHECK_EVERY:  # stopped by the budget between checks
        best_error, best_state, best_step = _keep_better(error(tail), tail, taken, best_error, best_state, best_step)
    adapted = copy.deepcopy(net)
    if best_state is not None:
        adapted.tail.load_state_dict(best_state)
    return Adaptation(adapted.eval(), best_step, before, best_error, error(None), taken, time.perf_counter() - started,
                      out_of_time)


class Adam:
    """:class:`torch.optim.Adam`'s update with its defaults (betas 0.9 and 0.999, eps 1e-8, no
    weight decay), written out: creating torch's optimiser first imports ``torch._dynamo``, about
    a second, more than half the classical step's time on a 640 x 480 burst. The same steps as
    torch's to float32 rounding (tested)."""

    def __init__(self, params, lr: float, betas: tuple[float, float] = (0.9, 0.999), eps: float = 1e-8):
        self.params = list(params)
        self.lr, self.betas, self.eps, self.count = lr, betas, eps, 0
        self.moments = [(torch.zeros_like(p), torch.zeros_like(p)) for p in self.params]

    def zero_grad(self) -> None:
        for p in self.params:
            p.grad = None

    @torch.no_grad()
    def step(self) -> None:
        self.count += 1
        (b1, b2), t = self.betas, self.count
        for p, (m, v) in zip(self.params, self.moments):
            if p.grad is None:
                continue
            m.mul_(b1).add_(p.grad, alpha=1 - b1)
            v.mul_(b2).addcmul_(p.grad, p.grad, value=1 - b2)
            denominator = (v.sqrt() / math.sqrt(1 - b2**t)).add_(self.eps)
            p.addcdiv_(m, denominator, value=-self.lr / (1 - b1**t))


def _keep_better(now: float, layer, step: int, best_error: float, best_state, best_step: int):
    """(error, weights, step) of the better of ``layer`` now and the best so far."""
    if now < best_error:
        return now, copy.deepcopy(layer.state_dict()), step
    return best_error, best_state, best_step


def refine(net: torch.nn.Module, image: np.ndarray, scale: int, noise_params: tuple[float, float],
           ensemble: int | None = 1) -> np.ndarray:
    """The classical image (S H, S W) refined by a PyTorch network, tiled as onnxruntime's runner
    is (:func:`~hbis_torch.reconstruct.learned.inputs.super_resolve`); float32 in [0, 1]."""
    from hbis_torch.reconstruct.learned.inputs import super_resolve

    halo = _halo(net)

    def infer(base: np.ndarray, noise: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            return net(torch.from_numpy(np.ascontiguousarray(base)), torch.from_numpy(noise)).numpy()

    def run_network(base: np.ndarray, noise: np.ndarray) -> np.ndarray:
        return run_tiled(infer, base, noise, scale, 256, halo)

    return super_resolve(run_network, image, scale, noise_params, "the adapted network", None, ensemble)
