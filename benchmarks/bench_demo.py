"""The demo's fovea before and after super-resolution: the README's picture and its figures.

    python benchmarks/bench_demo.py [--out benchmarks/results/bench_demo.json] [--picture docs/demo-fovea.png]

Runs ``hbis demo`` on its defaults (simulated: a 3 x 3 array watching a wall of photographs, the
two-stage loop steering the fovea onto a moving object, an h = 4 scan super-resolved by the
learned method; about a minute on 2 cores) into a temporary folder, then writes

* ``--out``: the demo's measures (``report.json``'s, less the event log: stitching error, FER,
  foveal ratio, BSR, the super-resolution's PSNR of the learned, classical and bicubic images
  against the simulated truth, dB), its settings and stage times, with provenance;
* ``--picture``: one frame of the fovea as the camera recorded it (each pixel drawn as an h x h
  block) beside the super-resolved fovea, the same central crop of each.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import numpy as np
from PIL import Image

from hbis_torch.errors import HbisInputError
from hbis_torch.io_utils import atomic_path, check_output_path
from hbis_torch.provenance import write_results

REPO = Path(__file__).resolve().parents[1]


def picture(folder: Path, h: int, path: Path, sr: dict) -> None:
    """The sub-image (nearest-neighbour enlarged) beside the SR fovea, central halves, as a PNG."""
    from matplotlib.figure import Figure

    before = np.asarray(Image.open(folder / "sub_image.png"), dtype=np.float32) / 255
    after = np.asarray(Image.open(folder / "sr_fovea.png"), dtype=np.float32) / 255
    before = np.kron(before, np.ones((h, h), np.float32))  # each recorded pixel as an h x h block
    side = after.shape[0] // 2
    crop = (slice(side // 2, side // 2 + side), slice(side // 2, side // 2 + side))
    fig = Figure(figsize=(8, 4.3))
    axes = fig.subplots(1, 2)
    titles = (f"before: one frame of the fovea, as recorded (enlarged bicubic: {sr['psnr_bicubic_db']:.1f} dB)",
              f"after: h = {h}, learned ({sr['psnr_sr_db']:.1f} dB)")
    for ax, image, title in zip(axes, (before, after), titles):
        ax.imshow(image[crop], cmap="gray", vmin=0, vmax=1, interpolation="nearest")
        ax.set_title(title, fontsize=9)
        ax.set_axis_off()
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=80, format="png")


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "bench_demo.json")
    parser.add_argument("--picture", type=Path, default=REPO / "docs" / "demo-fovea.png")
    args = parser.parse_args(argv)
    try:
        check_output_path(args.out, "--out")
        check_output_path(args.picture, "--picture")
    except HbisInputError as exc:
        print(f"bench_demo: {exc}", file=sys.stderr)
        return 2
    from hbis_torch.cli import main as hbis

    with tempfile.TemporaryDirectory() as tmp:
        if hbis(["demo", "--out", tmp, "--no-figures", "-q"]) != 0:
            return 1
        report = json.loads((Path(tmp) / "report.json").read_text())["system"]
        sr = report["sr"]
        picture(Path(tmp), report["config"]["h"], args.picture, sr)
    kept = ("config", "refinement", "fer", "foveal_ratio", "bandwidth", "loop", "sr", "timings_s")
    write_results(args.out, {"command_run": "hbis demo --out TMP --no-figures -q",
                             **{key: report[key] for key in kept},
                             "picture": str(args.picture.resolve().relative_to(REPO))
                             if args.picture.resolve().is_relative_to(REPO) else str(args.picture)}, argv=argv)
    print(f"learned {sr['psnr_sr_db']:.2f} dB, classical {sr['psnr_classical_db']:.2f} dB, "
          f"bicubic {sr['psnr_bicubic_db']:.2f} dB; wrote {args.out} and {args.picture}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
