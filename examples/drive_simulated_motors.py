"""
Drive the prism motors (simulated)
==================================

The two prisms are turned by stepper motors on a GRBL 1.1 controller: prism 1 on the X axis,
prism 2 on Y, with one GRBL unit meaning one degree of phase. This example needs no hardware:
:class:`hbis_torch.hardware.GrblSimulator` serves a simulated controller (the firmware's state
machine, :class:`~hbis_torch.hardware.sim_machine.GrblMachineModel`) on a pseudo-terminal in a
background thread, and :class:`hbis_torch.hardware.GrblController` talks to it through pyserial
exactly as it would to a USB serial adapter (``/dev/ttyUSB0``).

We move the prisms to a phase pair, then run a short h x h sub-pixel scan planned from phases the
motors can reach, and print the phases read back after each move. The motors move in whole
steps (``$100``/``$101`` steps per degree), so a read-back phase is within half a step of its
target. A journal of the frames taken is written to ``--out`` (default: a temporary folder);
rerunning a scan with the same journal after a fault would resume where it stopped.

From a shell the same is ``hbis motors simulate`` in one terminal and
``hbis motors --port PORT scan --h 3`` in another.

Run: ``python examples/drive_simulated_motors.py [--out DIR] [--h H]``
"""

import argparse
import tempfile
from pathlib import Path

from hbis_torch import FoveaSystem
from hbis_torch.hardware import GrblController, GrblSimulator
from hbis_torch.hardware.scan_executor import run_scan
from hbis_torch.scan import plan_scan, step_alignment_error


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    parser.add_argument("--out", type=Path, default=None, help="output folder (default: a temporary one)")
    parser.add_argument("--h", type=int, default=3, help="resolution improvement factor (default 3)")
    args = parser.parse_args()
    out = args.out or Path(tempfile.mkdtemp(prefix="hbis-motors-"))
    out.mkdir(parents=True, exist_ok=True)

    # speedup: the simulated machine runs 50 times faster than the real one would.
    with GrblSimulator(speedup=50, max_lifetime_s=120) as sim, \
            GrblController(sim.port, poll_interval_s=0.01).open() as grbl:
        step = grbl.step_deg
        print(f"GRBL {grbl.version} on {sim.port}: {grbl.status().state}, "
              f"{grbl.steps_per_deg[0]:g} steps/deg (one step = {step[0]:.4f} deg)")

        # 1. Move to a phase pair (the short way round) and read the phases back.
        target = (5.0, 70.0)
        phases = grbl.move_to(*target)
        print(f"goto {target}: read back ({phases[0]:.4f}, {phases[1]:.4f}) deg")

        # 2. A sub-pixel scan planned from phases the motors can stop at.
        system = FoveaSystem()
        initial = grbl.nearest_reachable(*target)
        plan = plan_scan(system, args.h, initial)
        predicted = step_alignment_error(system, plan, grbl.steps_per_deg)
        print(f"scan h = {plan.h}: {plan.frames} frames from ({initial[0]:.4f}, {initial[1]:.4f}) deg; "
              f"predicted axis AE with these steps: max {predicted['ae_axis_max']:.3f} SL")
        run = run_scan(grbl, plan.phases_deg, lambda index, phases: None,
                       journal=out / "scan-journal.json", settle_s=0.0)

    worst = 0.0
    for k, (planned, read) in enumerate(zip(run.targets_deg.tolist(), run.phases_deg.tolist())):
        err = max(abs(a - b) for a, b in zip(planned, read))
        worst = max(worst, err)
        print(f"  frame {k:2d}  planned ({planned[0]:8.4f}, {planned[1]:8.4f})  "
              f"read back ({read[0]:8.4f}, {read[1]:8.4f}) deg")
    print(f"largest read-back error {worst:.4f} deg (half a step is {max(step) / 2:.4f} deg)")
    print(f"wrote {out / 'scan-journal.json'}")


if __name__ == "__main__":
    main()
