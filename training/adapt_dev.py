"""Development bursts for the learned method's test-time adaptation: where its settings are chosen.

    python training/adapt_dev.py --out benchmarks/results/adapt_dev.json
        [--generators sim cam] [--seeds 0 1 2 3] [--size 640x480] [--frames 16] [--scale 2]
        [--variants 30:1e-3 40:1e-3 30:1e-3:2] [--lens 0.6] [--scene-blur 0.3] [--lens-weights 0 1] [--doubt]

Never the held-out renderer (:mod:`hbis_torch.training.handheld_render`) nor its photographs:
the scenes are the training photographs (:data:`hbis_torch.training.data.TRAIN_PHOTOS`) in a
grid of 192 px tiles, each turned by a multiple of 90 degrees (one photograph pixel one output
pixel). Two cameras:

* ``sim``: the training simulator's forward model (:func:`hbis_torch.simulate.burst.simulate_burst`:
  similarity motions, lens 0.3 LR px, Gaussian noise 1 %, 8 bits);
* ``cam``: a camera model of this script's own: the scene twice as fine as the output grid,
  homographies (turns to 1 degree, perspective, shifts to 2 px), a Gaussian lens of 0.2 to 0.5 LR
  px, each pixel the mean of a 3 x 3 quadrature of its footprint, Poisson-Gaussian noise (3000 to
  20000 e- full well, 3 e- read), 12 bits.

Each burst (``--frames``, 16 by default; ``--scale``, 2 by default) is assembled as ``hbis assemble
--burst`` does; its classical image (:func:`~hbis_torch.reconstruct.classical.burst.burst_sr`,
undoing the lens blur the classical method measures), the shipped network's refinement of it,
and the network adapted with each variant (``STEPS:LEARNING_RATE[:PATIENCE]`` of
:func:`~hbis_torch.reconstruct.learned.adapt.adapt_refiner`, no time budget) are scored against the truth
(PSNR without 4 LR px of border), with their seconds (torch on one thread).

``--lens`` fixes both cameras' lens, ``--scene-blur`` blurs the scene itself (a soft scene, whose
softness the lens estimate reads as lens), and ``--lens-weights`` tries each variant with each
:data:`~hbis_torch.reconstruct.learned.adapt.LENS_WEIGHT` (how far the adaptation's forward
model blurs by the lens the classical image undid); ``--doubt`` also hands it the lens estimate's
doubt, as the learned method does (:attr:`~hbis_torch.reconstruct.lens_blur.LensEstimate.doubt`:
the weight is then at least the doubt).
"""

from __future__ import annotations

import argparse
import functools
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def dev_scene(height: int, width: int, rng: np.random.Generator, tile: int = 192) -> np.ndarray:
    """Training photographs in a grid of ``tile`` px tiles, (height, width) float64 in [0, 1]."""
    from hbis_torch.simulate.rasters import photo
    from hbis_torch.training.data import TRAIN_PHOTOS

    out = np.empty((height, width))
    for y in range(0, height, tile):
        for x in range(0, width, tile):
            p = np.rot90(photo(str(rng.choice(TRAIN_PHOTOS))), int(rng.integers(4)))
            th, tw = min(tile, height - y), min(tile, width - x)
            if p.shape[0] < th or p.shape[1] < tw:
                p = np.tile(p, (2, 2))
            y0, x0 = rng.integers(0, p.shape[0] - th + 1), rng.integers(0, p.shape[1] - tw + 1)
            out[y:y + th, x:x + tw] = p[y0:y0 + th, x0:x0 + tw]
    return out


def _homographies(count: int, width: int, height: int, rng: np.random.Generator) -> np.ndarray:
    """(count, 3, 3) frame px -> reference px: turns to 1 degree, zoom 0.3 %, perspective moving
    a corner up to about 1.5 px, shifts to 2 px; frame 0 the identity."""
    cx, cy = (width - 1) / 2, (height - 1) / 2
    centre = np.array([[1, 0, cx], [0, 1, cy], [0, 0, 1.0]])
    out = [np.eye(3)]
    for _ in range(count - 1):
        a, s = np.deg2rad(rng.uniform(-1, 1)), 1 + rng.uniform(-0.003, 0.003)
        turn = np.array([[s * np.cos(a), -s * np.sin(a), 0], [s * np.sin(a), s * np.cos(a), 0], [0, 0, 1]])
        tilt = np.eye(3)
        tilt[2, :2] = rng.uniform(-1, 1, 2) * 1.5 / (width * max(cx, cy))
        shift = np.eye(3)
        shift[:2, 2] = rng.uniform(-2, 2, 2)
        out.append(shift @ centre @ tilt @ turn @ np.linalg.inv(centre))
    return np.stack(out)


def camera_burst(seed: int, scale: int, count: int, width: int, height: int, lens: float | None = None,
                 scene_blur: float = 0.0, first_blur: float = 0.0):
    """The ``cam`` burst (module docstring; ``lens``, LR px, in place of the drawn one; the scene
    itself blurred by ``scene_blur`` LR px; the first frame, the reference, out of focus by a
    Gaussian of ``first_blur`` LR px on top of the lens): (frames (F, H, W) uint16, truth (S H,
    S W), bits)."""
    from scipy.ndimage import gaussian_filter, map_coordinates, zoom

    rng = np.random.default_rng(77_000 + seed)
    blur, well = rng.uniform(0.2, 0.5), float(np.exp(rng.uniform(np.log(3000), np.log(20000))))
    blur = blur if lens is None else lens
    fine, margin, bits = 2, 8, 12  # scene px per output px; LR px of scene beyond the reference
    scene = dev_scene(scale * (height + 2 * margin), scale * (width + 2 * margin), rng)
    scene = zoom(gaussian_filter(scene, scene_blur * scale) if scene_blur else scene, fine, order=3)
    # the scene through the lens, before the pixels integrate it
    seen = gaussian_filter(scene.clip(0, 1), blur * scale * fine, mode="nearest")
    m = margin * scale * fine
    core = scene.clip(0, 1)[m:m + height * scale * fine, m:m + width * scale * fine]
    truth = core.reshape(height * scale, fine, width * scale, fine).mean((1, 3))
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    offsets = (np.arange(3) + 0.5) / 3 - 0.5
    frames = []
    for k, motion in enumerate(_homographies(count, width, height, rng)):
        through = seen
        if k == 0 and first_blur:
            through = gaussian_filter(scene.clip(0, 1), np.hypot(blur, first_blur) * scale * fine, mode="nearest")
        mean = np.zeros((height, width))
        for dy in offsets:
            for dx in offsets:
                x, y, w = motion @ np.stack(((u + dx).ravel(), (v + dy).ravel(), np.ones(u.size)))
                fx = ((x / w).reshape(height, width) + margin + 0.5) * scale * fine - 0.5
                fy = ((y / w).reshape(height, width) + margin + 0.5) * scale * fine - 0.5
                mean += map_coordinates(through, [fy, fx], order=1, mode="nearest") / 9
        electrons = rng.poisson(np.clip(mean, 0, None) * well) + rng.normal(0, 3.0, mean.shape)
        frames.append(np.clip(np.round(electrons / well * (2**bits - 1)), 0, 2**bits - 1).astype(np.uint16))
    return np.stack(frames), truth.astype(np.float32), bits


def simulator_burst(seed: int, scale: int, count: int, width: int, height: int, lens: float | None = None,
                    scene_blur: float = 0.0):
    """The ``sim`` burst (module docstring; ``lens``, LR px, in place of 0.3; the scene itself
    blurred by ``scene_blur`` LR px): (frames (F, H, W) uint8, truth (S H, S W), 8)."""
    from scipy.ndimage import gaussian_filter

    from hbis_torch.simulate.burst import random_motions, simulate_burst

    rng = np.random.default_rng(10_000 + seed)
    truth = dev_scene(scale * height, scale * width, rng)
    truth = gaussian_filter(truth, scene_blur * scale) if scene_blur else truth
    motions = random_motions(count, (height, width), rng, max_shift=2.0, max_rotation_deg=1.0, max_zoom=0.005)
    burst = simulate_burst(truth, scale, motions, noise=0.01, seed=int(rng.integers(2**31)),
                           blur_px=0.3 if lens is None else lens)
    return burst.frames, burst.truth, 8


def run_burst(generator: str, seed: int, args) -> dict:
    """One burst's scores and seconds (module docstring)."""
    import torch
    from skimage.metrics import peak_signal_noise_ratio

    from hbis_torch.capture.burst import assemble_burst
    from hbis_torch.reconstruct.burst import burst_samples
    from hbis_torch.reconstruct.classical.burst import burst_sr
    from hbis_torch.reconstruct.learned import adapt
    from hbis_torch.reconstruct.lens_blur import burst_lens
    from hbis_torch.reconstruct.learned.inputs import estimate_noise_params
    from hbis_torch.reconstruct.learned.runtime import shipped_model_path

    make = camera_burst if generator == "cam" else simulator_burst
    scale = args.scale
    frames, truth, bits = make(seed, scale, args.frames, args.width, args.height, args.lens, args.scene_blur)
    stack, _ = assemble_burst(frames, scale, bit_depth=bits)
    f, positions, _, weights = burst_samples(stack)
    noise = estimate_noise_params(f.numpy())
    # the lens blur the classical method measures and undoes, as the learned method's classical step
    estimate = burst_lens(f, positions, weights, stack.reference_index)
    lens_sigma, lens_doubt = estimate.sigma, estimate.doubt if args.doubt else 0.0
    classical = functools.partial(burst_sr, lens_sigma=lens_sigma)
    b = 4 * scale  # 4 LR px

    def score(image):
        return round(float(peak_signal_noise_ratio(truth[b:-b, b:-b], np.clip(image, 0, 1)[b:-b, b:-b],
                                                   data_range=1.0)), 3)

    t = time.perf_counter()
    image = classical(f, positions, scale, weights).numpy()
    out = {"generator": generator, "seed": seed, "lens_undone": round(lens_sigma, 3),
           "lens_sharpest": None if estimate.sharpest is None else round(estimate.sharpest, 3),
           "lens_doubt": round(lens_doubt, 3), "classical_db": score(image),
           "classical_s": round(time.perf_counter() - t, 3)}
    net = adapt.load_refiner(shipped_model_path(scale).with_suffix(".pt"))
    t = time.perf_counter()
    out["unadapted_db"] = score(adapt.refine(net, image, scale, noise))
    out["refine_s"] = round(time.perf_counter() - t, 3)
    shipped = adapt.LEARNING_RATE, adapt.LENS_WEIGHT
    for variant, weight in ((v, w) for v in args.variants for w in args.lens_weights):
        steps, rate, *patience = variant.split(":")
        adapt.LEARNING_RATE, adapt.LENS_WEIGHT = float(rate), weight
        try:
            done = adapt.adapt_refiner(net, f, positions, weights, scale, noise, stack.reference_index, classical,
                                       steps=int(steps), patience=int(patience[0]) if patience else None,
                                       lens_sigma=lens_sigma, lens_doubt=lens_doubt)
        finally:
            adapt.LEARNING_RATE, adapt.LENS_WEIGHT = shipped
        out[_key(variant, weight, args)] = {"db": score(adapt.refine(done.net, image, scale, noise)),
                                            "kept_step": done.step, "seconds": round(done.seconds, 3),
                                            "steps_taken": done.steps_taken}
    return out


def _key(variant: str, weight: float, args) -> str:
    """A row's key for ``variant`` with the lens weight ``weight``: the variant alone where only
    one weight is tried."""
    return variant if len(args.lens_weights) == 1 else f"{variant}@{weight:g}"


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", type=Path, required=True, help="results JSON (a .md beside it)")
    p.add_argument("--generators", nargs="+", default=["sim", "cam"], choices=["sim", "cam"])
    p.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2, 3])
    p.add_argument("--size", default="640x480")
    p.add_argument("--frames", type=int, default=16)
    p.add_argument("--scale", type=int, default=2, choices=[2, 3, 4], help="S (default 2)")
    p.add_argument("--variants", nargs="+", default=["30:1e-3"],
                   help="STEPS:LEARNING_RATE[:PATIENCE] (default 30:1e-3; PATIENCE: stop after that many checks "
                        "without better weights)")
    p.add_argument("--lens", type=float,
                   help="the cameras' lens blur, LR px (default: sim 0.3, cam drawn from 0.2 to 0.5)")
    p.add_argument("--scene-blur", type=float, default=0.0,
                   help="blur the scene itself by this many LR px (a soft scene, whose edges the lens estimate "
                        "reads as lens)")
    p.add_argument("--lens-weights", nargs="+", type=float,
                   help="adapt.LENS_WEIGHT values to try with each variant (default: the shipped one; 0: the "
                        "forward model blurs by adapt.BLUR_PX alone, the default; 1: by the lens undone)")
    p.add_argument("--doubt", action="store_true",
                   help="hand the adaptation the lens estimate's doubt, as the learned method does (its forward "
                        "model then blurs towards the lens undone where the sharpest edges are too soft for all of "
                        "their blur to be undone); without it, only --lens-weights decides, as before the doubt "
                        "existed")
    args = p.parse_args(argv)
    try:
        args.width, args.height = (int(v) for v in args.size.lower().split("x"))
        for v in args.variants:
            int(v.split(":")[0]), float(v.split(":")[1]), [int(k) for k in v.split(":")[2:3]]
    except (ValueError, IndexError):
        print(f"adapt_dev: --size is WxH and --variants STEPS:RATE[:PATIENCE], got {args.size!r} {args.variants}", file=sys.stderr)
        return 2
    if not args.out.parent.is_dir():
        print(f"adapt_dev: the folder of --out {args.out} does not exist", file=sys.stderr)
        return 2
    if args.lens is not None and not 0 <= args.lens <= 2 or not 0 <= args.scene_blur <= 2:
        print(f"adapt_dev: --lens and --scene-blur take 0 to 2 LR px, got {args.lens} and {args.scene_blur}",
              file=sys.stderr)
        return 2
    if args.lens_weights is None:
        from hbis_torch.reconstruct.learned import adapt

        args.lens_weights = [adapt.LENS_WEIGHT]
    import torch

    from hbis_torch.provenance import write_results

    torch.set_num_threads(1)
    rows = []
    for generator in args.generators:
        for seed in args.seeds:
            rows.append(run_burst(generator, seed, args))
            print(rows[-1], flush=True)
    summary = {"classical_db": float(np.mean([r["classical_db"] for r in rows])),
               "unadapted_minus_classical_db": float(np.mean([r["unadapted_db"] - r["classical_db"] for r in rows]))}
    for v in (_key(v, w, args) for v in args.variants for w in args.lens_weights):
        gains = [r[v]["db"] - r["classical_db"] for r in rows]
        summary[v] = {"minus_classical_mean_db": float(np.mean(gains)), "minus_classical_worst_db": float(min(gains)),
                      "seconds_over_classical_mean": float(np.mean([r[v]["seconds"] / r["classical_s"] for r in rows]))}
    write_results(args.out, {"settings": {k: getattr(args, k) for k in ("generators", "seeds", "size", "frames",
                                                                          "scale", "variants", "lens", "scene_blur",
                                                                          "lens_weights", "doubt")},
                             "rows": rows, "summary": summary}, argv=argv)
    print(summary)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
