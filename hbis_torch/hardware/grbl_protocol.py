"""The GRBL 1.1 line protocol: real-time bytes, line classification, status reports, G-code lines.

Pure functions, no I/O: the driver (:mod:`.grbl`) and the simulator (:mod:`.simulator`) share them.
Angles are GRBL length units: with prism 1 on X and prism 2 on Y, one GRBL "mm" is one degree.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from enum import Enum

SOFT_RESET = b"\x18"
STATUS_QUERY = b"?"
FEED_HOLD = b"!"
CYCLE_START = b"~"
JOG_CANCEL = b"\x85"
SAFETY_DOOR = b"\x84"
REALTIME_BYTES = frozenset(SOFT_RESET + STATUS_QUERY + FEED_HOLD + CYCLE_START + JOG_CANCEL + SAFETY_DOOR)

LINE_MAX_CHARS = 80
"""GRBL's serial line buffer; longer lines are rejected with error:11."""

HOMING_ALARMS = frozenset({6, 7, 8, 9, 10})
"""The homing failures. GRBL 1.1h resets itself after one (``mc_reset``): it spends 500 ms
printing ``ALARM:N``, answers the aborted ``$H`` with ``ok``, drops every line received meanwhile,
then prints its welcome and ``[MSG:'$H'|'$X' to unlock]``, still in Alarm."""

FLOAT32_MAX = 3.4028234663852886e38
"""The largest setting GRBL can hold (its settings are 32-bit floats: larger values become inf)."""

STATES = ("Idle", "Run", "Hold", "Jog", "Alarm", "Door", "Check", "Home", "Sleep")

_WELCOME_RE = re.compile(r"^Grbl(?:HAL)?\s+(\d+\.\d+\w*)\s+\[.*\]$")
_SETTING_RE = re.compile(r"^\$(\d+)=([-+]?(?:\d+\.?\d*|\.\d+))$")
_CODE_RE = re.compile(r"^(error|ALARM):(\d+)$")
_NUMBER = r"[-+]?(?:\d+\.?\d*|\.\d+)"
_VECTOR_RE = re.compile(rf"^{_NUMBER}(?:,{_NUMBER})*$")


class Kind(Enum):
    """What a line from the controller is."""

    OK = "ok"
    ERROR = "error"
    ALARM = "alarm"
    STATUS = "status"
    MESSAGE = "message"  # [MSG:...], pushed at any time
    FEEDBACK = "feedback"  # [GC:...], [VER:...], [HLP:...], ... answers to queries
    SETTING = "setting"  # $N=value, in answer to $$
    WELCOME = "welcome"  # Grbl 1.1h ['$' for help], after every reset
    STARTUP = "startup"  # >G54:ok, a startup line that ran
    EMPTY = "empty"
    NOISE = "noise"  # anything else: line noise, another device, a garbled reply


@dataclass(frozen=True)
class GrblStatus:
    """One real-time status report, ``<State|MPos:x,y,z|...>``.

    Attributes
    ----------
    state : str
        Machine state, one of :data:`STATES`.
    substate : int or None
        Sub-state code (``Hold:0``, ``Door:1``), else None.
    mpos : tuple of float or None
        Machine position (X, Y, Z, ...) in GRBL units (degrees here) when reported.
    wpos : tuple of float or None
        Work position when reported instead of ``mpos`` (``$10`` bit 0 cleared).
    wco : tuple of float or None
        Work coordinate offset, sent now and then; ``MPos = WPos + WCO``.
    fields : dict
        Every other field as its raw text (``FS``, ``Bf``, ``Ln``, ``Pn``, ``Ov``, ...).
    raw : str
        The report as received.
    """

    state: str
    substate: int | None
    mpos: tuple[float, ...] | None
    wpos: tuple[float, ...] | None
    wco: tuple[float, ...] | None
    fields: dict = field(default_factory=dict)
    raw: str = ""


def _vector(text: str) -> tuple[float, ...] | None:
    if not _VECTOR_RE.match(text):
        return None
    return tuple(float(v) for v in text.split(","))


def parse_status(line: str) -> GrblStatus | None:
    """Parse a GRBL 1.1 status report; None if ``line`` is not a well-formed one.

    A report always starts with the state and a position (``MPos`` or ``WPos``); further fields
    may come in any order and are kept as text in ``fields`` (``WCO`` is parsed).
    """
    if not (line.startswith("<") and line.endswith(">")):
        return None
    parts = line[1:-1].split("|")
    if len(parts) < 2:
        return None
    state, _, sub = parts[0].partition(":")
    if state not in STATES or (sub and not sub.isdigit()):
        return None
    values: dict[str, str] = {}
    for part in parts[1:]:
        name, sep, value = part.partition(":")
        if not sep or not name:
            return None
        values[name] = value
    mpos = wpos = wco = None
    if "MPos" in values:
        mpos = _vector(values.pop("MPos"))
        if mpos is None:
            return None
    if "WPos" in values:
        wpos = _vector(values.pop("WPos"))
        if wpos is None:
            return None
    if "WCO" in values:
        wco = _vector(values.pop("WCO"))
        if wco is None:
            return None
    if mpos is None and wpos is None:
        return None
    return GrblStatus(state, int(sub) if sub else None, mpos, wpos, wco, values, line)


def parse_welcome(line: str) -> str | None:
    """The version in a welcome line (``Grbl 1.1h ['$' for help]`` gives ``"1.1h"``), else None."""
    m = _WELCOME_RE.match(line)
    return m.group(1) if m else None


def parse_setting(line: str) -> tuple[int, float] | None:
    """``$100=80.000`` gives ``(100, 80.0)``; None for anything else."""
    m = _SETTING_RE.match(line)
    return (int(m.group(1)), float(m.group(2))) if m else None


def classify(line: str) -> tuple[Kind, object]:
    """Sort one line from the controller (already stripped of CR/LF).

    Returns
    -------
    (Kind, payload)
        payload: the code (int) for ERROR/ALARM, a :class:`GrblStatus` for STATUS, ``(n, value)``
        for SETTING, the version for WELCOME, the text inside the brackets for MESSAGE and
        FEEDBACK, and the line itself otherwise.
    """
    if line == "ok":
        return Kind.OK, line
    if not line:
        return Kind.EMPTY, line
    m = _CODE_RE.match(line)
    if m:
        return (Kind.ERROR if m.group(1) == "error" else Kind.ALARM), int(m.group(2))
    if line.startswith("<"):
        status = parse_status(line)
        return (Kind.STATUS, status) if status is not None else (Kind.NOISE, line)
    if line.startswith("[") and line.endswith("]") and line[1:-1].isprintable():
        if line.startswith("[MSG:"):
            return Kind.MESSAGE, line[5:-1]
        return Kind.FEEDBACK, line[1:-1]
    setting = parse_setting(line)
    if setting is not None:
        return Kind.SETTING, setting
    version = parse_welcome(line)
    if version is not None:
        return Kind.WELCOME, version
    if line.startswith(">") and (line.endswith(":ok") or ":error:" in line) and line.isprintable():
        return Kind.STARTUP, line
    return Kind.NOISE, line


def clean_line(line: str) -> str:
    """A line as GRBL 1.1's main loop keeps it before parsing (``protocol_main_loop``).

    Spaces and control characters are dropped, ``/`` (block delete) is ignored, a ``(`` comment
    runs to its ``)``, a ``;`` comment to the end of the line, and letters are upper-cased:
    ``"$1 3=(c)1;x"`` is ``"$13=1"``. Real-time bytes never reach the line (GRBL's serial
    interrupt takes them out first), so they are dropped too.
    """
    out, in_parens, rest_is_comment = [], False, False
    for char in line:
        if ord(char) in REALTIME_BYTES or ord(char) > 0x7F:
            continue
        if rest_is_comment:
            continue
        if in_parens:
            in_parens = char != ")"
        elif char <= " " or char == "/":
            continue
        elif char == "(":
            in_parens = True
        elif char == ";":
            rest_is_comment = True
        else:
            out.append(char.upper() if "a" <= char <= "z" else char)
    return "".join(out)


_GRBL_NUMBER_RE = re.compile(r"^([-+]?)(?:\d+\.?\d*|\.\d+)$", re.ASCII)
_SETTING_WRITE_RE = re.compile(r"^\$([-+]?(?:\d+\.?\d*|\.\d+))=([-+]?(?:\d+\.?\d*|\.\d+))$", re.ASCII)
_GRBL_DIGITS = 8  # MAX_INT_DIGITS of GRBL 1.1h's read_float


def grbl_number(text: str) -> float | None:
    """The value GRBL 1.1h's ``read_float`` gives a whole number ``text``; None when it is none.

    GRBL keeps the first 8 digits (leading zeros count) and drops the rest, so
    ``0.0000000001`` is 0 and ``000000013`` is 10; a value beyond its 32-bit floats is inf.
    The float32 rounding of the digits kept is not modelled.

    >>> grbl_number("142.222"), grbl_number("0.0000000001"), grbl_number("000000013")
    (142.222, 0.0, 10.0)
    >>> grbl_number("1" + "0" * 39), grbl_number("inf")
    (inf, None)
    """
    m = _GRBL_NUMBER_RE.match(text)
    if not m:
        return None
    digits, exponent, kept, point = 0, 0, 0, False
    for char in text[len(m.group(1)):]:
        if char == ".":
            point = True
        elif kept < _GRBL_DIGITS:
            digits, kept = digits * 10 + int(char), kept + 1
            exponent -= point
        else:
            exponent += not point  # an integer digit dropped still scales the value
    if digits == 0:
        value = 0.0
    elif exponent >= 0:
        value = math.inf if exponent > 38 else float(digits * 10 ** exponent)
    else:
        value = digits / 10 ** -exponent
    if value > FLOAT32_MAX:
        value = math.inf
    return -value if m.group(1) == "-" else value


def setting_write(line: str) -> tuple[int, float] | None:
    """``(N, value)`` when ``line``, cleaned as GRBL cleans it, writes setting ``$N``; else None.

    N and the value are read as GRBL reads numbers (:func:`grbl_number`); N is then truncated
    (``$013=1`` and ``$13.5=1`` both write ``$13``); an N above 255 writes nothing (error:3).
    """
    m = _SETTING_WRITE_RE.match(clean_line(line))
    if not m:
        return None
    n = grbl_number(m.group(1))
    if n > 255:
        return None
    return int(n), grbl_number(m.group(2))


def _number(value: float) -> str:
    if not math.isfinite(value):
        raise ValueError(f"non-finite coordinate {value!r}")
    text = f"{value:.4f}".rstrip("0").rstrip(".")
    return "0" if text in ("-0", "") else text


def format_move(x_deg: float, y_deg: float, feed_deg_per_min: float | None = None) -> str:
    """An absolute move in machine coordinates: ``G21 G90 G53 G0 X.. Y..`` (or ``G1 .. F..``).

    G21/G90 are repeated on every line so that no earlier G20/G91 changes its meaning; G53 makes
    the target a machine position, the same frame the status report's MPos is in.
    """
    words = f"X{_number(x_deg)} Y{_number(y_deg)}"
    if feed_deg_per_min is None:
        return f"G21 G90 G53 G0 {words}"
    return f"G21 G90 G53 G1 {words} F{_number(feed_deg_per_min)}"


def format_jog(dx_deg: float, dy_deg: float, feed_deg_per_min: float) -> str:
    """A relative jog ``$J=G21 G91 X.. Y.. F..``; stop it early with :data:`JOG_CANCEL`."""
    return f"$J=G21 G91 X{_number(dx_deg)} Y{_number(dy_deg)} F{_number(feed_deg_per_min)}"


def wrap_deg(angle_deg: float) -> float:
    """The angle folded into [-180, 180) degrees."""
    return (angle_deg + 180.0) % 360.0 - 180.0


def unwrap_near(target_deg: float, reference_deg: float) -> float:
    """The angle equal to ``target_deg`` modulo 360 that lies nearest ``reference_deg``.

    Moving from ``reference_deg`` to the result turns at most 180 degrees: the short way round.
    """
    return reference_deg + wrap_deg(target_deg - reference_deg)


def nearest_step_phase(phase_deg: float, steps_per_deg: float, offset_deg: float = 0.0,
                       machine_near_deg: float | None = None) -> float:
    """The phase a stepping axis can actually stop at that is nearest ``phase_deg``.

    GRBL counts whole steps from machine position 0 (``round(MPos * steps_per_deg)``); the phase
    is MPos + ``offset_deg``. The machine position is taken in the branch nearest
    ``machine_near_deg`` (where a move from there would go; default ``phase_deg - offset_deg``),
    and the result is returned in the branch of ``phase_deg``.
    """
    machine = phase_deg - offset_deg
    if machine_near_deg is not None:
        machine = unwrap_near(machine, machine_near_deg)
    snapped = round(machine * steps_per_deg) / steps_per_deg + offset_deg
    return unwrap_near(snapped, phase_deg)
