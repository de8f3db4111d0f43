"""What a variant of the network costs on this machine: training steps and inference, side by side.

    python benchmarks/bench_variant_cost.py                                  # a:32:4:0 against m:32:8:0:ir
    python benchmarks/bench_variant_cost.py --h 4 --variants a:32:4:0,c:48:6:0 --repeats 9

Variants are written as ``training/variants_ab.py`` writes them (``name:width:blocks:blur[:body]``,
:mod:`hbis_torch.training.variants`,
the first one the reference; ``a:32:4:0`` is the shipped design). For each, in turn and
``--repeats`` rounds after a warm-up, this times on the CPU:

* a training step as ``training/train_sr.py`` takes one (forward, a mean-square loss, backward and
  AdamW) on a batch of ``--batch`` crops of 32 x 32 LR pixels, torch with ``--threads`` threads;
* inference as the learned method runs it: the network exported to ONNX by the shipped exporter
  (:func:`~hbis_torch.training.export.export_model`) and run by
  :meth:`LearnedSR.infer <hbis_torch.reconstruct.learned.LearnedSR.infer>` with each installed
  provider (onnxruntime's CPU kernels, and OpenVINO where installed), on 64 x 64 LR pixels
  (256 x 256 out at h = 4) and on ``--large`` LR pixels.

Prints each variant's multiply-adds per LR pixel and the medians, with the ratios to the first
variant: a design's multiply-adds say little about its time on a CPU, where memory traffic decides.
``--json`` writes the rows. Results: docs/notes/2026-11-learned-history.md ("What limits the gain"),
benchmarks/results/bench_variant_cost.json.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from hbis_torch.training.variants import PATCH, VARIANT_FORMAT, macs_per_pixel, make_variant, parse_variants


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                     formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("--h", type=int, default=4, choices=(2, 4, 7))
    parser.add_argument("--variants", default="a:32:4:0,m:32:8:0:ir",
                        help=f"{VARIANT_FORMAT}, comma-separated; the first is the reference")
    parser.add_argument("--batch", type=int, default=64, help="training crops per step")
    parser.add_argument("--large", type=int, default=500, help="side of the large inference input, LR pixels")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--json", type=Path, default=None, help="write the rows here")
    args = parser.parse_args(argv)
    variants = parse_variants(args.variants)
    if variants is None:
        print(f"bench_variant_cost: --variants must be {VARIANT_FORMAT},..., got {args.variants!r}",
              file=sys.stderr)
        return 2
    if any(blur for _, _, _, blur, _ in variants):
        print("bench_variant_cost: a variant told the blur takes a third input; time it without (blur 0)",
              file=sys.stderr)
        return 2
    if args.json is not None and args.json.exists():
        print(f"bench_variant_cost: {args.json} exists; choose another --json", file=sys.stderr)
        return 2

    from hbis_torch.reconstruct.learned import LearnedSR
    from hbis_torch.training.export import export_model
    from hbis_torch.reconstruct.learned.runtime import available_providers

    torch.set_num_threads(args.threads)
    h, rng = args.h, np.random.default_rng(0)
    crops = (torch.rand(args.batch, h * h, PATCH, PATCH), torch.rand(args.batch, 1, PATCH, PATCH))
    truth = torch.rand(args.batch, 1, h * PATCH, h * PATCH)
    providers = available_providers()
    sides = (64, args.large)
    inputs = {side: (rng.random((1, h * h, side, side), dtype=np.float32),
                     rng.random((1, 1, side, side), dtype=np.float32)) for side in sides}
    cases = [(provider, side) for provider in providers for side in sides]
    models, optimizers, runners = {}, {}, {}
    with tempfile.TemporaryDirectory() as tmp:
        for name, width, blocks, _, body in variants:
            models[name] = make_variant(h, width, blocks, False, body)
            optimizers[name] = torch.optim.AdamW(models[name].parameters(), lr=1e-4)
            path = Path(tmp) / f"{name}.onnx"
            export_model(models[name], path)
            for provider in providers:  # the sessions hold the compiled models: the files can go
                runners[name, provider] = LearnedSR(path, threads=args.threads, provider=provider)

    def train_step(name):
        model = models[name].train()
        loss = (model(*crops) - truth).square().mean()
        optimizers[name].zero_grad(set_to_none=True)
        loss.backward()
        optimizers[name].step()

    timings = {name: {"train": [], **{case: [] for case in cases}} for name in models}
    for round_ in range(args.repeats + 1):  # round 0 warms up
        for name in models:
            start = time.perf_counter()
            train_step(name)
            if round_:
                timings[name]["train"].append(time.perf_counter() - start)
            for provider, side in cases:
                start = time.perf_counter()
                runners[name, provider].infer(*inputs[side])
                if round_:
                    timings[name][provider, side].append(time.perf_counter() - start)

    rows, first = [], variants[0][0]
    medians = {name: {key: statistics.median(values) for key, values in t.items()} for name, t in timings.items()}
    print(f"h = {h}, {args.threads} threads, {args.repeats} rounds; training batch {args.batch} x {PATCH}^2 LR px "
          f"(torch); inference (LearnedSR.infer) on LR sides {sides}; ratios to {first}")
    print(f"{'variant':24s} {'MACs/px':>8s} {'train step':>16s} "
          + " ".join(f"{f'{p} {s}^2':>18s}" for p, s in cases))
    for name, width, blocks, _, body in variants:
        m = medians[name]
        row = {"variant": name, "width": width, "blocks": blocks, "body": body, "macs": macs_per_pixel(models[name]),
               "train_s": m["train"], **{f"infer_{p}_{s}_s": m[p, s] for p, s in cases}}
        rows.append(row)
        ratio = {key: m[key] / medians[first][key] for key in m}
        print(f"{f'{name}: {width} x {blocks} {body}':24s} {row['macs']:8d} "
              f"{m['train']:7.3f} s {ratio['train']:5.2f}x "
              + " ".join(f"{m[case] * 1e3:8.1f} ms {ratio[case]:5.2f}x" for case in cases))
    if args.json is not None:
        from hbis_torch.provenance import write_results

        settings = {k: v for k, v in vars(args).items() if k != "json"}
        write_results(args.json, {"settings": settings, "providers": providers, "rows": rows}, argv=argv)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
