"""Research A/B of network variants: which change is worth a shipped training run?

    python training/variants_ab.py --h 4 --variants a:32:4:0,c:48:6:0 --seconds 330 --batch 64 --out ab.json

Not the shipped training (that is training/train_sr.py, 90 minutes on 2 CPU cores): a quick
comparison, made for a GPU (any device torch finds; CPU works, slowly). Every variant starts from
the same initial weights (seed 0) and trains for the same wall-clock budget on the *same* batches
of the training pool, in turn at each step, so that the variants differ in nothing but the
variant. Then each is scored as training/eval_matrix.py scores the shipped models: on the
validation set, and on the held-out matrix (its conditions x its photographs, the learned method's
path with one pass of the network, as ``eval_matrix.py --ensemble 1``:
:func:`~hbis_torch.reconstruct.learned.inputs.super_resolve` with the band limit, and the
classical image outside the training domain). The shipped model of the same h is scored beside
them ("s").

A variant is ``name:width:blocks:blur[:body]``: the residual body's width and depth, whether the
network is told the lens's blur width lambda F / p (1 / cutoff, LR pixels) as a second
conditioning channel beside the noise map (1) or not (0), and the body's blocks: ``plain`` (the
shipped design, conv 3x3 -> ReLU -> conv 3x3; the default) or ``ir`` (inverted residuals as in
MobileNetV2: conv 1x1 to 4 x width -> ReLU -> depthwise conv 3x3 -> ReLU -> conv 1x1 back, about
half a plain block's multiply-adds at equal width; the ``kind`` of the network's
:class:`~hbis_torch.reconstruct.learned.architecture.Architecture`). The extra input channel starts at zero weight,
so a variant told the blur starts as the same function as the variant without it. Each variant's
multiply-adds per LR pixel are printed and recorded (``macs``).

The pools are simulated by ``--procs`` worker processes (the training pool of train_sr.py's
shipped runs: 320 stacks, seed 0; validation 16 stacks, seed 1), and the held-out cells are
simulated meanwhile; the batches are cut on the device (random crops, the 8 flips/transposes,
either noise model, as :func:`~hbis_torch.training.data.crop_example`). The variants, their format
and their builder are :mod:`hbis_torch.training.variants`; the held-out matrix is
:mod:`hbis_torch.training.heldout`.

Results: docs/learned.md ("Limits"), docs/notes/2026-11-learned-history.md ("What limits the
gain"), benchmarks/results/variants_ab_*.json.
"""

from __future__ import annotations

import argparse
import copy
import math
import sys
import time
from multiprocessing import get_context
from pathlib import Path

import numpy as np
import torch

from hbis_torch.config import FoveaSystem
from hbis_torch.metrics import psnr
from hbis_torch.reconstruct.classical import optics_cutoff
from hbis_torch.reconstruct.learned.domain import outside_domain
from hbis_torch.reconstruct.learned.inputs import NOISE_SCALE, network_inputs, super_resolve
from hbis_torch.reconstruct.learned.method import classical_and_noise
from hbis_torch.training import heldout
from hbis_torch.training.data import build_pool, draw_example, example_seed, training_domain
from hbis_torch.training.export import load_checkpoint
from hbis_torch.training.net import depth_to_space, space_to_depth
from hbis_torch.training.variants import PATCH, VARIANT_FORMAT, macs_per_pixel, make_variant, parse_variants

SHIPPED = Path(__file__).resolve().parents[1] / "hbis_torch" / "models"  # hbis_sr_h{h}.pt, the "s" row


def simulate_example(args):
    """A pool example (:func:`~hbis_torch.training.data.build_pool`) and its
    lens's blur width ``blur`` (LR px), drawn as the example drew its f-number."""
    torch.set_num_threads(1)
    h, size, seed, index = args
    example = build_pool(h, 0, size, seed, [index])[0]
    camera = FoveaSystem().camera
    f_number = draw_example(camera, h, size, example_seed(seed, index)).f_number
    example["blur"] = camera.wavelength_nm * 1e-3 * f_number / camera.pixel_pitch_um
    return example


def simulate_cell(args):
    """One held-out cell of training/eval_matrix.py: the classical image, the noise measured on
    its lattice, the lens cutoff and the truth."""
    torch.set_num_threads(1)
    h, condition, photo, size = args
    stack, truth = heldout.make_stack(heldout.CONDITIONS[condition], photo, h, size, seed=1000 + condition)
    image, params = classical_and_noise(stack, "optics")
    return {"condition": condition, "photo": photo, "image": image, "params": params,
            "cutoff": optics_cutoff(stack.system), "truth": np.asarray(truth, np.float32)}


def parse_args(argv):
    """The command line, checked; (args, variants), or (None, None) after saying what is wrong."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                     formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("--h", type=int, default=4, choices=(2, 4, 7))
    parser.add_argument("--variants", default="a:32:4:0,b:32:4:1",
                        help=f"{VARIANT_FORMAT}, comma-separated")
    parser.add_argument("--seconds", type=float, default=300.0, help="training budget, wall clock, all variants together")
    parser.add_argument("--steps", type=int, default=None, help="stop after this many steps instead (a reproducible budget)")
    parser.add_argument("--batch", type=int, default=64)
    parser.add_argument("--lr", type=float, default=5e-4, help="peak (AdamW, 200 warm-up steps, cosine to 1/20)")
    parser.add_argument("--pool", type=int, default=320, help="training stacks")
    parser.add_argument("--procs", type=int, default=16, help="processes simulating the pools and cells")
    parser.add_argument("--cells", type=int, default=None, help="only the first N held-out cells (a smoke test)")
    parser.add_argument("--val", type=int, default=16, help="validation stacks")
    parser.add_argument("--out", type=Path, required=True, help="JSON of the validation curves and every cell")
    args = parser.parse_args(argv)
    if args.out.exists():
        print(f"variants_ab: {args.out} exists; choose another --out", file=sys.stderr)
        return None, None
    variants = parse_variants(args.variants)
    if variants is None:
        print(f"variants_ab: --variants must be {VARIANT_FORMAT},..., got {args.variants!r}",
              file=sys.stderr)
        return None, None
    if len({v[0] for v in variants} | {"s"}) != len(variants) + 1:
        print("variants_ab: variant names must differ from each other and from 's' (the shipped model)", file=sys.stderr)
        return None, None
    return args, variants


class Crops:
    """Random training crops cut on the device from the training pool, as train_sr.py's batches.

    Parameters
    ----------
    train : list of dict
        Pool examples (:func:`simulate_example`).
    h : int
    batch : int
        Crops per batch.
    dev : torch.device
    """

    def __init__(self, train: list[dict], h: int, batch: int, dev: torch.device):
        self.h, self.batch_size, self.dev = h, batch, dev
        self.images = torch.tensor(np.stack([e["base"] for e in train]), device=dev)  # (N, h S, h S)
        self.truths = torch.tensor(np.stack([e["truth"] for e in train]), device=dev)
        self.noises = torch.tensor(np.stack([e["noise"] for e in train]), device=dev)  # (N, 2, 2): (a, b) of each noise model
        self.blurs = torch.tensor([e["blur"] for e in train], device=dev, dtype=torch.float32)
        self.count, self.side = self.images.shape[0], self.images.shape[1] // h
        self.generator = torch.Generator(device=dev)
        self.generator.manual_seed(0)

    def randint(self, high):
        return torch.randint(high, (self.batch_size,), generator=self.generator, device=self.dev)

    def batch(self):
        """base (B, h^2, P, P), noise (B, 1, P, P), blur (B, 1, P, P), truth (B, 1, hP, hP)."""
        h, dev, out_side = self.h, self.dev, self.h * PATCH
        randint = self.randint
        i, y0, x0, k = (randint(self.count), h * randint(self.side - PATCH + 1), h * randint(self.side - PATCH + 1),
                        randint(8))
        transpose, flip_x, flip_y = (k & 4) > 0, (k & 1) > 0, (k & 2) > 0  # as hbis_torch.training.data.dihedral
        r = torch.arange(out_side, device=dev)
        rows = torch.where(flip_y[:, None], out_side - 1 - r, r)
        cols = torch.where(flip_x[:, None], out_side - 1 - r, r)
        t = transpose[:, None, None]
        ys = torch.where(t, y0[:, None, None] + cols[:, None, :], y0[:, None, None] + rows[:, :, None])
        xs = torch.where(t, x0[:, None, None] + rows[:, :, None], x0[:, None, None] + cols[:, None, :])
        image, truth = self.images[i[:, None, None], ys, xs], self.truths[i[:, None, None], ys, xs]
        ab = self.noises[i, randint(2)]
        base = space_to_depth(image[:, None], h)
        level = base.mean(1, keepdim=True).clamp(0, 1)  # as network_inputs
        noise = NOISE_SCALE * torch.sqrt(ab[:, 0, None, None, None] * level + ab[:, 1, None, None, None])
        return base, noise, self.blurs[i][:, None, None, None].expand(-1, 1, PATCH, PATCH), truth[:, None]


class Variants:
    """The variants' networks on the device, each told the blur or not.

    Parameters
    ----------
    variants : list of (name, width, blocks, blur, body)
        :func:`~hbis_torch.training.variants.parse_variants`.
    h : int
    dev : torch.device
    """

    def __init__(self, variants, h: int, dev: torch.device):
        self.models = {name: make_variant(h, width, blocks, blur, body).to(dev)
                       for name, width, blocks, blur, body in variants}
        self.told_blur = {name: blur for name, _, _, blur, _ in variants}

    def forward(self, k, base, noise, blur):
        """Variant ``k`` on (B, h^2, H, W), (B, 1, H, W), (B, 1, H, W) -> (B, 1, hH, hW)."""
        return self.models[k](base, torch.cat((noise, blur), 1) if self.told_blur[k] else noise)

    def add_shipped(self, h: int, dev: torch.device) -> None:
        """The shipped model of factor ``h`` as variant "s" (not told the blur)."""
        shipped, _ = load_checkpoint(SHIPPED / f"hbis_sr_h{h}.pt")
        self.models["s"] = shipped.to(dev).eval()
        self.told_blur["s"] = False


def validation_set(val: list[dict], h: int, dev: torch.device) -> list[tuple]:
    """Each validation example whole: (base, noise, blur map, truth) tensors on the device."""
    val_set = []
    for e in val:
        base, noise = (torch.tensor(a[None], device=dev) for a in network_inputs(e["base"], h, e["noise"][0]))
        val_set.append((base, noise, torch.full_like(noise, e["blur"]), torch.tensor(e["truth"][None, None], device=dev)))
    return val_set


def train(variants: Variants, crops: Crops, val_set: list[tuple], args) -> tuple[list[dict], dict, float, int]:
    """Train every variant on the same batches, in turn at each step, for the budget of ``args``.

    Returns
    -------
    history : list of dict
        Every 1000 steps and at the end: step, seconds, each variant's validation PSNR (dB).
    best : dict
        Each variant's best validation PSNR and its weights then (also loaded into the model).
    classical_val : float
        The classical image's validation PSNR (dB).
    steps : int
    """
    h, models = crops.h, variants.models
    optimizers = {k: torch.optim.AdamW(m.parameters(), lr=args.lr, weight_decay=1e-4) for k, m in models.items()}

    @torch.no_grad()
    def validate(k):
        models[k].eval()
        value = float(np.mean([psnr(variants.forward(k, b, n, bl).clamp(0, 1), t) for b, n, bl, t in val_set]))
        models[k].train()
        return value

    classical_val = float(np.mean([psnr(depth_to_space(b, h), t) for b, _, _, t in val_set]))
    history, best = [], {k: (-math.inf, None) for k in models}
    step, started = 0, time.time()
    while True:
        progress = step / args.steps if args.steps else (time.time() - started) / args.seconds
        if step % 1000 == 0 or progress >= 1:
            record = {"step": step, "s": time.time() - started, **{k: validate(k) for k in models}}
            history.append(record)
            for k in models:
                if record[k] > best[k][0]:
                    best[k] = (record[k], copy.deepcopy(models[k].state_dict()))
            print(f"step {step} {record['s']:.0f} s: val " + " ".join(f"{k} {record[k]:.3f}" for k in models)
                  + f" (classical {classical_val:.3f})", flush=True)
        if progress >= 1:
            break
        lr = args.lr * min(1, (step + 1) / 200) * (0.05 + 0.95 * 0.5 * (1 + math.cos(math.pi * progress)))
        base, noise, blur, truth = crops.batch()
        reference = (depth_to_space(base, h) - truth).square().mean(dim=(1, 2, 3))
        for k in models:
            for group in optimizers[k].param_groups:
                group["lr"] = lr
            mse = (variants.forward(k, base, noise, blur) - truth).square().mean(dim=(1, 2, 3))
            loss = (torch.log(mse + 1e-5) - torch.log(reference + 1e-5)).mean()  # train_sr.py's "db" loss
            optimizers[k].zero_grad(set_to_none=True)
            loss.backward()
            torch.nn.utils.clip_grad_norm_(models[k].parameters(), 1.0)
            optimizers[k].step()
        step += 1
    for k in models:
        models[k].load_state_dict(best[k][1])
        models[k].eval()
    print(f"trained {step} steps in {time.time() - started:.0f} s; best val "
          + " ".join(f"{k} {best[k][0]:.3f}" for k in best), flush=True)
    return history, best, classical_val, step


@torch.no_grad()
def score_cells(variants: Variants, cells: list[dict], h: int, dev: torch.device) -> list[dict]:
    """Each held-out cell's classical PSNR and each variant's gain over it (dB), as the learned
    method computes it (one pass, the band limit; the classical image outside the training domain)."""
    domain, results = training_domain(), []
    for cell in cells:
        row = {"h": h, "condition": heldout.CONDITIONS[cell["condition"]].name, "photo": cell["photo"],
               "classical_db": heldout.score(cell["image"], cell["truth"], h)}
        for k in variants.models:
            if outside_domain(domain, cell["params"], cell["cutoff"]) is not None:  # the classical image
                row[k] = 0.0
                continue

            def run(base, noise, k=k, blur=1.0 / cell["cutoff"]):
                b = torch.tensor(np.ascontiguousarray(base).reshape(1, h * h, *base.shape[-2:]), device=dev)
                n = torch.tensor(noise[None], device=dev)
                return variants.forward(k, b, n, torch.full_like(n, blur))[0, 0].cpu().numpy()

            image = super_resolve(run, cell["image"], h, cell["params"], cutoff=cell["cutoff"])
            row[k] = heldout.score(image, cell["truth"], h) - row["classical_db"]
        results.append(row)
    return results


def print_table(results: list[dict], variants, macs: dict, h: int) -> None:
    """Learned minus classical per condition (row mean and worst cell) and over all cells."""
    names = ["s"] + [v[0] for v in variants]
    print(f"\nheld-out, h = {h}: learned - classical, dB, row mean (worst cell); s: the shipped model; "
          + "; ".join(f"{n}: width {w}, {b} {body} blocks" + (", told the blur" if blur else "")
                      + f", {macs[n]} MACs/px" for n, w, b, blur, body in variants))
    for condition in heldout.CONDITIONS:
        rows = [r for r in results if r["condition"] == condition.name]
        if rows:
            print(f"{condition.name[:58]:58s} " + "  ".join(
                f"{k} {np.mean([r[k] for r in rows]):+.2f} ({min(r[k] for r in rows):+.2f})" for k in names))
    for k in names:
        deltas = np.array([r[k] for r in results])
        print(f"{k}: mean {deltas.mean():+.3f} dB, worst cell {deltas.min():+.2f}, {(deltas < -0.3).sum()} below -0.3")


def main(argv=None) -> int:
    args, variants = parse_args(argv)
    if args is None:
        return 2
    h = args.h
    pool_roi, val_roi, cell_size = (96, 64, 72) if h < 7 else (64, 48, 48)  # train_sr.py's and eval_matrix.py's
    started_all = time.time()
    workers = get_context("fork").Pool(args.procs)  # forked before any device is touched
    jobs = [(h, c, p, cell_size) for c in range(len(heldout.CONDITIONS)) for p in heldout.PHOTOS]
    train_async = workers.map_async(simulate_example, [(h, pool_roi, 0, i) for i in range(args.pool)], chunksize=4)
    val_async = workers.map_async(simulate_example, [(h, val_roi, 1, i) for i in range(args.val)], chunksize=1)
    cells_async = workers.map_async(simulate_cell, jobs[:args.cells], chunksize=1)  # simulated while training
    train_pool, val = train_async.get(), val_async.get()
    print(f"pools simulated in {time.time() - started_all:.0f} s", flush=True)

    dev = torch.device("cuda" if torch.cuda.is_available() else "cpu")
    torch.backends.cudnn.allow_tf32 = False  # float32 as on the CPU
    torch.backends.cuda.matmul.allow_tf32 = False
    crops = Crops(train_pool, h, args.batch, dev)
    nets = Variants(variants, h, dev)
    history, best, classical_val, step = train(nets, crops, validation_set(val, h, dev), args)
    nets.add_shipped(h, dev)

    cells = cells_async.get()
    workers.close()
    results = score_cells(nets, cells, h, dev)
    macs = {k: macs_per_pixel(m) for k, m in nets.models.items()}
    print_table(results, variants, macs, h)
    record = {"config": {**vars(args), "out": str(args.out), "device": str(dev)}, "steps": step,
              "classical_val_db": classical_val, "best_val_db": {k: best[k][0] for k in best}, "macs": macs,
              "history": history, "cells": results}
    from hbis_torch.provenance import write_results

    write_results(args.out, record, argv=argv)
    print(f"total {time.time() - started_all:.0f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
