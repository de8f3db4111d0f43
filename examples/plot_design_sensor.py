"""
Design a hybrid bionic image sensor
===================================

The design calculator answers the paper's first question: how far can the eight periphery
cameras be tilted away from the fovea without leaving a blind zone, and how much wider is the
whole field of view then? For the Table 1 prototype (a = 4 deg, n = 1.5) the FOV extension ratio
(FER) is about 2.63 horizontally and 2.51 vertically, the lens allows a resolution improvement
factor of up to h_max = 7, and super-resolving only the fovea saves about 80 % of the bandwidth
(BSR) against a uniformly sampled sensor.

The second half sweeps the wedge angle: larger wedges steer the fovea further but, past the
inflection point, no longer widen the field (FER levels off at 2). The plot is written to
``--out`` (default: a temporary folder).

Run: ``python examples/plot_design_sensor.py [--out DIR]``
"""

import argparse
import tempfile
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from hbis_torch import FoveaSystem
from hbis_torch.design import design, limit_sweep


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    parser.add_argument("--out", type=Path, default=None, help="output folder (default: a temporary one)")
    args = parser.parse_args()
    out = args.out or Path(tempfile.mkdtemp(prefix="hbis-design-"))
    out.mkdir(parents=True, exist_ok=True)

    # The design numbers of the Table 1 prototype (FoveaSystem() holds its parameters).
    system = FoveaSystem()
    report = design(system)
    print(f"single camera FOV  {report.single_fov_h_deg:.2f} x {report.single_fov_v_deg:.2f} deg")
    print(f"varphi limits      h {report.varphi_h_max_deg:.2f} deg, v {report.varphi_v_max_deg:.2f} deg")
    print(f"whole FOV          {report.fov_h_deg:.2f} x {report.fov_v_deg:.2f} deg")
    print(f"FER                h {report.fer_h:.3f}, v {report.fer_v:.3f}")
    print(f"h_max              {report.h_max} (diffraction ratio H = {report.diffraction_ratio:.2f})")
    print("BSR                " + ", ".join(f"h={h}: {v:.3f}" for h, v in report.bsr.items()))

    # FER against the wedge angle (the paper's Fig. 4b): linear, then flat past the inflection.
    angles = np.arange(1.0, 15.01, 0.5)
    sweep = limit_sweep(system, "wedge_angle_deg", angles)
    flat = angles[np.isclose(sweep["fer_h"], 2.0, atol=1e-9)]
    print(f"FER_h reaches 2 (the inflection) at a wedge angle of {flat[0]:.1f} deg" if len(flat)
          else "FER_h stays above 2 over the sweep")

    fig = Figure(figsize=(5, 3.5))
    ax = fig.subplots()
    ax.plot(angles, sweep["fer_h"], label="FER$_h$")
    ax.plot(angles, sweep["fer_v"], label="FER$_v$")
    ax.axvline(system.prisms.wedge_angle_deg, color="grey", ls=":", label="Table 1")
    ax.set_xlabel("wedge angle a [deg]")
    ax.set_ylabel("FOV extension ratio")
    ax.legend()
    fig.tight_layout()
    path = out / "fer_vs_wedge_angle.png"
    fig.savefig(path, dpi=100)
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
