"""The project's exceptions: one hierarchy, which the CLI maps to exit codes.

- :class:`HbisError`: the root. The CLI prints any other exception as a bug (exit code 1).
- :class:`HbisInputError`: the input was wrong (a shape, a non-finite value, an out-of-range
  parameter, a corrupt file, a controller that misbehaves). The message says what in one line;
  the CLI prints it and exits with code 2.

  - :class:`StackFormatError`: a stack file or object breaks the ``hbis-stack/1`` format.
  - :class:`OutOfScanField`: an object the fovea cannot be steered onto.
  - :class:`GrblError` and its kinds: the motor controller. A controller that is silent, rejects
    a line, raises an alarm or vanishes is a problem with what the user plugged in, not a bug in
    the program, so these are input errors too.
"""

from __future__ import annotations


class HbisError(Exception):
    """Root of every exception hbis-torch raises on purpose."""


class HbisInputError(HbisError, ValueError):
    """Bad input: wrong shape, non-finite value, out-of-range parameter, corrupt file, ...

    The message says what was wrong in one line; the CLI prints it and exits with status 2.
    """


class StackFormatError(HbisInputError):
    """A stack file or a Stack object breaks the hbis-stack/1 format (one-line message)."""


class OutOfScanField(HbisInputError):
    """The object cannot be brought into a ROI of the requested size."""


# --------------------------------------------------------------------------- the motor driver


class GrblError(HbisInputError):
    """Any failure talking to a GRBL controller."""


class GrblTimeout(GrblError):
    """The controller did not answer (a welcome, an ``ok``, a status report) in time."""


class GrblDisconnected(GrblError):
    """The serial connection went away (cable pulled, controller reset, socket closed)."""


class GrblMoveLost(GrblError):
    """The controller went Idle away from the target: the move line was lost or cut short."""


class GrblProtocolError(GrblError):
    """The controller answered, but not as GRBL 1.1 does (wrong version, missing settings)."""


class GrblCommandError(GrblError):
    """The controller rejected a line with ``error:N``.

    Attributes
    ----------
    code : int
        GRBL 1.1 error code N.
    meaning : str
        Its meaning from the GRBL 1.1 table.
    line : str
        The line that was rejected.
    """

    def __init__(self, code: int, meaning: str, line: str):
        self.code, self.meaning, self.line = code, meaning, line
        super().__init__(f"controller rejected {line!r}: error:{code} ({meaning})")


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

    def __init__(self, next_frame: int, frames_total: int, cause: BaseException, journal=None):
        self.next_frame, self.frames_total, self.cause = next_frame, frames_total, cause
        kept = f"{next_frame} frame(s) kept" + (f" in {journal}" if journal else "")
        super().__init__(
            f"scan stopped at frame {next_frame} of {frames_total} ({kept}): {cause}; "
            f"fix the cause and rerun with the same journal to resume at frame {next_frame}"
        )
