"""A GRBL 1.1 controller driving the two prisms, over any pyserial URL.

Prism 1 turns on the X axis and prism 2 on Y; GRBL's length unit is used as the degree, so ``$100``
and ``$101`` are steps per degree of prism rotation (after the belt ratio) and the status report's
``MPos`` is the prism phase in degrees (plus an optional fixed offset).

Every wait has a deadline; every failure is one clear :class:`~hbis_torch.errors.GrblError`:

>>> with GrblController("/dev/ttyUSB0").open() as grbl:   # doctest: +SKIP
...     grbl.move_to(5.0, 70.0)
(5.0, 70.0)
"""

from __future__ import annotations

import logging
import math
import time
from collections import deque

import serial

from hbis_torch.checks import MAX_PHASE_DEG
from hbis_torch.errors import (HbisInputError, GrblAlarm, GrblCommandError, GrblDisconnected, GrblError, GrblHeld,
                               GrblMoveLost, GrblProtocolError, GrblTimeout)
from hbis_torch.hardware.grbl_codes import alarm_meaning, error_meaning
from hbis_torch.hardware.grbl_protocol import (FLOAT32_MAX, HOMING_ALARMS, JOG_CANCEL, LINE_MAX_CHARS, REALTIME_BYTES,
                                               SOFT_RESET, STATUS_QUERY, GrblStatus, Kind, classify, clean_line,
                                               format_jog, format_move, nearest_step_phase, setting_write,
                                               unwrap_near)
from hbis_torch.hardware.motion_profile import axis_limited, move_duration_s

from hbis_torch.hardware.serial_port import IO_ERRORS as _IO_ERRORS
from hbis_torch.hardware.serial_port import open_serial_port
from hbis_torch.hardware.timeouts import GrblTimeouts

log = logging.getLogger(__name__)

_ALARM_HINT = "reset the controller, then home ($H) or unlock ($X) before moving again"
_HOMING_ALARM_HINT = "the controller has reset itself; home ($H) again or unlock ($X) before moving"
# A reset that brings no welcome within this is sent again: GRBL 1.1h loses a reset sent in the
# 500 ms it spends printing ALARM:1 or ALARM:2 (report_alarm_message), and answers a later one.
_RESET_RESEND_S = 1.0
_HELD_STATES = ("Hold", "Door")
# Fallbacks for timeout estimates when a controller does not report $110/$111 or $120/$121.

_DEFAULT_RATE_DEG_PER_MIN = 500.0
_DEFAULT_ACCEL_DEG_PER_S2 = 10.0


class GrblController:
    """One GRBL 1.1 controller with prism 1 on X and prism 2 on Y.

    Parameters
    ----------
    url : str
        Any pyserial URL: a device (``/dev/ttyUSB0``, ``COM3``), ``socket://host:port``,
        ``loop://``, ``spy:///dev/ttyUSB0?file=log.txt``, ...
    baudrate : int
        Serial speed; GRBL 1.1 uses 115200.
    timeouts : GrblTimeouts
        Deadlines for each kind of wait.
    poll_interval_s : float
        Time between ``?`` status queries while waiting for a move (GRBL advises <= 5-10 Hz).
    phase_offset_deg : (float, float)
        Prism phases at machine position zero: phase = MPos + offset, per prism, in degrees.

    Attributes
    ----------
    settings : dict[int, float]
        The ``$$`` settings read when the connection opened.
    version : str
        Firmware version from the welcome line, e.g. ``"1.1h"``.
    messages : deque[str]
        The ``[MSG:...]`` lines pushed by the controller, oldest first.
    noise_lines : deque[str]
        Lines that were not GRBL 1.1 protocol (line noise, garbled replies); ignored.
    stale_replies : int
        ``ok``/``error`` lines that answered a line the driver had already given up on.
    """

    def __init__(self, url: str, *, baudrate: int = 115200, timeouts: GrblTimeouts | None = None,
                 poll_interval_s: float = 0.1, phase_offset_deg: tuple[float, float] = (0.0, 0.0)):
        if not isinstance(url, str) or not url:
            raise HbisInputError(f"serial port URL must be a non-empty string, got {url!r}")
        offsets = tuple(float(v) for v in phase_offset_deg)
        if len(offsets) != 2 or not all(math.isfinite(v) for v in offsets):
            raise HbisInputError(f"phase offset must be two finite angles in degrees, got {phase_offset_deg!r}")
        if not (math.isfinite(poll_interval_s) and poll_interval_s > 0):
            raise HbisInputError(f"poll interval must be a finite positive number, got {poll_interval_s!r}")
        self.url, self.baudrate = url, int(baudrate)
        self.timeouts = timeouts or GrblTimeouts()
        self.poll_interval_s = float(poll_interval_s)
        self.phase_offset_deg = offsets
        self.settings: dict[int, float] = {}
        self.version = ""
        # the latest 100 of each: a noisy line must not fill memory in a long session
        self.messages: deque[str] = deque(maxlen=100)
        self.noise_lines: deque[str] = deque(maxlen=100)
        self.stale_replies = 0
        self.alarm_code: int | None = None
        self.last_status: GrblStatus | None = None
        self._wco: tuple[float, ...] | None = None
        self._serial = None
        self._buffer = bytearray()

    # ----------------------------------------------------------------------------- connection
    def open(self) -> "GrblController":
        """Open the port, soft-reset the controller, wait for its welcome, read ``$$``.

        Raises
        ------
        HbisInputError
            When ``url`` names something that can never be a serial port: a directory, a regular
            file, a character device that is not a terminal (``/dev/null``).
        GrblError
            When the port cannot be opened otherwise (a missing device: an unplugged adapter).
        """
        self._serial = open_serial_port(self.url, self.baudrate, self.timeouts.reply_s)
        try:
            self.reset()
            self.read_settings()
        except BaseException:
            self.close()
            raise
        return self

    def close(self) -> None:
        """Close the port (safe to call twice)."""
        if self._serial is not None:
            try:
                self._serial.close()
            except _IO_ERRORS:
                pass
            self._serial = None

    def __enter__(self) -> "GrblController":
        return self if self._serial is not None else self.open()

    def __exit__(self, *exc) -> None:
        self.close()

    # ------------------------------------------------------------------------------- low level
    def _port(self):
        if self._serial is None:
            raise GrblDisconnected(f"serial port {self.url!r} is not open")
        return self._serial

    def _write(self, data: bytes) -> None:
        port = self._port()
        log.debug("-> %r", data)
        try:
            port.write(data)
            port.flush()
        except serial.SerialTimeoutException:
            raise GrblTimeout(f"could not write to {self.url!r} within {self.timeouts.reply_s:.1f} s") from None
        except _IO_ERRORS as exc:
            self.close()
            raise GrblDisconnected(f"lost the connection to the controller at {self.url!r}: {exc}") from None

    def _read_line(self, deadline: float) -> str | None:
        """The next line (CR/LF stripped, decoded), or None when ``deadline`` passes first."""
        port = self._port()
        while True:
            end = self._buffer.find(b"\n")
            if end >= 0:
                raw = bytes(self._buffer[:end])
                del self._buffer[: end + 1]
                line = raw.decode("ascii", errors="replace").strip()
                log.debug("<- %r", line)
                return line
            if time.monotonic() >= deadline:
                return None
            try:
                chunk = port.read(max(1, port.in_waiting))
            except _IO_ERRORS as exc:
                self.close()
                raise GrblDisconnected(f"lost the connection to the controller at {self.url!r}: {exc}") from None
            self._buffer += chunk

    def _next(self, deadline: float, *, in_reset: bool = False) -> tuple[Kind, object] | None:
        """The next line, classified and with pushed messages handled; None at ``deadline``.

        ``ALARM:N`` raises :class:`GrblAlarm` (outside a reset), once the reset that GRBL does by
        itself after a homing alarm has been read; a welcome line outside a reset means the
        controller restarted by itself and raises :class:`GrblProtocolError`.
        """
        line = self._read_line(deadline)
        if line is None:
            return None
        kind, payload = classify(line)
        if kind is Kind.ALARM:
            self.alarm_code = payload
            if not in_reset:
                if payload in HOMING_ALARMS:
                    self._await_self_reset(payload)
                    raise GrblAlarm(payload, alarm_meaning(payload), _HOMING_ALARM_HINT)
                raise GrblAlarm(payload, alarm_meaning(payload), _ALARM_HINT)
        elif kind is Kind.MESSAGE:
            self.messages.append(payload)
            log.info("controller message: %s", payload)
        elif kind is Kind.STATUS:
            self.last_status = payload
            if payload.wco is not None:
                self._wco = payload.wco
        elif kind is Kind.NOISE:
            self.noise_lines.append(line)
            log.warning("ignored a line that is not GRBL 1.1: %r", line)
        elif kind is Kind.WELCOME and not in_reset:
            raise GrblProtocolError(
                f"controller restarted by itself (welcome {line!r} arrived unasked); its position "
                "may be lost: home it or check its power and cable")
        return kind, payload

    # ------------------------------------------------------------------------------- protocol
    def reset(self) -> str:
        """Soft reset (0x18) and wait for the welcome line; returns the firmware version."""
        port = self._port()
        self._buffer.clear()
        try:
            port.reset_input_buffer()
        except (*_IO_ERRORS, AttributeError):
            pass
        self._write(SOFT_RESET)
        start = time.monotonic()
        deadline, resend_at, sent = start + self.timeouts.welcome_s, start + _RESET_RESEND_S, 1
        while True:
            event = self._next(min(deadline, resend_at), in_reset=True)
            now = time.monotonic()
            if event is None and now >= deadline:
                raise GrblTimeout(
                    f"no GRBL welcome line from {self.url!r} within {self.timeouts.welcome_s:.1f} s of "
                    f"{sent} soft reset(s): is a GRBL 1.1 controller connected at {self.baudrate} baud?")
            # Reset again when none came back in time, or when GRBL says it now hears one (the end
            # of its alarm window: a reset sent before that line was cleared).
            if event is None or event == (Kind.MESSAGE, "Reset to continue"):
                log.info("no welcome yet: soft reset again (GRBL drops a reset sent while it reports an alarm)")
                self._write(SOFT_RESET)
                resend_at, sent = now + _RESET_RESEND_S, sent + 1
                continue
            kind, payload = event
            if kind is Kind.WELCOME:
                break
        if sent > 1:
            self._drain_welcomes(0.3)  # a reset sent again may have been heard twice
        if not str(payload).startswith("1.1"):
            raise GrblProtocolError(f"controller runs GRBL {payload}; this driver speaks GRBL 1.1")
        self.version = str(payload)
        self._wco = None
        return self.version

    def _await_self_reset(self, code: int) -> None:
        """Read through the reset GRBL does by itself after homing ``ALARM:code``: the ``ok`` of the
        aborted ``$H`` and the welcome (any line sent meanwhile is dropped by GRBL, unanswered)."""
        deadline = time.monotonic() + self.timeouts.welcome_s
        while True:
            event = self._next(deadline, in_reset=True)
            if event is None:
                log.warning("no welcome within %.1f s of ALARM:%d (GRBL resets itself after a homing alarm)",
                            self.timeouts.welcome_s, code)
                return
            if event[0] is Kind.WELCOME:
                self._wco = None
                self.alarm_code = code
                return

    def _drain_welcomes(self, wait_s: float) -> None:
        """Read what comes within ``wait_s`` as part of the reset (a second welcome is no restart)."""
        deadline = time.monotonic() + wait_s
        while self._next(deadline, in_reset=True) is not None:
            pass

    def _no_answer(self, message: str, doing: str) -> GrblError:
        """What a missing answer means: :class:`GrblHeld` when ``?`` shows a feed hold or an open
        door (GRBL then runs no line but still reports), else :class:`GrblTimeout` with ``message``."""
        try:
            report = self._poll(self.timeouts.status_s)
        except GrblAlarm as exc:
            return exc
        if report is not None and report.state in _HELD_STATES:
            return GrblHeld(report.state, report.substate, doing)
        return GrblTimeout(message)

    def send(self, line: str, timeout_s: float | None = None) -> list[tuple[Kind, object]]:
        """Send one line and wait for its ``ok``; returns the lines that came before it.

        Raises
        ------
        GrblCommandError
            On ``error:N``, with N and its meaning.
        GrblTimeout
            When no ``ok``/``error`` arrives within ``timeout_s`` (default ``timeouts.reply_s``).
        """
        if not isinstance(line, str) or "\n" in line or "\r" in line or not line.isascii():
            raise HbisInputError(f"a GRBL line must be one line of ASCII text, got {line!r}")
        if any(ord(c) in REALTIME_BYTES or (ord(c) < 0x20 and c != "\t") for c in line):
            raise HbisInputError(f"refusing {line!r}: it holds a real-time or control character "
                                 "(GRBL acts on ?, !, ~ and 0x18 wherever they appear, comments included)")
        # Match what GRBL will run, not what was typed: it drops spaces and comments first.
        cleaned = clean_line(line)
        setting = setting_write(line)
        if setting is not None and setting[0] == 13 and int(setting[1]) != 0:
            raise HbisInputError(f"refusing {line!r}: $13=1 makes GRBL report inches, and this driver "
                                 "reads positions as degrees ($13 must stay 0)")
        if setting is not None and setting[0] in (100, 101) and not 0 < setting[1] <= FLOAT32_MAX:
            raise HbisInputError(f"refusing {line!r}: GRBL would store ${setting[0]}={setting[1]:g}, and steps per "
                                 "degree must be positive and finite (the driver could not use the controller after)")
        rereads = cleaned.startswith("$") and "=" in cleaned and not cleaned.startswith("$J=")
        if len(line) >= LINE_MAX_CHARS:
            raise HbisInputError(f"line too long for GRBL ({len(line)} >= {LINE_MAX_CHARS} characters): {line!r}")
        wait = self.timeouts.reply_s if timeout_s is None else float(timeout_s)
        self._write(line.encode("ascii") + b"\n")
        deadline = time.monotonic() + wait
        replies: list[tuple[Kind, object]] = []
        while True:
            event = self._next(deadline)
            if event is None:
                raise self._no_answer(f"no reply from the controller to {line!r} within {wait:.1f} s",
                                      f"(it did not run {line!r})")
            kind, payload = event
            if kind is Kind.OK:
                if rereads:
                    self.read_settings()  # a setting may have changed: what the driver relies on is read again
                return replies
            if kind is Kind.ERROR:
                raise GrblCommandError(payload, error_meaning(payload), line)
            if kind in (Kind.SETTING, Kind.FEEDBACK, Kind.MESSAGE, Kind.STARTUP):
                replies.append(event)

    def resync(self) -> None:
        """Re-align replies with lines after a timeout: discard any late ``ok``/``error``.

        Sends ``$G``, whose ``[GC:...]`` line comes just before its own ``ok``: every ``ok`` or
        ``error`` seen before that line answered something older and is dropped.
        """
        self._write(b"$G\n")
        wait = self.timeouts.reply_s
        deadline = time.monotonic() + wait
        seen_modes = False
        while True:
            event = self._next(deadline)
            if event is None:
                raise self._no_answer(f"controller did not answer '$G' within {wait:.1f} s: it has gone silent",
                                      "(it did not answer '$G')")
            kind, payload = event
            if kind is Kind.FEEDBACK and str(payload).startswith("GC:"):
                seen_modes = True
            elif kind in (Kind.OK, Kind.ERROR):
                if seen_modes:
                    if kind is Kind.ERROR:
                        raise GrblCommandError(payload, error_meaning(payload), "$G")
                    return
                self.stale_replies += 1

    def read_settings(self) -> dict[int, float]:
        """Read ``$$`` and check what the driver relies on ($100/$101 > 0, $13 = 0)."""
        replies = self.send("$$")
        settings = {n: v for kind, (n, v) in ((k, p) for k, p in replies if k is Kind.SETTING)}
        for n, axis in ((100, "X (prism 1)"), (101, "Y (prism 2)")):
            if n not in settings:
                raise GrblProtocolError(f"controller did not report ${n} (steps per degree of {axis}) in $$")
            if not (math.isfinite(settings[n]) and settings[n] > 0):
                raise GrblProtocolError(f"${n} (steps per degree of {axis}) must be positive, got {settings[n]}")
        if settings.get(13, 0) != 0:
            raise GrblProtocolError("controller reports positions in inches ($13=1); set $13=0 so degrees stay degrees")
        self.settings = settings
        return settings

    @property
    def steps_per_deg(self) -> tuple[float, float]:
        """Steps per degree of prism 1 and prism 2 ($100, $101), after the belt ratio."""
        return self.settings[100], self.settings[101]

    @property
    def step_deg(self) -> tuple[float, float]:
        """The smallest turn of each prism, degrees (1 / steps per degree)."""
        return 1.0 / self.settings[100], 1.0 / self.settings[101]

    @property
    def homing_enabled(self) -> bool:
        """Whether ``$22`` enables the homing cycle."""
        return int(self.settings.get(22, 0)) & 1 == 1

    @property
    def position_tolerance_deg(self) -> tuple[float, float]:
        """How far MPos may sit from a target it reached: half a step plus the 0.001 print rounding."""
        return tuple(0.5 / s + 1.1e-3 for s in self.steps_per_deg)

    # --------------------------------------------------------------------------------- status
    def _poll(self, wait_s: float) -> GrblStatus | None:
        """Send ``?`` and return the report, or None if none came within ``wait_s``."""
        self._write(STATUS_QUERY)
        deadline = time.monotonic() + wait_s
        while True:
            event = self._next(deadline)
            if event is None:
                return None
            kind, payload = event
            if kind is Kind.STATUS:
                return payload
            if kind in (Kind.OK, Kind.ERROR):
                self.stale_replies += 1

    def status(self) -> GrblStatus:
        """One status report.

        Raises :class:`GrblAlarm` if none comes after an ``ALARM:N`` (GRBL ignores ``?`` after a
        limit alarm until a soft reset), else :class:`GrblTimeout` if none comes.
        """
        for _ in range(2):  # GRBL may drop a '?' that arrives while it is busy: ask twice
            report = self._poll(self.timeouts.status_s)
            if report is not None:
                return report
        if self.alarm_code is not None:
            raise GrblAlarm(self.alarm_code, alarm_meaning(self.alarm_code),
                            "it answers no status query until a soft reset: reconnect (the driver resets "
                            "on opening), then home ($H) or unlock ($X)")
        raise GrblTimeout(f"no status report from the controller within 2 x {self.timeouts.status_s:.1f} s")

    def machine_position(self, report: GrblStatus) -> tuple[float, float]:
        """(X, Y) machine position in degrees from a report (``MPos``, or ``WPos + WCO``)."""
        if report.mpos is not None:
            pos = report.mpos
        elif self._wco is not None:
            pos = tuple(w + o for w, o in zip(report.wpos, self._wco))
        else:
            raise GrblProtocolError("status reports WPos but no WCO has arrived yet; set $10=1 so GRBL reports MPos")
        if len(pos) < 2:
            raise GrblProtocolError(f"status report has fewer than two axes: {report.raw!r}")
        return float(pos[0]), float(pos[1])

    def phases_deg(self, near: tuple[float, float] | None = None) -> tuple[float, float]:
        """Current prism phases (MPos + offset), degrees; unwrapped next to ``near`` if given."""
        x, y = self.machine_position(self.status())
        phases = (x + self.phase_offset_deg[0], y + self.phase_offset_deg[1])
        if near is not None:
            phases = (unwrap_near(phases[0], near[0]), unwrap_near(phases[1], near[1]))
        # MPos is printed to 0.001 deg; rounding to 1e-6 only drops the float noise of the sums
        return round(phases[0], 6), round(phases[1], 6)

    def nearest_reachable(self, phi1_deg: float, phi2_deg: float) -> tuple[float, float]:
        """The phases nearest (phi1, phi2) that the motors can stop at, from where they are now.

        A scan planned from these initial phases is quantised by the controller exactly as the
        scan planner's step model assumes (whole steps counted from the initial phases).
        """
        here = self.machine_position(self.status())
        return tuple(nearest_step_phase(p, s, o, m) for p, s, o, m in
                     zip((float(phi1_deg), float(phi2_deg)), self.steps_per_deg, self.phase_offset_deg, here))

    # --------------------------------------------------------------------------------- motion
    def estimate_move_s(self, start: tuple[float, float], end: tuple[float, float],
                        feed_deg_per_min: float | None = None) -> float:
        """Rough duration of a straight move between machine positions, seconds."""
        delta = (end[0] - start[0], end[1] - start[1])
        length = math.hypot(*delta)
        if length == 0:
            return 0.0
        unit = (delta[0] / length, delta[1] / length)
        rates = tuple(self.settings.get(n, _DEFAULT_RATE_DEG_PER_MIN) / 60.0 for n in (110, 111))
        accels = tuple(self.settings.get(n, _DEFAULT_ACCEL_DEG_PER_S2) for n in (120, 121))
        speed = axis_limited(unit, rates)
        if feed_deg_per_min is not None:
            speed = min(speed, feed_deg_per_min / 60.0)
        return move_duration_s(length, speed, axis_limited(unit, accels))

    def _check_ready(self) -> GrblStatus:
        """The status once the controller is Idle; a move still running (say one whose ``ok`` was
        lost) is waited for, as long as the longest move this driver sends (half a turn)."""
        report = self.status()
        if report.state in ("Run", "Jog"):
            longest = self.estimate_move_s((0.0, 0.0), (180.0, 180.0))
            deadline = time.monotonic() + 2.0 * longest + self.timeouts.move_margin_s
            while report.state in ("Run", "Jog") and time.monotonic() < deadline:
                time.sleep(self.poll_interval_s)
                report = self.status()
        if report.state == "Alarm":
            raise GrblAlarm(self.alarm_code, alarm_meaning(self.alarm_code) if self.alarm_code
                            else "motion is locked", "home ($H) or unlock ($X) first")
        if report.state in _HELD_STATES:
            raise GrblHeld(report.state, report.substate)
        if report.state != "Idle":
            raise GrblError(f"controller is in state {report.state}, not Idle; wait for it or reset it")
        return report

    def move_to(self, phi1_deg: float, phi2_deg: float, *, feed_deg_per_min: float | None = None,
                timeout_s: float | None = None) -> tuple[float, float]:
        """Turn the prisms to phases (phi1, phi2) the short way; wait until they are there.

        Each axis goes to the machine position equal to its target modulo 360 that is nearest
        its present one, so no prism turns more than 180 degrees. The move is absolute (G53).

        Parameters
        ----------
        phi1_deg, phi2_deg : float
            Target phases of prism 1 and prism 2, degrees.
        feed_deg_per_min : float, optional
            Feed for a G1 move; default a G0 rapid at the controller's $110/$111.
        timeout_s : float, optional
            Deadline for reaching the target; default twice the estimate plus a margin.

        Returns
        -------
        (float, float)
            Phases read back from MPos after the move, unwrapped next to the targets, degrees.
        """
        target = (float(phi1_deg), float(phi2_deg))
        if not all(math.isfinite(v) and abs(v) <= MAX_PHASE_DEG for v in target):
            raise HbisInputError(f"target phases must be finite degrees within +-{MAX_PHASE_DEG:g}, got {target}")
        if feed_deg_per_min is not None and not (math.isfinite(feed_deg_per_min) and feed_deg_per_min > 0):
            raise HbisInputError(f"feed must be a finite positive number of deg/min, got {feed_deg_per_min!r}")
        start = self.machine_position(self._check_ready())
        goal = tuple(unwrap_near(t - o, s) for t, o, s in zip(target, self.phase_offset_deg, start))
        line = format_move(goal[0], goal[1], feed_deg_per_min)
        if timeout_s is None:
            timeout_s = 2.0 * self.estimate_move_s(start, goal, feed_deg_per_min) + self.timeouts.move_margin_s
        self.send(line)
        self.wait_until_at(goal, timeout_s)
        return self.phases_deg(near=target)

    def wait_until_at(self, goal: tuple[float, float], timeout_s: float) -> GrblStatus:
        """Poll until the controller is Idle at machine position ``goal`` (within a half step)."""
        tolerance = self.position_tolerance_deg
        deadline = time.monotonic() + timeout_s
        idle_grace = max(0.5, 5 * self.poll_interval_s)
        idle_elsewhere_since = None
        report = None
        while True:
            polled = self._poll(min(self.timeouts.status_s, max(0.0, deadline - time.monotonic()) + 0.05))
            report = polled or report
            if polled is not None:
                if polled.state == "Alarm":
                    raise GrblAlarm(self.alarm_code, alarm_meaning(self.alarm_code) if self.alarm_code
                                    else "motion is locked", _ALARM_HINT)
                pos = self.machine_position(polled)
                arrived = all(abs(p - g) <= t for p, g, t in zip(pos, goal, tolerance))
                if polled.state == "Idle" and arrived:
                    return polled
                if polled.state == "Idle":
                    idle_elsewhere_since = idle_elsewhere_since or time.monotonic()
                    if time.monotonic() - idle_elsewhere_since > idle_grace:
                        raise GrblMoveLost(
                            f"controller stopped at X{pos[0]:.3f} Y{pos[1]:.3f} but was sent to "
                            f"X{goal[0]:.3f} Y{goal[1]:.3f}: the move was lost or cut short")
                else:
                    idle_elsewhere_since = None
            if time.monotonic() >= deadline:
                if report is not None and report.state in _HELD_STATES:
                    raise GrblHeld(report.state, report.substate,
                                   f"short of X{goal[0]:.3f} Y{goal[1]:.3f} after {timeout_s:.1f} s")
                last = f"last state {report.state}" if report else "no status report"
                raise GrblTimeout(f"prisms did not reach X{goal[0]:.3f} Y{goal[1]:.3f} within {timeout_s:.1f} s ({last})")
            time.sleep(self.poll_interval_s)

    def unlock(self) -> None:
        """Leave the Alarm state without homing (``$X``); the position may be wrong afterwards."""
        self.send("$X")
        self.alarm_code = None

    def home(self) -> GrblStatus:
        """Run the homing cycle (``$H``); needs homing enabled (``$22=1``) and switches."""
        if not self.homing_enabled:
            raise GrblError("homing is not enabled on the controller ($22=0): set $22=1 if the "
                            "prisms have home switches, or unlock with $X instead")
        self.send("$H", timeout_s=self.timeouts.homing_s)
        self.alarm_code = None
        return self.status()

    def jog(self, dphi1_deg: float, dphi2_deg: float, feed_deg_per_min: float) -> None:
        """Start a relative jog (``$J=``); it runs until done or :meth:`jog_cancel`."""
        values = (float(dphi1_deg), float(dphi2_deg), float(feed_deg_per_min))
        if not all(math.isfinite(v) for v in values) or values[2] <= 0:
            raise HbisInputError(f"jog needs finite turns and a positive feed, got {values}")
        self.send(format_jog(*values))

    def jog_cancel(self, timeout_s: float | None = None) -> GrblStatus:
        """Stop a jog at once (real-time 0x85) and wait until the controller is Idle again."""
        self._write(JOG_CANCEL)
        deadline = time.monotonic() + (timeout_s or self.timeouts.move_margin_s)
        while True:
            report = self._poll(self.timeouts.status_s)
            if report is not None and report.state == "Idle":
                return report
            if time.monotonic() >= deadline:
                raise GrblTimeout("controller did not come to Idle after a jog cancel")
            time.sleep(self.poll_interval_s)


def open_grbl(url: str, **kwargs) -> GrblController:
    """Open a :class:`GrblController` at ``url`` (handshake and settings done); close it after use."""
    return GrblController(url, **kwargs).open()
