"""Score a checkpoint on the benchmark's photograph stacks (a development aid, torch only).

    python training/eval_photos.py training/runs/sr_h4/model.pt [--sizes 128 256 full]

Simulates (once, cached in training/runs/cache) exactly the photograph stacks that
benchmarks/bench_learned.py uses for the checkpoint's h (same scenes, ROIs and seeds:
hbis_torch.simulate.cases) and prints the network's PSNR on each, next to the classical
method's (computed once per version of hbis_torch.reconstruct.classical and cached too, written
atomically).
The photographs are never trained on; this only saves rerunning the whole benchmark to
compare training runs.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

from hbis_torch.metrics import psnr
from hbis_torch.config import FoveaSystem
from hbis_torch.io_utils import atomic_path
from hbis_torch.simulate import sample_positions
from hbis_torch.simulate.cases import make_stack, roi_for, scene_cases
from hbis_torch.reconstruct import classical as classical_module
from hbis_torch.reconstruct.classical import classical_sr, optics_cutoff
from hbis_torch.reconstruct.learned import run_tiled, super_resolve
from hbis_torch.reconstruct.learned.net import HbisSRNet

REPO = Path(__file__).resolve().parents[1]  # the checkout: default cache folder


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("checkpoint", type=Path)
    parser.add_argument("--sizes", nargs="+", default=["128", "256"])
    parser.add_argument("--cache", type=Path, default=REPO / "training" / "runs" / "cache")
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    ckpt = torch.load(args.checkpoint, map_location="cpu", weights_only=False)
    model = HbisSRNet(**ckpt["model_config"])
    model.load_state_dict(ckpt["model"])
    model.eval()
    h, system = model.h, FoveaSystem()
    # The cached classical PSNRs belong to one version of the classical method.
    version = classical_module.source_version()[:8]
    means = {}
    for size_arg in args.sizes:
        size = None if size_arg == "full" else int(size_arg)
        for i, (kind, scene) in enumerate(scene_cases(size)):
            roi = roi_for(system, size, i)
            path = args.cache / f"bench_h{h}_{size_arg}_{scene}_{i}_classical{version}.npz"
            if not path.exists():
                stack, truth = make_stack(system, h, roi, scene, 1000 + i)
                frames = stack.to_float()
                positions = sample_positions(system, stack.phases_deg, stack.reference_index, stack.roi)
                classical = classical_sr(frames, positions, h, cutoff=optics_cutoff(system), fill_factor=1.0).numpy()
                with atomic_path(path) as tmp, open(tmp, "wb") as out:
                    np.savez(out, frames=frames.numpy(), positions=positions.numpy(), truth=truth,
                             classical=np.float64(psnr(classical, truth)))
            data = np.load(path)

            def infer(a, b):
                with torch.inference_mode():
                    return model(torch.from_numpy(a), torch.from_numpy(b)).numpy()

            image = super_resolve(lambda a, b: run_tiled(infer, a, b, h), data["frames"], data["positions"], h)
            score, classical = psnr(image, data["truth"]), float(data["classical"])
            means.setdefault((size_arg, kind), []).append((score, classical))
            print(f"h={h} {size_arg} {kind} {scene}: learned {score:.2f} dB, classical {classical:.2f} dB", flush=True)
    summary = {f"{s} {k}": [float(np.mean([a for a, _ in v])), float(np.mean([b for _, b in v]))] for (s, k), v in means.items()}
    for key, (a, b) in summary.items():
        print(f"mean {key}: learned {a:.2f} dB, classical {b:.2f} dB, difference {a - b:+.2f} dB")
    print(json.dumps(summary))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
