"""Opening a serial device as a master of its line: alone, in the kernel's RS485 mode, tuned.

One master per line: two masters on one RS485 line corrupt each other's frames, so the port
is opened exclusively, twice over. An advisory lock (``flock``, as pyserial's
``exclusive=True``) stops every program that asks for one, root included, and goes with the
process; ``TIOCEXCL`` (tty_ioctl(4)) makes the kernel refuse any further ``open()`` with
``EBUSY``, but root (``CAP_SYS_ADMIN``) passes it, so the lock is what stops a second
gateway run as root.

``TIOCEXCL`` is a flag of the tty, not of the process: it stays until the tty's last close.
A pseudo-terminal's slave is usually held open by the program on its master side (the
simulator, a relay), so a gateway killed with SIGKILL left it set, and the service
restarted as its unprivileged user found its own port busy for good (the systemd test's
restart after SIGKILL). So a pseudo-terminal gets the lock only; a real serial device,
whose tty ends with its last opener, gets both, and a clean close clears the flag.

An RS485 UART without automatic direction control needs the kernel's RS485 mode
(``TIOCSRS485``) to switch its driver between sending and receiving; a bus with ``rs485:``
gets it, and a driver without it is a port that cannot open. A port that cannot be opened
raises :class:`~gateway.errors.PortUnavailableError` with its reason and remedy
(:mod:`gateway.line.transports.port_diagnosis`); a USB adapter, once open, is tuned
(:mod:`gateway.line.transports.usb_adapter`) before the device is handed to asyncio.
"""

from __future__ import annotations

import asyncio
import contextlib
import fcntl
import functools
import logging
import termios
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import serial
import serial_asyncio_fast
from serial.rs485 import RS485Settings

from gateway.errors import PortUnavailableError
from gateway.line.transports.port_diagnosis import PortReason, port_unavailable, strerror
from gateway.line.transports.port_names import SystemRoots
from gateway.line.transports.usb_adapter import tune_usb

if TYPE_CHECKING:
    from gateway.config.rs485 import Rs485Config
    from gateway.wire.timing import LineFormat

_LOGGER = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True, kw_only=True)
class PortOptions:
    """How to open one bus's port, beyond its line format.

    ``shared_bus`` holds how other programs can reach the line through the gateway that
    owns it (``shared_bus.listen``), for the message of a port in use.
    """

    rs485: Rs485Config | None = None
    shared_bus: tuple[str, ...] = ()
    roots: SystemRoots = field(default_factory=SystemRoots)


def rs485_settings(config: Rs485Config) -> RS485Settings:
    """The config's RS485 block as pyserial's settings (its delays are seconds, ours ms)."""
    return RS485Settings(
        rts_level_for_tx=config.rts_level_for_tx,
        rts_level_for_rx=config.rts_level_for_rx,
        loopback=config.rx_during_tx,
        delay_before_tx=config.delay_before_tx_ms / 1000,
        delay_before_rx=config.delay_before_rx_ms / 1000,
    )


def open_serial(
    port: str,
    *,
    baudrate: int,
    parity: str,
    stopbits: int,
    options: PortOptions,
    tiocexcl: bool = True,
) -> serial.Serial:
    """Open a serial device exclusively and set it up, or raise :class:`PortUnavailableError`.

    Blocking (a few system calls): the caller runs it in an executor.
    """
    device = serial.Serial()
    device.port = port
    device.baudrate = baudrate
    device.parity = parity
    device.stopbits = stopbits
    device.bytesize = serial.EIGHTBITS
    device.exclusive = True  # flock(LOCK_EX | LOCK_NB) before any setting is changed
    try:
        device.open()
    except (serial.SerialException, OSError, termios.error) as exc:
        # termios.error is no OSError: a setting the port refuses (tcsetattr).
        raise port_unavailable(
            port, exc, roots=options.roots, shared_bus=options.shared_bus
        ) from exc
    try:
        if tiocexcl:
            _exclusive_open(device)
        if options.rs485 is not None:
            _rs485_mode(device, port, options.rs485)
    except BaseException:
        device.close()
        raise
    return device


@dataclass(frozen=True, slots=True)
class OpenedDevice:
    """A serial device opened for a line: its transport, and its adapter's latency timer."""

    transport: serial_asyncio_fast.SerialTransport
    latency_timer_s: float | None  # an FTDI adapter's, else None
    latency_advice: str | None  # the warning for a timer above 2 ms, else None


async def open_device(
    port: str,
    line: LineFormat,
    *,
    parity: str,
    tiocexcl: bool,
    options: PortOptions,
    protocol: asyncio.Protocol,
) -> OpenedDevice:
    """Open a serial device exclusively (in an executor), tune it, and wrap it for asyncio.

    ``parity`` may differ from the line's (a pseudo-terminal takes none); ``tiocexcl``:
    whether the kernel's exclusive mode is set too (not on a pseudo-terminal, see above).
    Raises :class:`PortUnavailableError` when it cannot be opened.
    """
    loop = asyncio.get_running_loop()
    device = await loop.run_in_executor(
        None,
        functools.partial(
            open_serial,
            port,
            baudrate=line.baudrate,
            parity=parity,
            stopbits=line.stopbits,
            tiocexcl=tiocexcl,
            options=options,
        ),
    )
    latency_s, advice = tune_usb(device, options.roots)
    transport, _ = await serial_asyncio_fast.connection_for_serial(loop, lambda: protocol, device)
    return OpenedDevice(transport=transport, latency_timer_s=latency_s, latency_advice=advice)


def _exclusive_open(device: serial.Serial) -> None:
    """TIOCEXCL: the kernel refuses other opens (EBUSY) while this one is open."""
    try:
        fcntl.ioctl(device.fileno(), termios.TIOCEXCL)
    except OSError as exc:  # not a tty at all: the lock alone guards it
        _LOGGER.debug("%s: TIOCEXCL refused: %s", device.port, exc)


def release(device: object) -> None:
    """Clear ``TIOCEXCL`` before a close: the flag would outlive this process's descriptor."""
    fileno = getattr(device, "fileno", None)
    if not getattr(device, "is_open", False) or fileno is None:
        return
    with contextlib.suppress(OSError, ValueError, serial.SerialException):
        fcntl.ioctl(fileno(), termios.TIOCNXCL)


def _rs485_mode(device: serial.Serial, port: str, config: Rs485Config) -> None:
    try:
        device.rs485_mode = rs485_settings(config)
    except (ValueError, OSError) as exc:  # pyserial raises ValueError for the ioctl's OSError
        cause = exc.__context__ if isinstance(exc.__context__, OSError) else exc
        raise PortUnavailableError(
            f"cannot open {port} in the kernel's RS485 mode: its driver has none (TIOCSRS485: "
            f"{strerror(cause)}). For a USB adapter: use one with automatic direction "
            "control and remove `rs485:` from the bus. For an RS485 HAT: load the driver "
            "its maker names in /boot/firmware/config.txt (e.g. `dtoverlay=sc16is752-spi1`: "
            "the sc16is7xx driver has the mode, and `linux,rs485-enabled-at-boot-time` in "
            "the overlay turns it on at boot), or use a HAT with automatic direction "
            "control and remove `rs485:`",
            port=port,
            reason=PortReason.NO_RS485,
        ) from exc
