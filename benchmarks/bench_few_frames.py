"""What a burst of few frames gives, with and without the lattice-fill blend of hbis reconstruct.

    python benchmarks/bench_few_frames.py [--frames 4 8 16] [--seeds 4]

A simulated 40 x 40 px burst at S = 2 (astronaut, 0.5 % noise, random shifts to 1.5 px,
hbis_torch.simulate.burst), assembled as a user's is, and reconstructed by the classical method
three ways: the single-frame estimate (the reference frame enlarged, bicubic), the method as
shipped (it leans on the single frame where the samples leave sub-pixel phases empty,
hbis_torch.reconstruct.burst), and the method without that blend. PSNR against the truth, mean
over the seeds.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from skimage import data, transform

from hbis_torch.capture.burst import assemble_burst
from hbis_torch.metrics import psnr
from hbis_torch.provenance import run_recorded
from hbis_torch.reconstruct import reconstruct
import hbis_torch.reconstruct.burst_fill as burst_fill
from hbis_torch.reconstruct.single_frame import single_frame
from hbis_torch.simulate.burst import random_motions, simulate_burst


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, nargs="+", default=[4, 8, 16])
    parser.add_argument("--seeds", type=int, default=4)
    parser.add_argument("--out", type=Path, default=None,
                        help="also write what is printed to this file (.txt/.md, or .json), with its provenance")
    args = parser.parse_args(argv)
    return run_recorded("bench_few_frames", measure, args, argv)


def measure(args):
    """Run the benchmark and print its result."""
    truth = transform.resize(data.astronaut()[100:300, 150:350].mean(-1) / 255, (80, 80), anti_aliasing=True)
    print("| frames | single frame | classical | classical without the fill blend |\n| --- | --- | --- | --- |")
    for count in args.frames:
        scores = []
        for seed in range(args.seeds):
            motions = random_motions(count, (40, 40), np.random.default_rng(seed), 1.5)
            sim = simulate_burst(truth, 2, motions, noise=0.005, seed=seed)
            stack, _ = assemble_burst(sim.frames, 2)
            shipped = psnr(reconstruct(stack, "classical"), truth)
            limits = burst_fill.NO_FILL, burst_fill.FULL_FILL
            burst_fill.NO_FILL, burst_fill.FULL_FILL = -1.0, -0.5  # every node counts as filled: no blend
            try:
                unblended = psnr(reconstruct(stack, "classical"), truth)
            finally:
                burst_fill.NO_FILL, burst_fill.FULL_FILL = limits
            scores.append((psnr(single_frame(sim.frames[0] / 255.0, 2), truth), shipped, unblended))
        one, shipped, unblended = np.mean(scores, axis=0)
        print(f"| {count} | {one:.2f} | {shipped:.2f} | {unblended:.2f} |")


if __name__ == "__main__":
    raise SystemExit(main())
