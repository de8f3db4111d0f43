"""Prism motors: a GRBL 1.1 driver over pyserial, scan execution, and a protocol simulator.

Prism 1 turns on GRBL's X axis and prism 2 on Y, with degrees as GRBL units. See
``docs/hardware.md`` for wiring, settings and fault behaviour.
"""

from hbis_torch.errors import (GrblAlarm, GrblCommandError, GrblDisconnected, GrblError, GrblHeld, GrblMoveLost,
                               GrblProtocolError, GrblTimeout, ScanInterrupted)
from hbis_torch.hardware.grbl_codes import alarm_meaning, error_meaning
from hbis_torch.hardware.grbl_protocol import GrblStatus, parse_status, unwrap_near
from hbis_torch.lazy import lazy_exports

__all__ = [
    "GrblAlarm", "GrblCommandError", "GrblController", "GrblDisconnected", "GrblError", "GrblHeld", "GrblMoveLost",
    "GrblProtocolError", "GrblSimulator", "GrblStatus", "GrblTimeout", "GrblTimeouts",
    "ScanInterrupted", "alarm_meaning", "error_meaning", "open_grbl", "parse_status", "unwrap_near",
]


# Names imported on first use, from the module that defines them: the driver needs pyserial, and
# the simulator must not be imported before ``python -m hbis_torch.hardware.simulator`` runs it.
# The package's light modules (``hbis motors --help`` needs the simulator's options) load neither.
_LAZY = {"GrblController": "grbl", "GrblTimeouts": "timeouts", "open_grbl": "grbl", "GrblSimulator": "simulator"}


__getattr__, __dir__ = lazy_exports(__name__, _LAZY, globals())
