"""The project's exceptions: one hierarchy, which the CLI maps to exit codes.

Each class carries its exit code (``exit_code``), so that a script can tell "my command was
wrong" from "the bench failed, retry":

- :class:`HbisError`: the root (exit 1). The CLI prints any other exception as a bug (exit 1).
- :class:`HbisInputError`: the input was wrong (a shape, a non-finite value, an out-of-range
  parameter, a corrupt file). The message says what in one line; exit code 2.

  - :class:`StackFormatError`: a stack file or object breaks the ``hbis-stack/1`` format.
  - :class:`OutOfScanField`: an object the fovea cannot be steered onto.
  - :class:`GrblCommandError`: the controller refused a line (``error:N``): the command was wrong.

- :class:`HbisDeviceError`: a device failed (exit 3): the motor controller timed out, went
  silent, vanished, raised an alarm, is held, or answers as no GRBL 1.1 does
  (:class:`GrblError` and its kinds). Retrying after fixing the bench may succeed.
"""

from __future__ import annotations


class HbisError(Exception):
    """Root of every exception hbis-torch raises on purpose (exit code 1 when nothing more is known)."""

    exit_code = 1


class HbisInputError(HbisError, ValueError):
    """Bad input: wrong shape, non-finite value, out-of-range parameter, corrupt file, ...

    The message says what was wrong in one line; the CLI prints it and exits with status 2.
    """

    exit_code = 2


class HbisDeviceError(HbisError, RuntimeError):
    """A device failed: a timeout, a lost connection, a silent controller, an alarm, a hold.

    The message says what and the way out in one line; the CLI prints it and exits with status 3.
    """

    exit_code = 3


class StackFormatError(HbisInputError):
    """A stack file or a Stack object breaks the hbis-stack/1 format (one-line message)."""


class OutOfScanField(HbisInputError):
    """The object cannot be brought into a ROI of the requested size."""


# --------------------------------------------------------------------------- the motor driver


class GrblError(HbisDeviceError):
    """Any failure talking to a GRBL controller (exit code 3, a device failure)."""


class GrblTimeout(GrblError):
    """The controller did not answer (a welcome, an ``ok``, a status report) in time."""


class GrblDisconnected(GrblError):
    """The serial connection went away (cable pulled, controller reset, socket closed)."""


class GrblMoveLost(GrblError):
    """The controller went Idle away from the target: the move line was lost or cut short."""


class GrblProtocolError(GrblError):
    """The controller answered, but not as GRBL 1.1 does (wrong version, missing settings)."""


class GrblCommandError(GrblError, HbisInputError):
    """The controller rejected a line with ``error:N``: the line was wrong (exit code 2).

    Attributes
    ----------
    code : int
        GRBL 1.1 error code N.
    meaning : str
        Its meaning from the GRBL 1.1 table.
    line : str
        The line that was rejected.
    """

    exit_code = 2

    def __init__(self, code: int, meaning: str, line: str):
        self.code, self.meaning, self.line = code, meaning, line
        super().__init__(f"controller rejected {line!r}: error:{code} ({meaning})")


class GrblHeld(GrblError):
    """The controller is in a feed hold (``Hold``) or its safety door is open (``Door``).

    GRBL then runs no line at all until cycle start (``~``) or a soft reset, while it still
    answers ``?``: a held controller is not a silent one.

    Attributes
    ----------
    state : str
        ``"Hold"`` or ``"Door"``.
    """

    def __init__(self, state: str, substate: int | None = None, doing: str = ""):
        self.state = state
        where = f"{state}:{substate}" if substate is not None else state
        remedy = ("close the door, then send cycle start (~) to resume, or reset the controller"
                  if state == "Door" else "send cycle start (~) to resume, or reset the controller")
        super().__init__(f"controller is in {'a feed hold' if state == 'Hold' else 'a safety-door stop'} "
                         f"({where}){' ' + doing if doing else ''} and runs no line until then: {remedy}")


class GrblAlarm(GrblError):
    """The controller reported ``ALARM:N`` or is in its Alarm state.

    Attributes
    ----------
    code : int or None
        GRBL 1.1 alarm code N; None when only the Alarm state was seen.
    meaning : str
        Its meaning from the GRBL 1.1 table.
    """

    def __init__(self, code: int | None, meaning: str, hint: str = ""):
        self.code, self.meaning = code, meaning
        what = f"raised ALARM:{code} ({meaning})" if code is not None else f"is in its Alarm state ({meaning})"
        super().__init__(f"controller {what}" + (f"; {hint}" if hint else ""))


class ScanInterrupted(GrblError):
    """A scan stopped before its last frame; rerunning with the same journal resumes it.

    Attributes
    ----------
    next_frame : int
        Index of the first frame not taken; a resumed scan starts there.
    frames_total : int
        Number of frames in the plan.
    cause : Exception
        What stopped the scan (also chained as ``__cause__``).
    """

    @property
    def exit_code(self) -> int:  # what stopped the scan decides: a device (3), a bad line (2), ...
        return getattr(self.cause, "exit_code", 3)  # a failed capture is the bench's too

    def __init__(self, next_frame: int, frames_total: int, cause: BaseException, journal=None):
        self.next_frame, self.frames_total, self.cause = next_frame, frames_total, cause
        kept = f"{next_frame} frame(s) kept" + (f" in {journal}" if journal else "")
        super().__init__(
            f"scan stopped at frame {next_frame} of {frames_total} ({kept}): {cause}; "
            f"fix the cause and rerun with the same journal to resume at frame {next_frame}"
        )
