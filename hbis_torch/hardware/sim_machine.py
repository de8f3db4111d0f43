"""The GRBL 1.1 machine the simulator plays: line protocol, step-quantised motion, faults.

No I/O and no clock of its own: the caller feeds received bytes and the model time (seconds) and
collects the bytes to send back, so the model can be tested without threads. The transport and
the thread live in :mod:`.simulator`.

What is modelled: the welcome after a soft reset; ``$$`` and ``$N=value``; ``$G``, ``$I``, ``$``;
``$X`` unlock and ``$H`` homing (with ``$22``); ``$J=`` jogs and their cancel (0x85); feed hold
``!``, the safety door (0x84) and resume ``~``, during which no line runs (GRBL's suspend loop
answers only ``?`` and a reset); the status report ``?``; G-code lines
G0/G1/G4/G20/G21/G53/G90/G91 with X, Y, Z, F, P and N words and the GRBL 1.1 error codes for bad
ones; Alarm lock-out (error:9); soft limits (``$20=1``: a move outside ``-$130..0`` raises
ALARM:2, a jog gets error:15); the line cleaning of GRBL's main loop (spaces, control characters
and ``/`` dropped, ``( )`` and ``;`` comments removed, letters upper-cased); and the 500 ms that
GRBL 1.1h spends printing an alarm (``report_alarm_message``): after ALARM:1 or ALARM:2 a soft
reset sent before ``[MSG:Reset to continue]`` is lost, and only a later one is heard; a failed
homing cycle (:meth:`GrblMachineModel.fail_next_homing`): GRBL 1.1h prints ``ALARM:N`` (6 to 10),
spends the same 500 ms, answers the aborted ``$H`` with ``ok`` and resets itself (the welcome and
``[MSG:'$H'|'$X' to unlock]``, still in Alarm), dropping every byte that came meanwhile; ``$N=``
numbers read as GRBL reads them (8 digits kept; beyond a 32-bit float, inf).
Positions are whole steps (``$100``-``$102``): a target is rounded to the nearest step, as GRBL
does. A move follows a trapezoidal profile limited per axis by ``$110``-``$112`` (deg/min) and
``$120``-``$122`` (deg/s^2). Not modelled: arcs, probing, coordinate offsets, the planner's
junction speeds (each move starts and ends at rest), limit switches other than injected alarms.
"""

from __future__ import annotations

import math
import random
import re
from collections import deque
from dataclasses import dataclass, field

from hbis_torch.hardware.grbl_protocol import (CYCLE_START, FEED_HOLD, HOMING_ALARMS, JOG_CANCEL,
                                               LINE_MAX_CHARS, SAFETY_DOOR, SOFT_RESET, STATUS_QUERY, clean_line,
                                               grbl_number)
from hbis_torch.hardware.motion_profile import axis_limited, distance_at, move_duration_s
from hbis_torch.hardware.sim_settings import DEFAULT_SETTINGS, INTEGER_SETTINGS

VERSION = "1.1h"
WELCOME = f"Grbl {VERSION} ['$' for help]"

PLANNER_BLOCKS = 15
HOMING_DURATION_S = 1.0
ALARM_REPORT_DELAY_S = 0.5
"""GRBL 1.1h's ``report_alarm_message`` waits this long after ``ALARM:N``; a critical alarm then
prints ``[MSG:Reset to continue]`` and clears any reset that arrived meanwhile."""
FAULT_KINDS = ("drop_reply", "garbage", "garbled_reply", "disconnect", "error", "alarm", "silent", "hold")

_WORD_RE = re.compile(r"([A-Z])([-+]?(?:\d+\.?\d*|\.\d+))?")


class _GcodeError(Exception):
    def __init__(self, code: int):
        self.code = code


@dataclass
class Fault:
    """A fault that fires on the ``after_moves``-th motion line from now (0: the next one).

    Kinds: ``drop_reply`` (run the move, send no ``ok``), ``garbage`` (a line of noise before the
    ``ok``), ``garbled_reply`` (noise instead of the ``ok``), ``disconnect`` (hang up instead of
    answering), ``error`` (refuse the line with ``error:code``), ``alarm`` (run the move but stop
    half way with ``ALARM:code``, default 1, a hard limit), ``silent`` (answer nothing ever again),
    ``hold`` (accept the move, then a feed hold as if ``!`` came at once: no line runs until ``~``).
    """

    kind: str
    after_moves: int = 0
    code: int | None = None


@dataclass
class _Block:
    kind: str  # "move", "jog", "home", "dwell"
    start_steps: tuple[int, int, int]
    end_steps: tuple[int, int, int]
    duration: float
    length: float = 0.0
    speed: float = 1.0
    accel: float = 1.0
    feed: float = 0.0  # reported in FS, deg/min
    reply_when_done: bool = False  # $H and G4 answer only when finished
    alarm_fraction: float | None = None
    alarm_code: int = 1
    start: float | None = None


@dataclass
class GrblMachineModel:
    """The state machine of one simulated GRBL 1.1 controller (prism 1 on X, prism 2 on Y).

    Parameters
    ----------
    settings : dict, optional
        Overrides of :data:`DEFAULT_SETTINGS` (``$N`` -> value).
    seed : int
        Seed of the noise bytes used by the ``garbage`` faults.
    """

    settings: dict = field(default_factory=dict)
    seed: int = 0

    def __post_init__(self) -> None:
        self.settings = {**DEFAULT_SETTINGS, **{int(k): float(v) for k, v in self.settings.items()}}
        self._rng = random.Random(self.seed)
        self.steps = [0, 0, 0]
        self.state = "Alarm" if self._homing_enabled() else "Idle"
        self.critical = False  # after a hard limit: nothing but a soft reset is heard
        self.silent = False
        self.hung_up = False
        self.faults: list[Fault] = []
        self.received_lines: list[str] = []
        self.moves_done = 0
        self._blocks: deque[_Block] = deque()
        self._rx = bytearray()
        self._lines: deque[str] = deque()
        self._out = bytearray()
        self._modal = {"motion": 0, "distance": 90, "units": 21, "feed": None}
        self._planned = list(self.steps)  # where the last queued block ends
        self._hold_since: float | None = None
        self.held: str | None = None  # "Hold" or "Door": suspended, no line runs until ~ or a reset
        self._reset_lost_until: float | None = None  # the alarm window: a reset is lost before this
        self._homing_fails: int | None = None  # the alarm code the next homing cycle ends with
        self._self_reset_at: float | None = None  # after a homing alarm: GRBL resets itself then
        self._send_wco = True
        self._last_now = 0.0

    # ----------------------------------------------------------------------------- interface
    def inject(self, kind: str, after_moves: int = 0, code: int | None = None) -> None:
        """Arm a :class:`Fault`; it fires once."""
        if kind not in FAULT_KINDS:
            raise ValueError(f"unknown fault {kind!r}; known: {', '.join(FAULT_KINDS)}")
        if int(after_moves) < 0:
            raise ValueError("after_moves must be >= 0")
        self.faults.append(Fault(kind, int(after_moves), code))

    def fail_next_homing(self, code: int = 8) -> None:
        """Make the next homing cycle fail at its end with ``ALARM:code`` (6 to 10; 8: the switch
        stayed closed after the pull-off, 9: no switch found); GRBL then resets itself."""
        if int(code) not in HOMING_ALARMS:
            raise ValueError(f"a homing alarm is one of {sorted(HOMING_ALARMS)}, got {code!r}")
        self._homing_fails = int(code)

    def take_output(self) -> bytes:
        """Bytes produced since the last call, to be sent to the host."""
        out = bytes(self._out)
        self._out.clear()
        return out

    def receive(self, data: bytes, now: float) -> None:
        """Bytes from the host at model time ``now`` (s). Real-time bytes act at once."""
        self.tick(now)
        for byte in data:
            char = bytes([byte])
            if self._self_reset_at is not None:
                continue  # GRBL is printing a homing alarm and resets itself next: all is dropped
            if char == SOFT_RESET:
                if not self.silent and self._reset_lost_until is None:
                    self._soft_reset(now)
            elif self.silent or (self.critical and char != SOFT_RESET):
                continue
            elif char == STATUS_QUERY:
                if self.state != "Home":  # GRBL sends no reports while homing
                    self._emit(self._status_report(now))
            elif char == JOG_CANCEL:
                self._jog_cancel(now)
            elif char == FEED_HOLD:
                self._feed_hold(now, "Hold")
            elif char == SAFETY_DOOR:
                self._feed_hold(now, "Door")
            elif char == CYCLE_START:
                self._cycle_start(now)
            elif char in b"\r\n":
                line = self._rx.decode("ascii", errors="replace")
                self._rx.clear()
                self._lines.append(line)
            elif byte >= 0x80:
                continue  # other extended-ASCII real-time commands (overrides): not modelled
            else:
                self._rx.append(byte)
        self._process_lines(now)

    def tick(self, now: float) -> None:
        """Advance motion to model time ``now`` (s)."""
        self._last_now = now
        if self._self_reset_at is not None and now >= self._self_reset_at:
            self._self_reset_at = None
            self._emit("ok")  # the aborted $H is answered, then GRBL resets (main loop's sys.abort)
            self._soft_reset(now)
        if self._reset_lost_until is not None and now >= self._reset_lost_until:
            self._reset_lost_until = None  # the window closes: the message, and resets heard again
            self._emit("[MSG:Reset to continue]")
        if self._hold_since is not None:
            return
        while self._blocks:
            block = self._blocks[0]
            if block.start is None:
                block.start = now
            if block.alarm_fraction is not None and now >= block.start + block.alarm_fraction * block.duration:
                at = block.start + block.alarm_fraction * block.duration
                self.steps = list(self._position(block, at))
                if block.kind == "home":
                    self._homing_alarm(block.alarm_code, now=at)
                else:
                    self._raise_alarm(block.alarm_code, critical=True, now=at)
                self.tick(now)  # the alarm window may be over already
                return
            end = block.start + block.duration
            if now < end:
                break
            self._blocks.popleft()
            self._finish(block)
            if self._blocks:
                self._blocks[0].start = end
        if not self._blocks and self.state in ("Run", "Jog", "Home"):
            self.state = "Idle"
        self._process_lines(now)

    def busy(self) -> bool:
        """Whether motion or a line is pending (the server polls faster then)."""
        return bool(self._blocks or self._lines or self._reset_lost_until is not None
                    or self._self_reset_at is not None)

    def position_deg(self, now: float | None = None) -> tuple[float, float, float]:
        """Machine position in degrees (whole steps over steps per degree)."""
        steps = self._current_steps(self._last_now if now is None else now)
        return tuple(s / self.settings[100 + i] for i, s in enumerate(steps))

    # ------------------------------------------------------------------------------- helpers
    def _emit(self, text: str) -> None:
        self._out += text.encode("ascii") + b"\r\n"

    def _noise(self) -> bytes:
        return bytes(self._rng.randrange(0x80, 0x100) for _ in range(6))

    def _homing_enabled(self) -> bool:
        return int(self.settings.get(22, 0)) & 1 == 1

    def _position(self, block: _Block, t: float) -> tuple[int, int, int]:
        if block.kind not in ("move", "jog") or block.length == 0:
            return block.start_steps
        fraction = distance_at(t - block.start, block.length, block.speed, block.accel) / block.length
        return tuple(round(a + (b - a) * fraction) for a, b in zip(block.start_steps, block.end_steps))

    def _current_steps(self, now: float) -> tuple[int, int, int]:
        if self._blocks and self._blocks[0].start is not None:
            t = now if self._hold_since is None else self._hold_since
            return self._position(self._blocks[0], t)
        return tuple(self.steps)

    def _finish(self, block: _Block) -> None:
        if block.kind == "home":
            self.steps = [0, 0, 0]
            self._planned = [0, 0, 0]
            self.state = "Idle"
        else:
            self.steps = list(block.end_steps)
            if block.kind in ("move", "jog"):
                self.moves_done += 1
        if block.reply_when_done:
            self._emit("ok")

    def _append(self, block: _Block, now: float) -> None:
        if not self._blocks:
            block.start = now  # an idle machine starts the block at once
        self._blocks.append(block)

    def _raise_alarm(self, code: int, *, critical: bool, now: float) -> None:
        self._blocks.clear()
        self._lines.clear()
        self._planned = list(self.steps)
        self._hold_since, self.held = None, None
        self.state = "Alarm"
        self.critical = critical
        self._emit(f"ALARM:{code}")
        if critical:  # "[MSG:Reset to continue]" follows at the end of the window (tick)
            self._reset_lost_until = now + ALARM_REPORT_DELAY_S

    def _homing_alarm(self, code: int, *, now: float) -> None:
        """A failed homing cycle: ``ALARM:code`` now, GRBL's own reset at the end of its 500 ms."""
        self._raise_alarm(code, critical=False, now=now)
        self._self_reset_at = now + ALARM_REPORT_DELAY_S

    def _soft_reset(self, now: float) -> None:
        self.tick(now)
        moving = self.state in ("Run", "Jog", "Home") or self._hold_since is not None
        was_homing = self.state == "Home"
        self.steps = list(self._current_steps(now))
        self._blocks.clear()
        self._lines.clear()
        self._rx.clear()
        self._planned = list(self.steps)
        self._hold_since, self.held = None, None
        self._modal = {"motion": 0, "distance": 90, "units": 21, "feed": None}
        if moving:
            self._emit(f"ALARM:{6 if was_homing else 3}")
            self.state = "Alarm"
        self.critical = False
        self._send_wco = True
        self._emit("")
        self._emit(WELCOME)
        if self.state == "Alarm":
            self._emit("[MSG:'$H'|'$X' to unlock]")

    def _status_report(self, now: float) -> str:
        steps = self._current_steps(now)
        pos = ",".join(f"{s / self.settings[100 + i]:.3f}" for i, s in enumerate(steps))
        state = f"{self.held}:0" if self.held else self.state
        moving = self._blocks and self._blocks[0].kind in ("move", "jog") and self._hold_since is None
        feed = self._blocks[0].feed if moving else 0.0
        where = "MPos" if int(self.settings[10]) & 1 else "WPos"  # no offsets here: WPos = MPos
        report = f"<{state}|{where}:{pos}|FS:{feed:.0f},0"
        if self._send_wco:
            report += "|WCO:0.000,0.000,0.000"
            self._send_wco = False
        return report + ">"

    # ------------------------------------------------------------------------------ realtime
    def _jog_cancel(self, now: float) -> None:
        if self.state != "Jog":
            return
        self.steps = list(self._current_steps(now))
        self._blocks = deque(b for b in self._blocks if b.kind != "jog")
        self._planned = list(self.steps)
        self._hold_since = None
        self.state = "Idle"

    def _feed_hold(self, now: float, kind: str) -> None:
        """``!`` (kind "Hold") or the safety door (kind "Door"): motion freezes (when moving) and
        GRBL enters its suspend loop, Idle or not: no line runs until ``~`` or a reset."""
        if self.state in ("Alarm", "Check", "Home"):
            return
        if kind == "Door":
            self._emit("[MSG:Check Door]")
        if self.held is None or kind == "Door":
            self.held = kind
        if self.state in ("Run", "Jog") and self._hold_since is None:
            self._hold_since = now

    def _cycle_start(self, now: float) -> None:
        self.held = None  # the door of the model closes at once
        if self._hold_since is not None:
            if self._blocks and self._blocks[0].start is not None:
                self._blocks[0].start += now - self._hold_since
            self._hold_since = None

    # --------------------------------------------------------------------------------- lines
    def _process_lines(self, now: float) -> None:
        while self._lines and not self.critical and not self.silent and not self.hung_up and not self.held:
            if any(b.reply_when_done for b in self._blocks):
                return  # $H and G4 hold the line parser until they finish, as in GRBL
            if len(self._blocks) >= PLANNER_BLOCKS:
                return  # planner full: GRBL stops reading lines until a block finishes
            raw = self._lines.popleft()
            self.received_lines.append(raw)
            reply = self._execute(raw, now)
            if reply is not None:
                self._emit(reply)

    def _execute(self, raw: str, now: float) -> str | None:
        """Run one line; returns the reply (``ok``/``error:N``) or None when it comes later."""
        line = clean_line(raw)
        if len(line) >= LINE_MAX_CHARS:
            return "error:11"
        if not line:
            return "ok"
        try:
            if line.startswith("$"):
                return self._system(line, now)
            if self.state == "Alarm":
                return "error:9"
            if self.state == "Jog":
                return "error:9"
            return self._gcode(line, now, jog=False)
        except _GcodeError as exc:
            return f"error:{exc.code}"

    def _system(self, line: str, now: float) -> str | None:
        if line == "$":
            self._emit("[HLP:$$ $# $G $I $N $x=val $Nx=line $J=line $SLP $C $X $H ~ ! ? ctrl-x]")
        elif line == "$$":
            if self.state in ("Run", "Jog", "Home") or self._hold_since is not None:
                return "error:8"
            for n, value in sorted(self.settings.items()):
                self._emit(f"${n}={int(value)}" if n in INTEGER_SETTINGS else f"${n}={value:.3f}")
        elif line == "$G":
            m = self._modal
            feed = m["feed"] or 0
            self._emit(f"[GC:G{m['motion']} G54 G17 G{m['units']} G{m['distance']} G94 M5 M9 T0 F{feed:g} S0]")
        elif line == "$I":
            self._emit(f"[VER:{VERSION}.20190825:hbis-torch simulator]")
            self._emit("[OPT:V,15,128]")
        elif line == "$#":
            for name in ("G54", "G55", "G56", "G57", "G58", "G59", "G28", "G30", "G92"):
                self._emit(f"[{name}:0.000,0.000,0.000]")
            self._emit("[TLO:0.000]")
        elif line == "$X":
            if self.state == "Alarm":
                self.state = "Idle"
                self._emit("[MSG:Caution: Unlocked]")
        elif line == "$H":
            if not self._homing_enabled():
                return "error:5"
            if self.state not in ("Idle", "Alarm"):
                return "error:8"
            self.state = "Home"
            here = tuple(self.steps)
            block = _Block("home", here, (0, 0, 0), HOMING_DURATION_S, reply_when_done=True)
            if self._homing_fails is not None:
                block.alarm_fraction, block.alarm_code = 1.0, self._homing_fails
                self._homing_fails = None
            self._append(block, now)
            return None
        elif line.startswith("$J="):
            if self.state not in ("Idle", "Jog"):
                return "error:9" if self.state == "Alarm" else "error:8"
            return self._gcode(line[3:], now, jog=True)
        elif re.fullmatch(r"\$[-+]?(\d+\.?\d*|\.\d+)=.*", line):
            n_text, value_text = line[1:].split("=", 1)
            number = grbl_number(n_text)  # GRBL reads N as a number and truncates it
            n = int(number) if number <= 255 else None
            if n not in self.settings:
                return "error:3"
            if self.state not in ("Idle", "Alarm"):
                return "error:8"
            value = grbl_number(value_text)  # 8 digits kept; beyond a 32-bit float: inf
            if value is None:  # no number (error:2), or one followed by more (error:3: "1e5")
                return "error:3" if re.match(r"[-+]?\.?\d", value_text) else "error:2"
            if value < 0:
                return "error:4"
            if n == 20 and value and not self._homing_enabled():
                return "error:10"  # soft limits need homing
            self.settings[n] = value
        else:
            return "error:3"
        return "ok"

    def _parse_words(self, line: str) -> list[tuple[str, float]]:
        words, pos = [], 0
        while pos < len(line):
            m = _WORD_RE.match(line, pos)
            if not m:
                raise _GcodeError(1)  # no letter where a word should start
            if m.group(2) is None:
                raise _GcodeError(2)
            words.append((m.group(1), float(m.group(2))))
            pos = m.end()
        return words

    def _gcode(self, line: str, now: float, *, jog: bool) -> str | None:
        try:
            words = self._parse_words(line)
        except _GcodeError:
            if jog:
                raise _GcodeError(16) from None
            raise
        motion = None
        absolute_override = False
        dwell = False
        modal = dict(self._modal)
        axes: dict[int, float] = {}
        seen: set[str] = set()
        params: dict[str, float] = {}
        for letter, value in words:
            if letter == "G":
                if value in (0, 1):
                    if motion is not None:
                        raise _GcodeError(21)
                    motion = int(value)
                elif value == 4:
                    dwell = True
                elif value in (20, 21):
                    modal["units"] = int(value)
                elif value in (90, 91):
                    modal["distance"] = int(value)
                elif value == 53:
                    absolute_override = True
                elif value in (17, 54, 94):
                    pass
                else:
                    raise _GcodeError(16 if jog else 20)
            elif letter in "XYZFPN":
                if letter in seen:
                    raise _GcodeError(25)
                seen.add(letter)
                if letter in "XYZ":
                    axes["XYZ".index(letter)] = value
                else:
                    params[letter] = value
            elif letter == "M" and not jog and value in (2, 30, 3, 4, 5, 8, 9):
                if value in (2, 30):
                    self._emit("[MSG:Pgm End]")
            else:
                raise _GcodeError(16 if jog else 20)
        if jog:
            if motion is not None or dwell or "F" not in params or not axes:
                raise _GcodeError(16)
            motion = 1
        if "F" in params:
            if params["F"] <= 0:
                raise _GcodeError(4)
            modal["feed"] = params["F"]
        if motion is not None:
            modal["motion"] = motion
        if absolute_override and modal["motion"] not in (0, 1):
            raise _GcodeError(30)
        if dwell:
            if "P" not in params:
                raise _GcodeError(28)
            if axes:
                raise _GcodeError(31)
        if axes and modal["motion"] == 1 and not modal["feed"]:
            raise _GcodeError(22)
        if not jog:
            self._modal = {k: v for k, v in modal.items()}

        if dwell:
            here = tuple(self._planned)
            self._append(_Block("dwell", here, here, params["P"], reply_when_done=True), now)
            return None
        if not axes:
            return "ok"
        return self._queue_move(axes, modal, absolute_override, jog, now)

    def _queue_move(self, axes, modal, absolute_override, jog, now) -> str | None:
        fault = self._due_faults()
        if "disconnect" in fault:
            self.hung_up = True
            return None
        if "error" in fault:
            return f"error:{fault['error'] or 20}"
        if "silent" in fault:
            self.silent = True
            return None
        scale = 25.4 if modal["units"] == 20 else 1.0
        spm = [self.settings[100 + i] for i in range(3)]
        start = tuple(self._planned)
        target = []
        for i in range(3):
            if i not in axes:
                target.append(start[i])
            elif modal["distance"] == 91 and not absolute_override:
                target.append(start[i] + round(axes[i] * scale * spm[i]))
            else:
                target.append(round(axes[i] * scale * spm[i]))
        target = tuple(target)
        if int(self.settings[20]) and self._beyond_travel(target):
            if jog:
                return "error:15"  # GRBL checks a jog's target and refuses it
            self._raise_alarm(2, critical=True, now=now)  # ALARM:2 and no reply to the line
            return None
        delta = [(b - a) / s for a, b, s in zip(start, target, spm)]
        length = math.sqrt(sum(d * d for d in delta))
        if length == 0:
            speed = accel = 1.0
        else:
            unit = [d / length for d in delta]
            speed = axis_limited(unit, [self.settings[110 + i] / 60.0 for i in range(3)])
            if modal["motion"] == 1 or jog:
                speed = min(speed, modal["feed"] / 60.0)
            accel = axis_limited(unit, [self.settings[120 + i] for i in range(3)])
        block = _Block("jog" if jog else "move", start, target, move_duration_s(length, speed, accel),
                       length, speed, accel, feed=speed * 60.0)
        if "alarm" in fault:
            block.alarm_fraction, block.alarm_code = 0.5, fault["alarm"] or 1
        self._append(block, now)
        self._planned = list(target)
        if self.state == "Idle":
            self.state = "Jog" if jog else "Run"
        if "hold" in fault:
            self._feed_hold(now, "Hold")
        if "drop_reply" in fault:
            return None
        if "garbled_reply" in fault:
            self._out += b"o" + self._noise() + b"k\r\n"
            return None
        if "garbage" in fault:
            self._out += self._noise() + b"\r\n"
        return "ok"

    def _beyond_travel(self, target_steps) -> bool:
        """GRBL 1.1h's soft limits: machine travel runs from -$130 (-$131, -$132) to 0."""
        return any(not -self.settings[130 + i] <= t / self.settings[100 + i] <= 0 for i, t in enumerate(target_steps))

    def _due_faults(self) -> dict[str, int | None]:
        due: dict[str, int | None] = {}
        for fault in list(self.faults):
            if fault.after_moves == 0:
                due[fault.kind] = fault.code
                self.faults.remove(fault)
            else:
                fault.after_moves -= 1
        return due
