"""The command-line options of the GRBL simulator, shared by ``python -m
hbis_torch.hardware.simulator`` and ``hbis motors simulate``.

A module of its own so that building the ``hbis motors`` parser imports neither the simulator
(threads, sockets, a pseudo-terminal) nor the driver (pyserial).
"""

from __future__ import annotations

import argparse

from hbis_torch.checks import bounded_float, bounded_int
from hbis_torch.hardware.sim_machine import FAULT_KINDS


def add_simulator_args(parser: argparse.ArgumentParser) -> None:
    """Options of the simulator command line (shared with ``hbis motors simulate``)."""
    parser.add_argument("--tcp", type=bounded_int(0, 65535), metavar="PORT", help="serve on socket://127.0.0.1:PORT instead of a pty (0: any free port)")
    parser.add_argument("--speedup", type=bounded_float(0.0, 1e6, lo_open=True), default=1.0, help="run motion this many times faster than real (default 1)")
    parser.add_argument("--steps-per-deg", metavar="S1,S2", help="$100,$101: steps per degree of prism 1 and 2 "
                        "(default 35.556: 1.8 deg motor, 16 microsteps, 4:1 belt)")
    parser.add_argument("--homing", action="store_true", help="enable homing ($22=1): starts in Alarm until $H")
    parser.add_argument("--fault", action="append", default=[], metavar="KIND[:AFTER[:CODE]]",
                        help=f"inject a fault on the AFTER-th move from now (default 0); KIND is one of {', '.join(FAULT_KINDS)}")
    parser.add_argument("--duration", type=bounded_float(0.0, 1e7, lo_open=True), default=None, help="stop after this many seconds (default: until Ctrl-C)")
