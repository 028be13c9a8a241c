"""Modbus RTU on a serial port: an RS485 adapter, a UART, a pseudo-terminal, a pyserial URL.

What is the serial port's own and no other line's: the device opened exclusively and in the
kernel's RS485 mode where configured (:mod:`gateway.line.transports.port_access`), an FTDI adapter's
latency timer read and warned of, the bytes read and written with one system call each,
a pseudo-terminal told apart by its device number, and the bytes the kernel holds that the
event loop has not handed over yet. The transactions are
:class:`~gateway.line.transports.rtu.RtuLine`'s.

A port given as one of pyserial's URLs (``rfc2217://``, ``loop://``, ``spy://``...) is a
serial port too, opened by pyserial's handler for it: not locked (there is no device node),
and its answers not judged by the wire time (the line behind it is out of sight).
``socket://`` is not among them: :mod:`gateway.line.transports.rtu_over_tcp` carries it.
"""

from __future__ import annotations

import asyncio
import logging
import os
import select
import stat
import termios
from pathlib import Path
from typing import TYPE_CHECKING, Final, cast

import serial
import serial_asyncio_fast

from gateway.config.echo import EchoMode
from gateway.errors import BusClosedError, PortUnavailableError
from gateway.line.transports import port_access
from gateway.line.transports.port_diagnosis import PortReason
from gateway.line.transports.rtu import RtuLine

if TYPE_CHECKING:
    from gateway.line.stats import LineStats
    from gateway.line.transports.inbox import Inbox
    from gateway.wire.timing import LineFormat

_LOGGER = logging.getLogger(__name__)


class SerialLine(RtuLine):
    """One local serial device and the RTU transactions on it."""

    def __init__(
        self,
        *,
        port: str,
        line: LineFormat,
        stats: LineStats | None = None,
        bus: str = "",
        echo: EchoMode = EchoMode.AUTO,
        options: port_access.PortOptions | None = None,
    ) -> None:
        """Describe the line; :meth:`open` opens it. ``bus`` names it in log lines.

        ``options``: how the port is opened (RS485 mode, shared-bus hints, system roots).
        """
        url = "://" in port
        super().__init__(
            port=port, line=line, stats=stats, bus=bus, echo=echo, judges_by_wire=not url
        )
        self._url = url
        self.options = options or port_access.PortOptions()
        self._latency_warned = False
        self._serial: serial.Serial | None = None

    async def _connect(self, inbox: Inbox) -> asyncio.Transport:
        """Open the device exclusively; one that cannot be opened raises :class:`BusClosedError`.

        A device that is missing, not permitted, in use or without the configured RS485
        mode raises :class:`PortUnavailableError` with its ``reason``
        (:mod:`gateway.line.transports.port_diagnosis`); its message names the remedy.
        """
        # A pseudo-terminal has no physical line: some kernels refuse a parity setting on
        # it (EINVAL), so parity is left off there. Timing still follows the configured
        # format, which is what the simulator on the other end referees.
        if self._url:
            return await self._connect_url(inbox)
        pty = _is_pseudo_terminal(self.port)
        parity = "N" if pty else self.format.parity
        try:
            opened = await port_access.open_device(
                self.port,
                self.format,
                parity=parity,
                tiocexcl=not pty,
                options=self.options,
                protocol=inbox,
            )
        except PortUnavailableError as exc:
            self.stats.closed_because(exc.reason, str(exc))
            raise
        except (OSError, ValueError, termios.error) as exc:
            # termios.error is no OSError: a line setting the port refuses (tcsetattr)
            # would otherwise end the gateway instead of this bus's retry with backoff.
            # (pyserial's SerialException is an OSError.)
            message = f"cannot open {self.port}: {exc}"
            self.stats.closed_because(PortReason.DRIVER, message)
            raise BusClosedError(message) from exc
        _direct_io(opened.transport.serial)
        self.stats.latency_timer_s = opened.latency_timer_s
        if opened.latency_advice is not None and not self._latency_warned:
            self._latency_warned = True  # once per line, not at every reconnection
            _LOGGER.warning("%s", opened.latency_advice)
        # The serial port under the transport, looked at before every request.
        self._serial = cast("serial.Serial | None", opened.transport.get_extra_info("serial"))
        return opened.transport

    async def _connect_url(self, inbox: Inbox) -> asyncio.Transport:
        """A pyserial URL, opened by its handler (``serial_for_url``)."""
        try:
            transport, _ = await serial_asyncio_fast.create_serial_connection(
                asyncio.get_running_loop(),
                lambda: inbox,
                self.port,
                baudrate=self.format.baudrate,
                parity=self.format.parity,
                stopbits=self.format.stopbits,
                bytesize=8,
            )
        except (OSError, ValueError, termios.error) as exc:
            message = f"cannot open {self.port}: {exc}"
            self.stats.closed_because(PortReason.DRIVER, message)
            raise BusClosedError(message) from exc
        self._serial = cast("serial.Serial | None", transport.get_extra_info("serial"))
        return transport

    def _release(self, transport: asyncio.Transport) -> None:
        """TIOCEXCL off, for a clean stop; the device is closed with the transport."""
        self._serial = None
        port_access.release(transport.get_extra_info("serial"))

    def _unread_input(self) -> bool:
        """Whether the kernel holds bytes the inbox has not seen (one ioctl, no read)."""
        port = self._serial
        if port is None or not port.is_open:
            return False  # the port went away: the write or the inbox will say so
        try:
            return bool(port.in_waiting)
        except (OSError, TypeError, serial.SerialException):
            return False  # closed meanwhile (pyserial then has no file descriptor)


def _direct_io(device: serial.Serial | None) -> None:
    """Let the transport read and write the device with one ``os.read``/``os.write``.

    pyserial-asyncio-fast calls the port's ``read`` when the event loop has seen it
    readable; pyserial then makes two timeout objects, calls ``select`` once more and
    only then ``os.read`` (a system call and some 15 Python calls per answer, for what
    the loop already knew: 7.5 against 3 µs a read, measured on a pseudo-terminal); the
    replacement asks ``select`` only when a read comes back empty. Its
    non-blocking ``write`` makes a timeout object around one ``os.write``. The
    replacements keep pyserial's verdicts: nothing to read (``EAGAIN``, ``EINTR``) is
    no data, a read that fails or finds the device gone (readable, yet nothing) is a
    :class:`serial.SerialException`, which the transport turns into a lost connection;
    a write the kernel cannot take now (``EAGAIN``) is left to the transport's buffer
    (pyserial spun on it), a failed one is a :class:`serial.SerialException`. Only a
    port opened as a local device gets them.
    """
    fd = getattr(device, "fd", None)
    if device is None or not isinstance(fd, int):
        return

    def read(size: int = 1) -> bytes:
        try:
            data = os.read(fd, size)
        except (BlockingIOError, InterruptedError):
            return b""
        except OSError as exc:
            raise serial.SerialException(f"read failed: {exc}") from exc
        if not data and select.select([fd], [], [], 0)[0]:
            # Readable, yet nothing: the device is gone (a tty in raw mode reads nothing,
            # not EAGAIN, when it merely has nothing, so readiness tells the two apart).
            raise serial.SerialException(
                "device reports readiness to read but returned no data "
                "(device disconnected or multiple access on port?)"
            )
        return data

    def write(data: bytes | bytearray | memoryview) -> int:
        try:
            return os.write(fd, data)
        except (BlockingIOError, InterruptedError):
            raise
        except OSError as exc:
            raise serial.SerialException(f"write failed: {exc}") from exc

    device.read = read  # type: ignore[method-assign]
    device.write = write  # type: ignore[method-assign,assignment]


# Unix98 pseudo-terminal slaves: character devices of majors 136..143 (the kernel's
# Documentation/admin-guide/devices.txt), wherever their node is reached from.
PTY_SLAVE_MAJORS: Final = range(136, 144)


def _is_pseudo_terminal(port: str) -> bool:
    """Whether ``port`` is a pseudo-terminal, by its device number, not its path.

    A pty bound at another path (``/dev/ttyUSB0`` in a container, a bind mount) is still
    one; its path alone said otherwise, and the parity setting then failed.
    """
    if "://" in port:
        return False
    try:
        mode = Path(port).stat()
    except OSError:
        return False  # opening it will say what is wrong
    return stat.S_ISCHR(mode.st_mode) and os.major(mode.st_rdev) in PTY_SLAVE_MAJORS
