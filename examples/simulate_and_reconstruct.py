"""
Simulate a stack and super-resolve it
=====================================

The fovea takes h x h frames while the Risley pair shifts its view by 1/h pixel between them;
reconstruction puts the samples back together on a grid h times finer. This example runs the
whole path on a small region of interest (64 x 48 pixels at the centre of the Table 1 sensor,
h = 4, 16 frames):

1. :func:`hbis_torch.scan.plan_scan` plans the scan from the initial phases (5, 70) deg;
2. :func:`hbis_torch.simulate.simulate_stack` renders the frames a camera would record (exact
   per-pixel optics, diffraction-limited PSF, pixel aperture, shot and read noise, 12-bit ADC)
   and the ground truth, what an ideal sensor of pitch p/h would see at the reference phases;
3. :func:`hbis_torch.reconstruct.reconstruct` super-resolves the stack with each method of
   :data:`hbis_torch.reconstruct.METHODS` (the classical splat-and-deconvolve baseline and the
   shipped network run in onnxruntime);
4. :func:`hbis_torch.metrics.psnr` scores them, and bicubic upsampling of the reference frame,
   against the truth.

The sample positions come from the optics alone (``--registration optics``): the simulated
stack's phases are the true ones, so the tracer is exact. For a captured stack keep the default
``"auto"``, which corrects the positions by registering the frames. The stack, the truth and the
reconstructions are written to ``--out`` as TIFF files (default: a temporary folder).

Run: ``python examples/simulate_and_reconstruct.py [--out DIR] [--scene NAME]``
"""

import argparse
import tempfile
from pathlib import Path

import torch

from hbis_torch import FoveaSystem
from hbis_torch.metrics import psnr
from hbis_torch.reconstruct import METHODS, reconstruct
from hbis_torch.scan import plan_scan
from hbis_torch.simulate import simulate_stack
from hbis_torch.stack_io import write_image, write_stack


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    parser.add_argument("--out", type=Path, default=None, help="output folder (default: a temporary one)")
    parser.add_argument("--scene", default="camera",
                        help="built-in scene name or image path (default camera)")
    parser.add_argument("--registration", default="optics", choices=("optics", "auto", "data"),
                        help="where the sample positions come from (default optics)")
    args = parser.parse_args()
    out = args.out or Path(tempfile.mkdtemp(prefix="hbis-sr-"))
    out.mkdir(parents=True, exist_ok=True)

    system, h = FoveaSystem(), 4
    cam = system.camera
    roi = ((cam.cols - 64) // 2, (cam.rows - 48) // 2, 64, 48)  # (u0, v0, width, height), pixels
    plan = plan_scan(system, h, (5.0, 70.0))
    stack, truth = simulate_stack(args.scene, system, plan, roi=roi, seed=0)
    write_stack(out / "stack.tif", stack)
    write_image(out / "truth.tif", truth)
    print(f"simulated {stack.frames.shape[0]} frames of {roi[2]} x {roi[3]} ({stack.frames.dtype}, "
          f"{stack.bit_depth} bits), h = {stack.h}, reference frame {stack.reference_index}; "
          f"truth {truth.shape[1]} x {truth.shape[0]}")

    # Score away from the border, where every method is short of neighbouring samples.
    inner = (slice(2 * h, -2 * h), slice(2 * h, -2 * h))
    reference = stack.to_float()[stack.reference_index]
    bicubic = torch.nn.functional.interpolate(reference[None, None], scale_factor=h, mode="bicubic",
                                              align_corners=False)[0, 0].clamp(0, 1).numpy()
    print(f"PSNR bicubic    {psnr(bicubic[inner], truth[inner]):6.2f} dB")
    for method in METHODS:
        image = reconstruct(stack, method=method, registration=args.registration)
        write_image(out / f"sr_{method}.tif", image)
        print(f"PSNR {method:10s} {psnr(image[inner], truth[inner]):6.2f} dB   "
              f"({image.shape[1]} x {image.shape[0]} {image.dtype})")
    print(f"wrote stack.tif, truth.tif and sr_*.tif in {out}")


if __name__ == "__main__":
    main()
