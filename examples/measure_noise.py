"""
Measure a stack's noise from the stack itself
=============================================

The learned method tells its network how noisy the frames are: a Poisson-Gaussian variance
``a x + b`` of a frame value x in [0, 1] (``a`` from the shot noise, 1 / full well; ``b`` from the
read noise and the ADC's rounding). A stack that records its sensor (``sensor.full_well_e`` and
``sensor.read_noise_e`` in its JSON) gives them; a stack assembled from a camera's frames usually
does not, and the noise is measured from the stack. Where it is measured matters:

* on **single frames** (:func:`hbis_torch.reconstruct.learned.estimate_noise_params`) a frame of
  a sub-pixel scan is aliased, and its fine detail passes for noise;
* on the classical step's **lattice** (:func:`hbis_torch.reconstruct.learned.method.classical_and_noise`,
  which the learned method uses), the samples of all frames interleave a fraction of a pixel
  apart and the scene is smooth from node to node.

This example simulates a photograph's stack (h = 4, 64 x 64 pixels at the sensor's centre, a
50,000 e- sensor with 2 e- read noise, 12 bit: low noise, where single frames overstate it most),
takes the sensor model out of its metadata as a captured stack comes, and prints both estimates
against the sensor's: a and b, and the noise's standard deviation at black and at mid grey (in %
of full scale). The estimates are written to ``--out`` as ``noise.json``. At this noise the
shot noise dominates, so the fit pins ``a`` (and the level at mid grey) well and ``b`` (the level
at black) loosely: a captured stack that records its sensor needs no estimate at all.

Run: ``python examples/measure_noise.py [--out DIR] [--scene NAME]``
"""

import argparse
import json
import math
import tempfile
from pathlib import Path

from hbis_torch import FoveaSystem
from hbis_torch.reconstruct.learned import estimate_noise_params, noise_params_from_meta
from hbis_torch.reconstruct.learned.domain import noise_at_mid_grey
from hbis_torch.reconstruct.learned.method import classical_and_noise
from hbis_torch.scan import plan_scan
from hbis_torch.simulate import SensorModel, simulate_stack
from hbis_torch.stack_io import Stack

BITS = 12


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    parser.add_argument("--out", type=Path, default=None, help="output folder (default: a temporary one)")
    parser.add_argument("--scene", default="astronaut", help="built-in scene name or image path (default astronaut)")
    args = parser.parse_args()
    out = args.out or Path(tempfile.mkdtemp(prefix="hbis-noise-"))
    out.mkdir(parents=True, exist_ok=True)

    system, h = FoveaSystem(), 4
    cam = system.camera
    roi = ((cam.cols - 64) // 2, (cam.rows - 64) // 2, 64, 64)
    sensor = SensorModel(full_well_e=50_000, read_noise_e=2.0, bit_depth=BITS)
    stack, _ = simulate_stack(args.scene, system, plan_scan(system, h), roi=roi, sensor=sensor, seed=0)
    truth = noise_params_from_meta(stack.meta)
    meta = json.loads(json.dumps(stack.meta))  # as a captured stack comes: no sensor model
    for key in ("full_well_e", "read_noise_e"):
        meta["simulation"]["sensor"].pop(key)
    captured = Stack(stack.frames, meta).validate("the example's stack")

    estimates = {
        "sensor": truth,
        "single frames": estimate_noise_params(captured.to_float().numpy()),
        "lattice": classical_and_noise(captured, "optics")[1],
    }
    mid = {name: noise_at_mid_grey(params) for name, params in estimates.items()}
    print(f"{args.scene}, h = {h}, {roi[2]} x {roi[3]} px, {sensor.full_well_e:.0f} e- full well, "
          f"{sensor.read_noise_e} e- read noise, {BITS} bit")
    for name, (a, b) in estimates.items():
        print(f"  {name:14s} a {a:.3e}  b {b:.3e}  noise at black {100 * math.sqrt(b):.3f} %, at mid grey "
              f"{100 * mid[name]:.3f} % ({mid[name] / mid['sensor']:.2f} x the sensor's)")
    results = {name: {"a": a, "b": b, "mid_grey": mid[name]} for name, (a, b) in estimates.items()}
    (out / "noise.json").write_text(json.dumps(results, indent=1))
    print(f"wrote {out / 'noise.json'}")


if __name__ == "__main__":
    main()
