"""How long the GRBL driver (:mod:`hbis_torch.hardware.grbl`) waits for each kind of answer."""

from __future__ import annotations

import math
from dataclasses import dataclass

from hbis_torch.errors import HbisInputError


@dataclass(frozen=True)
class GrblTimeouts:
    """How long the driver waits for each kind of answer, in seconds.

    Attributes
    ----------
    welcome_s : float
        For the welcome line after a soft reset (an Arduino that reboots on connect needs ~2 s).
    reply_s : float
        For the ``ok``/``error`` that answers a line (GRBL answers within milliseconds).
    status_s : float
        For one status report after ``?``.
    homing_s : float
        For a whole homing cycle.
    move_margin_s : float
        Added to twice the estimated duration of a move to give its deadline.
    """

    welcome_s: float = 5.0
    reply_s: float = 2.0
    status_s: float = 0.5
    homing_s: float = 60.0
    move_margin_s: float = 2.0

    def __post_init__(self) -> None:
        for name, value in vars(self).items():
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise HbisInputError(f"timeout {name} must be a finite positive number, got {value!r}")
