"""A simulated GRBL 1.1 controller on a pseudo-terminal (or a TCP port), for tests and for trying
the motor commands without hardware.

The machine itself is :class:`~.sim_machine.GrblMachineModel`; this module gives it a serial line and
a clock. On the default pseudo-terminal the driver talks through the real pyserial path to the
slave side (``/dev/pts/N``), exactly as to a USB serial adapter::

    with GrblSimulator(speedup=20) as sim:
        with GrblController(sim.port).open() as grbl:
            grbl.move_to(5.0, 70.0)

Run it from a shell (it prints the port and serves until Ctrl-C or ``--duration``)::

    python -m hbis_torch.hardware.simulator            # or: hbis motors simulate
    hbis motors --port /dev/pts/7 status               # in another terminal
"""

from __future__ import annotations

import argparse
import math
import os
import select
import socket
import sys
import threading
import time
import tty

from hbis_torch.hardware.sim_machine import VERSION, GrblMachineModel
from hbis_torch.hardware.simulator_args import add_simulator_args


class _PtyLine:
    """The master side of a pseudo-terminal pair; the client opens the slave by its name."""

    def __init__(self):
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)  # no echo, no CR/LF translation: a plain 8-bit line
        os.set_blocking(self.master, False)
        self.name = os.ttyname(self.slave)

    def read(self, timeout_s: float) -> bytes:
        ready, _, _ = select.select([self.master], [], [], timeout_s)
        if not ready:
            return b""
        try:
            return os.read(self.master, 4096)
        except (BlockingIOError, InterruptedError):
            return b""

    def write(self, data: bytes) -> bytes:
        """Write what the line takes now; returns the rest (a client not reading fills it up)."""
        try:
            sent = os.write(self.master, data)
        except BlockingIOError:
            sent = 0
        return data[sent:]

    def close(self) -> None:
        for fd in (self.master, self.slave):
            try:
                os.close(fd)
            except OSError:
                pass


class _TcpLine:
    """A TCP listener on localhost serving one client at a time (pyserial ``socket://``)."""

    def __init__(self, port: int = 0):
        self.server = socket.create_server(("127.0.0.1", port))
        self.server.setblocking(False)
        self.client: socket.socket | None = None
        self.name = f"socket://127.0.0.1:{self.server.getsockname()[1]}"

    def read(self, timeout_s: float) -> bytes:
        sock = self.client or self.server
        ready, _, _ = select.select([sock], [], [], timeout_s)
        if not ready:
            return b""
        if self.client is None:
            self.client, _ = self.server.accept()
            self.client.setblocking(False)
            return b""
        try:
            data = self.client.recv(4096)
        except (BlockingIOError, InterruptedError):
            return b""
        except OSError:
            data = b""
        if not data:  # the client went away; wait for the next one
            self.client.close()
            self.client = None
        return data

    def write(self, data: bytes) -> bytes:
        if self.client is None:
            return b""  # nobody listening: the bytes are lost, as on an unplugged line
        try:
            sent = self.client.send(data)
        except BlockingIOError:
            sent = 0
        except OSError:
            return b""
        return data[sent:]

    def close(self) -> None:
        for sock in (self.client, self.server):
            if sock is not None:
                sock.close()
        self.client = None


class GrblSimulator:
    """A :class:`GrblMachineModel` served on a serial line by a background thread.

    Parameters
    ----------
    settings : dict, optional
        ``$N`` overrides, e.g. ``{100: 80.0, 101: 80.0, 22: 1}``.
    speedup : float
        Simulated motion runs this many times faster than the modelled machine (tests use 20-100).
    tcp_port : int, optional
        Serve on ``socket://127.0.0.1:PORT`` (0 picks a free port) instead of a pseudo-terminal.
    max_lifetime_s : float
        The thread stops by itself after this long, whatever happens.
    seed : int
        Seed of the injected noise bytes.

    Attributes
    ----------
    port : str
        What to give pyserial: ``/dev/pts/N`` or ``socket://127.0.0.1:PORT``.
    machine : GrblMachineModel
        The simulated controller (read its state in tests; arm faults with :meth:`inject`).
    """

    def __init__(self, settings: dict | None = None, *, speedup: float = 1.0, tcp_port: int | None = None,
                 max_lifetime_s: float = 600.0, seed: int = 0):
        if not speedup > 0:
            raise ValueError(f"speedup must be positive, got {speedup!r}")
        self.machine = GrblMachineModel(settings or {}, seed=seed)
        self.speedup = float(speedup)
        self.max_lifetime_s = float(max_lifetime_s)
        if not self.max_lifetime_s > 0:  # NaN fails this too; inf (serve until stopped) passes
            from hbis_torch.errors import HbisInputError

            raise HbisInputError(f"the simulator's lifetime must be a positive number of seconds, got {max_lifetime_s!r}")
        self._tcp_port = tcp_port
        self._line = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self.port = ""

    def start(self) -> "GrblSimulator":
        """Open the line and start serving; returns self (``port`` is set)."""
        self._line = _PtyLine() if self._tcp_port is None else _TcpLine(self._tcp_port)
        self.port = self._line.name
        self._thread = threading.Thread(target=self._serve, name=f"grbl-sim {self.port}", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        """Stop serving and close the line (safe to call twice)."""
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=5.0)
        if self._line is not None:
            self._line.close()
            self._line = None

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def inject(self, kind: str, after_moves: int = 0, code: int | None = None) -> None:
        """Arm a fault (see :class:`~.sim_machine.Fault`); thread-safe."""
        with self._lock:
            self.machine.inject(kind, after_moves, code)

    def fail_next_homing(self, code: int = 8) -> None:
        """Make the next homing cycle end in ``ALARM:code`` (see
        :meth:`~.sim_machine.GrblMachineModel.fail_next_homing`); thread-safe."""
        with self._lock:
            self.machine.fail_next_homing(code)

    def __enter__(self) -> "GrblSimulator":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    def _serve(self) -> None:
        line, machine = self._line, self.machine
        t0 = time.monotonic()
        pending = b""
        while not self._stop.is_set() and time.monotonic() - t0 < self.max_lifetime_s:
            with self._lock:
                busy = machine.busy() or bool(pending)
            data = line.read(0.002 if busy else 0.02)
            now = (time.monotonic() - t0) * self.speedup
            with self._lock:
                if data:
                    machine.receive(data, now)
                else:
                    machine.tick(now)
                pending += machine.take_output()
                hung_up = machine.hung_up
            if pending:
                pending = line.write(pending)
            if hung_up:  # the "disconnect" fault: drop the line as a pulled cable would
                line.close()
                self._line = None
                break
        self._stop.set()


def _parse_pair(text: str, what: str) -> tuple[float, float]:
    from hbis_torch.errors import HbisInputError

    try:
        a, b = (float(v) for v in text.split(","))
    except ValueError:
        raise HbisInputError(f"{what} must be two numbers separated by a comma, got {text!r}") from None
    return a, b


def simulator_from_args(args) -> GrblSimulator:
    """Build (not start) the simulator the options describe; raises HbisInputError on bad ones."""
    from hbis_torch.errors import HbisInputError

    settings: dict[int, float] = {}
    if args.steps_per_deg:
        s1, s2 = _parse_pair(args.steps_per_deg, "--steps-per-deg")
        if not (s1 > 0 and s2 > 0):
            raise HbisInputError(f"--steps-per-deg must be positive, got {args.steps_per_deg!r}")
        settings.update({100: s1, 101: s2})
    if args.homing:
        settings[22] = 1
    if not (args.speedup > 0):
        raise HbisInputError(f"--speedup must be positive, got {args.speedup!r}")
    if args.duration is not None and not (math.isfinite(args.duration) and args.duration > 0):
        raise HbisInputError(f"--duration must be a finite positive number of seconds, got {args.duration!r}")
    lifetime = args.duration if args.duration is not None else float("inf")
    sim = GrblSimulator(settings, speedup=args.speedup, tcp_port=args.tcp, max_lifetime_s=lifetime)
    for spec in args.fault:
        kind, *rest = spec.split(":")
        try:
            sim.inject(kind, int(rest[0]) if rest else 0, int(rest[1]) if len(rest) > 1 else None)
        except ValueError as exc:
            raise HbisInputError(f"bad --fault {spec!r}: {exc}") from None
    return sim


def serve_until_done(sim: GrblSimulator, out=sys.stdout) -> int:
    """Start ``sim``, print its port, serve until its lifetime ends, it hangs up, or Ctrl-C."""
    sim.start()
    print(f"GRBL {VERSION} simulator serving on {sim.port}", file=out)
    print(f"try: hbis motors --port {sim.port} status", file=out, flush=True)
    try:
        while sim.running:
            time.sleep(0.1)
    except KeyboardInterrupt:
        pass
    finally:
        sim.stop()
    return 0


def main(argv: list[str] | None = None) -> int:
    """``python -m hbis_torch.hardware.simulator``."""
    from hbis_torch.errors import HbisInputError

    parser = argparse.ArgumentParser(prog="python -m hbis_torch.hardware.simulator",
                                     description="A simulated GRBL 1.1 prism controller on a pseudo-terminal.")
    add_simulator_args(parser)
    args = parser.parse_args(argv)
    try:
        sim = simulator_from_args(args)
    except HbisInputError as exc:
        print(f"simulator: error: {exc}", file=sys.stderr)
        return 2
    return serve_until_done(sim)


if __name__ == "__main__":
    sys.exit(main())
