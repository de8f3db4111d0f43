"""Opening a serial port for the GRBL driver, and telling a wrong argument from an unplugged device.

A path that exists but can never be a serial port (a directory, a regular file, a FIFO, a
character device that is no terminal such as ``/dev/null``) is a wrong argument: one line,
:class:`~hbis_torch.errors.HbisInputError`, exit 2. A port that cannot be opened otherwise (a
missing device: an unplugged adapter) is the bench's fault: :class:`~hbis_torch.errors.GrblError`,
exit 3, worth a retry.
"""

from __future__ import annotations

import os
import stat

import serial

from hbis_torch.errors import GrblError, HbisInputError

try:  # pyserial's POSIX backend lets termios.error (not an OSError) out of flush() on a dead tty
    from termios import error as _TermiosError
except ImportError:  # Windows
    _TermiosError = OSError

#: What a serial port's reads, writes and closes raise when the link fails.
IO_ERRORS = (serial.SerialException, OSError, _TermiosError)


def open_serial_port(url: str, baudrate: int, write_timeout_s: float):
    """A pyserial port for ``url`` (a device path or a pyserial URL such as ``socket://``), read
    timeout 0.02 s.

    Raises
    ------
    HbisInputError
        ``url`` names something that can never be a serial port.
    GrblError
        The port cannot be opened otherwise.
    """
    why = _never_a_serial_port(url)
    if why is not None:
        raise HbisInputError(f"{url!r} cannot be a serial port: {why}")
    try:
        return serial.serial_for_url(url, baudrate=baudrate, timeout=0.02, write_timeout=write_timeout_s)
    except (*IO_ERRORS, ValueError) as exc:
        if _not_a_terminal(url):
            raise HbisInputError(f"{url!r} cannot be a serial port: it is a character device "
                                 "that is not a terminal") from None
        raise GrblError(f"cannot open serial port {url!r}: {exc}") from None


def _never_a_serial_port(url: str) -> str | None:
    """Why the file at ``url`` can never be a serial port (a directory, a regular file, a FIFO...:
    anything but a character device), or None when it may be one, is missing (an unplugged
    adapter) or ``url`` is a pyserial URL such as ``socket://``.

    Judged from :func:`os.stat` alone, before anything is opened. Whether a character device is a
    terminal (:func:`_not_a_terminal`) is asked only after pyserial failed to open it, so a real
    serial port is never opened twice.
    """
    if "://" in url:
        return None
    try:
        mode = os.stat(url).st_mode
    except (OSError, ValueError):
        return None
    if stat.S_ISDIR(mode):
        return "it is a directory"
    if stat.S_ISREG(mode):
        return "it is a regular file"
    if not stat.S_ISCHR(mode):
        return "it is not a character device"
    return None


def _not_a_terminal(url: str) -> bool:
    """Whether the character device at ``url`` opens but is no terminal (``/dev/null``)."""
    if "://" in url:
        return False
    try:
        fd = os.open(url, os.O_RDONLY | os.O_NOCTTY | os.O_NONBLOCK)
    except (OSError, ValueError, AttributeError):  # O_NOCTTY is POSIX only
        return False
    try:
        return not os.isatty(fd)
    finally:
        os.close(fd)
