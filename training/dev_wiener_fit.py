"""Development matrix for the Wiener prior's fit (issue 49): the classical burst path's default on the
training simulator, with the prior s^2 / abs(f)^beta fitted by variants of
:func:`~hbis_torch.reconstruct.classical.wiener.fit_spectrum`.

    python training/dev_wiener_fit.py --out benchmarks/results/dev_wiener_fit.json
        [--kinds shift rot object] [--scales 2 3 4] [--frames 8 16] [--seeds 1 2]
        [--variants committed grid05 ...] [--sweep] [--cache DIR]

Development data only (never the held-out renderer's photographs): the training photographs
(:data:`~hbis_torch.training.data.TRAIN_PHOTOS`, less the page and the text) collaged into a
scene of S x 640 by S x 480 output px, a burst of F frames of 640 x 480 by
:func:`~hbis_torch.simulate.burst.simulate_burst` (lens blur 0.3 LR px, noise 1 %, shifts to 2 px;
``rot``: turns to 0.5 degrees besides; ``object``: a fifth-of-the-frame square displaced by
(25, 35) output px in every frame but the reference). Each burst is assembled with
:func:`~hbis_torch.capture.burst.assemble_burst`'s defaults and reconstructed by
``reconstruct(stack, "classical")``; the Wiener filter's input (the lattice image and its
settings) is kept (``--cache``), and each variant of the prior's fit deblurs that same input.
PSNR (scikit-image) against the truth without a border of 4 LR px.

The variants (:data:`VARIANTS`): ``committed`` (the package's own fit_spectrum, whatever it is
now), ``grid25`` (the fit of main before issue 49's beta work: 0.25 steps, least scatter),
``grid05`` (0.05 steps), ``count`` (rings weighted by their frequencies), ``invvar`` (by the
inverse variance of the log of a ring's mean power less the noise), ``whittle`` (the Gaussian
profile likelihood of the rings' mean power, the noise inside the model, not subtracted).
``--sweep`` adds beta fixed at 1.5 .. 4 in steps of 0.25 (s^2 fitted as in grid25): where the
best fixed beta lies.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
KINDS = ("shift", "rot", "object")
SIZE = (640, 480)
BORDER = 4


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", type=Path, required=True, help="results JSON (resumed if it exists)")
    p.add_argument("--kinds", nargs="+", default=list(KINDS), choices=KINDS)
    p.add_argument("--scales", nargs="+", type=int, default=[2, 3, 4])
    p.add_argument("--frames", nargs="+", type=int, default=[8, 16])
    p.add_argument("--seeds", nargs="+", type=int, default=[1, 2])
    p.add_argument("--variants", nargs="+", default=None, help="default: all of VARIANTS")
    p.add_argument("--sweep", action="store_true", help="also beta fixed at 1.5 .. 4 (0.25 steps)")
    p.add_argument("--cache", type=Path, default=Path("/tmp/dev_wiener_fit"),
                   help="where each burst's Wiener input is kept between runs")
    args = p.parse_args(argv)
    bad = [v for v in (args.variants or []) if v not in VARIANTS]
    if bad:
        p.exit(2, f"unknown variant(s) {bad}; known: {sorted(VARIANTS)}\n")
    if any(s < 2 or s > 8 for s in args.scales) or any(f < 2 for f in args.frames):
        p.exit(2, "scales must lie in 2 .. 8 and frames be at least 2\n")
    return args


# --- the fit's variants -----------------------------------------------------------------------

def _rings(power, fx, fy, kernel, shifts, noise2, highest):
    """fit_spectrum's rings: (m, count, clear, S_beta) with S_beta(beta) the model's shape per ring."""
    from hbis_torch.reconstruct.classical import wiener as W

    rows, half = power.shape
    cols = 2 * (half - 1) if half > 1 else 1
    edges = torch.logspace(math.log10(1.5 / max(rows, cols)), math.log10(0.71), 25, dtype=fx.dtype)
    count, total = W._ring_sums(power, fx, fy, edges)
    m = total / count.clamp_min(1)
    stride = max(1, rows * half // 16384)
    pick = torch.arange(0, rows * half, stride)
    ring = W._ring_of(fx[0, pick % half], fy[pick // half, 0], edges)
    inside = (ring >= 0) & (ring < 24)
    pick, sub_ring = pick[inside], ring[inside]
    sub_count = torch.bincount(sub_ring, minlength=24)
    at = [kernel(kx, ky, (pick // half, pick % half)) for kx, ky in shifts]
    k2 = torch.stack([t[0] * t[0] for t in at])
    log_r2 = torch.stack([torch.log(t[3]) for t in at])
    passed = torch.bincount(sub_ring, k2.sum(0), minlength=24) / sub_count.clamp_min(1)
    clear = (count >= 8) & (sub_count >= 1) & (m > 2 * noise2) & (passed > 1e-4 * float(passed.max()))
    if highest is not None:
        clear &= edges[1:] <= highest

    def shape(beta):
        s = (k2 * torch.exp(-0.5 * beta * log_r2)).sum(0)
        return (torch.bincount(sub_ring, s, minlength=24) / sub_count.clamp_min(1)).clamp_min(1e-300)

    return m, count.double(), clear, shape


def _least_scatter(betas, weight=None):
    """A fit choosing beta from ``betas`` by the (weighted) least scatter of log(m - noise) - log S."""
    def fit(m, count, clear, shape, noise2):
        target = (m[clear] - noise2).log()
        w = torch.ones_like(target) if weight is None else weight(m, count, noise2)[clear]
        w = w / w.sum()
        best = None
        for beta in betas:
            gap = target - shape(beta)[clear].log()
            level = float((w * gap).sum())
            scatter = float((w * (gap - level) ** 2).sum())
            if best is None or scatter < best[0]:
                best = (scatter, math.exp(level), beta)
        return best[1], best[2]
    return fit


def _whittle(betas):
    """Profile Gaussian likelihood of the rings' mean power: each ring's mean of count exponential
    powers, model s^2 S + noise; s^2 maximised per beta (a 1-D search in log s^2)."""
    from scipy.optimize import minimize_scalar

    def fit(m, count, clear, shape, noise2):
        mm, cc = m[clear], count[clear]
        best = None
        for beta in betas:
            s = shape(beta)[clear]

            def nll(log_s2):
                model = math.exp(log_s2) * s + noise2
                return float((cc * (model.log() + mm / model)).sum())
            start = float(((mm - noise2).clamp_min(1e-30) / s).log().mean())
            r = minimize_scalar(nll, bounds=(start - 8, start + 8), method="bounded")
            if best is None or r.fun < best[0]:
                best = (r.fun, math.exp(r.x), beta)
        return best[1], best[2]
    return fit


GRID25 = torch.arange(1.5, 4.01, 0.25).tolist()
GRID05 = [round(1.5 + 0.05 * i, 2) for i in range(51)]
VARIANTS = {
    "committed": None,
    "grid25": _least_scatter(GRID25),
    "grid05": _least_scatter(GRID05),
    "count": _least_scatter(GRID05, lambda m, c, n2: c),
    "invvar": _least_scatter(GRID05, lambda m, c, n2: c * ((m - n2) / m).clamp_min(0) ** 2),
    "whittle": _whittle(GRID05),
}


def _fixed(beta):
    return _least_scatter([beta])


def variant_fit(fit):
    """A fit_spectrum replacement running ``fit`` on fit_spectrum's rings (its fallbacks kept)."""
    from hbis_torch.reconstruct.classical import wiener as W
    original = W.fit_spectrum

    def fit_spectrum(power, fx, fy, kernel, shifts, noise2, highest=None):
        m, count, clear, shape = _rings(power, fx, fy, kernel, shifts, noise2, highest)
        if int(clear.sum()) < 3:
            return original(power, fx, fy, kernel, shifts, noise2, highest=highest)
        return fit(m, count, clear, shape, noise2)
    return fit_spectrum


# --- the bursts -------------------------------------------------------------------------------

def make_burst(kind: str, S: int, F: int, seed: int):
    """(truth, frames) of one development burst (the module's docstring)."""
    from hbis_torch.simulate.burst import random_motions, simulate_burst
    from hbis_torch.training.data import TRAIN_PHOTOS
    from hbis_torch.training.handheld_render import collage

    W, H = SIZE
    rng = np.random.default_rng(seed)
    photos = [n for n in TRAIN_PHOTOS if n not in ("page", "text")]
    truth = collage(S * H, S * W, rng, photos=photos)
    motions = random_motions(F, (H, W), rng, max_shift=2.0, max_rotation_deg=0.5 if kind == "rot" else 0.0)
    patch, moving = None, ()
    if kind == "object":
        patch, moving = (S * H // 3, S * W // 3, S * (W // 5), S * 25, S * 35), range(1, F)
    b = simulate_burst(truth, S, motions, noise=0.01, seed=seed, blur_px=0.3, moving_patch=patch,
                       moving_frames=moving)
    return b.truth, b.frames


def score(image, truth, S) -> float:
    from skimage.metrics import peak_signal_noise_ratio
    b = S * BORDER
    image = np.clip(np.asarray(image, dtype=np.float64), 0, 1)
    return float(peak_signal_noise_ratio(truth[b:-b, b:-b], image[b:-b, b:-b], data_range=1.0))


def wiener_input(kind, S, F, seed, cache: Path):
    """The burst's truth, the Wiener filter's input (args, kwargs) of its default reconstruction, the
    blend with the single frame that follows it (:func:`~hbis_torch.reconstruct.burst.reconstruct_burst`),
    that reconstruction's PSNR and the bicubic one's; kept in ``cache``."""
    path = cache / f"{kind}_{S}_{F}_{seed}.pt"
    if path.exists():
        return torch.load(path, weights_only=False)
    from hbis_torch.capture.burst import assemble_burst
    from hbis_torch.reconstruct import burst as B
    from hbis_torch.reconstruct.classical import sr
    from hbis_torch.reconstruct.registry import reconstruct
    from hbis_torch.reconstruct.single_frame import single_frame

    truth, frames = make_burst(kind, S, F, seed)
    stack, _ = assemble_burst(frames, S)
    seen = {}

    def recorder(name, function):
        def recording(*a, **k):
            if name == "call":  # before the call: it overwrites its input
                seen.setdefault("calls", []).append((a[0].clone(), a[1:], dict(k)))
            seen[name] = function(*a, **k)
            return seen[name]
        return recording
    saved = sr.wiener_deblur, B._blend_weight, B.Tally.run_scale, B.single_frame
    sr.wiener_deblur = recorder("call", sr.wiener_deblur)
    B._blend_weight, B.single_frame = recorder("alpha", B._blend_weight), recorder("fallback", B.single_frame)
    B.Tally.run_scale = recorder("run", B.Tally.run_scale)
    try:
        out = reconstruct(stack, "classical")
    finally:
        sr.wiener_deblur, B._blend_weight, B.Tally.run_scale, B.single_frame = saved
    run_scale, fill = seen["run"]
    alpha = seen["alpha"]
    if S <= 2 or float(fill.mean()) < B.RUN_FILL:  # classical_burst.fill_blend_to = 2
        alpha = np.minimum(alpha, fill)
    item = dict(truth=truth.astype(np.float32), call=seen["calls"][-1], calls=len(seen["calls"]), alpha=alpha, fallback=seen["fallback"],
                run_scale=run_scale, scale=S, bicubic=score(seen["fallback"], truth, S))
    item["default"] = score(out, truth, S)
    cache.mkdir(parents=True, exist_ok=True)
    torch.save(item, path)
    return item


def finish(item, image: np.ndarray) -> np.ndarray:
    """The classical image at the run scale blended with the single frame as reconstruct_burst does."""
    from hbis_torch.reconstruct.single_frame import enlarge

    alpha, fallback = item["alpha"], item["fallback"]
    if item["run_scale"] != item["scale"]:
        image, alpha = enlarge(image, fallback.shape[:2]), enlarge(alpha, fallback.shape[:2])
    return np.clip(alpha * np.asarray(image, dtype=np.float32) + (1 - alpha) * fallback, 0, 1)


def deblur_with(item, fit):
    """PSNR and (s2, beta) of the cached Wiener input deblurred with the prior fit ``fit``."""
    from hbis_torch.reconstruct.classical import wiener as W

    image, a, k = item["call"]
    chosen = []
    inner = W.fit_spectrum if fit is None else variant_fit(fit)

    def recording(*args, **kw):
        chosen.append(inner(*args, **kw))
        return chosen[-1]
    saved = W.fit_spectrum
    W.fit_spectrum = recording
    try:
        out = W.wiener_deblur(image.clone(), *a, **k).clamp_(0, 1).to(torch.float32).numpy()
    finally:
        W.fit_spectrum = saved
    return score(finish(item, out), item["truth"].astype(np.float64), item["scale"]), chosen[-1]


def table(cells: dict) -> list[str]:
    """Markdown rows: per burst the bicubic and committed PSNR (dB, the committed beta), each other
    variant's change against committed (its beta), and the best fixed beta's where swept."""
    names = sorted({n for c in cells.values() for n in c if isinstance(c[n], dict) and not n.startswith("beta=")}
                   - {"committed"}, key=list(VARIANTS).index)
    rows = ["| burst | bicubic | committed (beta) | " + " | ".join(names) + " | best fixed beta |",
            "|---" * (len(names) + 4) + "|"]
    for key, c in cells.items():
        base = c["committed"]["psnr"]
        row = [key, f"{c['bicubic']:.2f}", f"{base:.2f} ({c['committed']['beta']:g})"]
        row += [f"{c[n]['psnr'] - base:+.3f} ({c[n]['beta']:g})" if n in c else "" for n in names]
        fixed = [(c[n]["psnr"], c[n]["beta"]) for n in c if n.startswith("beta=")]
        row.append(f"{max(fixed)[0] - base:+.3f} ({max(fixed)[1]:g})" if fixed else "")
        rows.append("| " + " | ".join(row) + " |")
    return rows


def main(argv=None) -> int:
    args = parse_args(argv)
    from hbis_torch.provenance import write_results

    argv = sys.argv[1:] if argv is None else list(argv)
    results = json.loads(args.out.read_text()) if args.out.exists() else {}
    cells = results.setdefault("cells", {})
    names = args.variants or list(VARIANTS)
    fits = {n: VARIANTS[n] for n in names}
    if args.sweep:
        fits.update({f"beta={b:g}": _fixed(b) for b in GRID25})
    for kind in args.kinds:
        for S in args.scales:
            for F in args.frames:
                for seed in args.seeds:
                    key = f"{kind}|S={S}|F={F}|seed={seed}"
                    cell = cells.setdefault(key, {})
                    todo = [n for n in fits if n not in cell]
                    if not todo:
                        continue
                    t = time.time()
                    item = wiener_input(kind, S, F, seed, args.cache)
                    cell.update(bicubic=item["bicubic"], default=item["default"])
                    for name in todo:
                        psnr, (s2, beta) = deblur_with(item, fits[name])
                        cell[name] = dict(psnr=round(psnr, 4), beta=round(float(beta), 3), s2=float(s2))
                    write_results(args.out, results, argv=argv)
                    print(key, {n: (cell[n]["psnr"], cell[n]["beta"]) for n in todo}, f"{time.time() - t:.0f} s",
                          flush=True)
    # the commands that filled the file (each run adds its own; a run with nothing left to do too)
    command = " ".join(["python", "training/dev_wiener_fit.py", *argv])
    results["commands"] = list(dict.fromkeys([*results.get("commands", []), command]))
    results["table"] = table(cells)
    write_results(args.out, results, argv=argv)
    print("\n".join(results["table"]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
