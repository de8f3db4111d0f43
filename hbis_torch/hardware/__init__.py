"""Prism motors: a GRBL 1.1 driver over pyserial, scan execution, and a protocol simulator.

Prism 1 turns on GRBL's X axis and prism 2 on Y, with degrees as GRBL units. See
``docs/hardware.md`` for wiring, settings and fault behaviour.
"""

from hbis_torch.errors import (GrblAlarm, GrblCommandError, GrblDisconnected, GrblError, GrblMoveLost,
                               GrblProtocolError, GrblTimeout, ScanInterrupted)
from hbis_torch.hardware.grbl import GrblController, GrblTimeouts, open_grbl
from hbis_torch.hardware.grbl_codes import alarm_meaning, error_meaning
from hbis_torch.hardware.grbl_protocol import GrblStatus, parse_status, unwrap_near

__all__ = [
    "GrblAlarm", "GrblCommandError", "GrblController", "GrblDisconnected", "GrblError", "GrblMoveLost",
    "GrblProtocolError", "GrblSimulator", "GrblStatus", "GrblTimeout", "GrblTimeouts",
    "ScanInterrupted", "alarm_meaning", "error_meaning", "open_grbl", "parse_status", "unwrap_near",
]


def __getattr__(name):
    # Imported on first use, so that ``python -m hbis_torch.hardware.simulator`` runs cleanly.
    if name == "GrblSimulator":
        from hbis_torch.hardware.simulator import GrblSimulator

        return GrblSimulator
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
