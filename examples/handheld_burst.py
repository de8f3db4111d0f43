"""
Super-resolve a hand-held burst
===============================

A hand holding a camera moves it between frames: a little shift, a turn of a few tenths of a
degree, a change of perspective. Those sub-pixel moves are what multi-frame super-resolution
needs. This example renders such a burst with the project's held-out burst renderer (a collage of
photographs, a lens blur, pixel integration, Poisson-Gaussian noise, 16-bit frames; nothing the
registration was tuned on), then does what a user does with their own frames:

1. :func:`hbis_torch.capture.burst.assemble_burst` measures each frame's motion (coarse to fine
   on a pyramid, the model chosen per frame, local shifts on top) and builds the burst stack,
   as ``hbis assemble --burst --scale 2 --out burst.tif frames.tif`` does;
2. :func:`hbis_torch.reconstruct.reconstruct` super-resolves it with the classical method, once
   as is and once with the lens blur given (``hbis reconstruct burst.tif --method classical
   --psf-sigma 0.3``), as a calibration of the camera would give it;
3. the reference frame enlarged by bicubic interpolation, the two reconstructions and the truth
   are scored (PSNR) and shown side by side, cropped, in ``handheld_burst.png``.

Run: ``python examples/handheld_burst.py [--out DIR] [--size 640x480] [--motion similarity]``
"""

import argparse
import tempfile
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
import tifffile

from hbis_torch.capture.burst import assemble_burst
from hbis_torch.metrics import psnr
from hbis_torch.reconstruct import reconstruct
from hbis_torch.reconstruct.single_frame import single_frame
from hbis_torch.stack_io import write_stack
from hbis_torch.training.handheld_render import MOTIONS, render_burst


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    parser.add_argument("--out", type=Path, default=None, help="output folder (default: a temporary one)")
    parser.add_argument("--size", default="320x240", help="frame size WxH (default 320x240)")
    parser.add_argument("--frames", type=int, default=8, help="frames in the burst (default 8)")
    parser.add_argument("--motion", default="similarity", choices=MOTIONS, help="the hand's motion")
    args = parser.parse_args()
    out = args.out or Path(tempfile.mkdtemp(prefix="hbis-handheld-"))
    out.mkdir(parents=True, exist_ok=True)
    width, height = (int(n) for n in args.size.lower().split("x"))
    scale, blur = 2, 0.3

    burst = render_burst(args.motion, scale, args.frames, width, height, blur_sigma_px=blur, seed=7)
    tifffile.imwrite(out / "frames.tif", burst.frames, photometric="minisblack")
    stack, messages = assemble_burst(burst.frames, scale)
    write_stack(out / "burst.tif", stack)
    for line in messages:
        print("assemble:", line)
    models = stack.meta["motion_models"]
    print(f"burst of {len(models)} frames of {width} x {height} px; models: "
          + ", ".join(f"{models.count(m)} {m}" for m in dict.fromkeys(models)))

    images = {"bicubic": single_frame(burst.frames[0].astype(np.float32) / 65535, scale),
              "classical": reconstruct(stack, "classical"),
              "classical, lens given": reconstruct(stack, "classical", lens_sigma=blur)}
    for name, image in images.items():
        print(f"PSNR {name:22s} {psnr(image, burst.truth):6.2f} dB")

    # A crop of the centre, every image at the output's pixels.
    side = min(160, scale * height // 2)
    v0, u0 = (scale * height - side) // 2, (scale * width - side) // 2
    panels = {**images, "truth": burst.truth}
    fig, axes = plt.subplots(1, len(panels), figsize=(3 * len(panels), 3.3))
    for ax, (name, image) in zip(axes, panels.items()):
        ax.imshow(image[v0:v0 + side, u0:u0 + side], cmap="gray", vmin=0, vmax=1, interpolation="nearest")
        ax.set_title(name, fontsize=10)
        ax.axis("off")
    fig.suptitle(f"A simulated hand-held burst ({args.motion}, {args.frames} frames of {width} x {height} px, S = 2)",
                 fontsize=10)
    fig.tight_layout()
    fig.savefig(out / "handheld_burst.png", dpi=100)
    print(f"wrote {out / 'handheld_burst.png'}")


if __name__ == "__main__":
    main()
