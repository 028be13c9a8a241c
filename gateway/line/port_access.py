"""Opening a serial port as real hardware needs it: alone, by a stable name, tuned, with reasons.

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

A port that cannot be opened raises :class:`~gateway.errors.PortUnavailableError` with a
:class:`PortReason` and a message that names the remedy: the ``/dev/serial/by-id`` names
that do exist when the port is missing, the group to join when permission is denied, the
process (and its systemd unit) that holds a port in use, or the driver's own error.

The rest of the module is what an FTDI adapter and an RS485 UART need: the by-id names of
a ``/dev/ttyUSBn`` node (which swaps with its neighbours at a replug), the driver's
low-latency mode and its latency timer in sysfs, and the kernel's RS485 mode
(``TIOCSRS485``). Every file system root is a :class:`SystemRoots` so tests run on a fake
``/dev``, ``/sys`` and ``/proc`` tree.
"""

from __future__ import annotations

import asyncio
import contextlib
import errno
import fcntl
import functools
import grp
import logging
import os
import pwd
import re
import stat
import termios
from dataclasses import dataclass, field
from enum import StrEnum
from pathlib import Path
from typing import TYPE_CHECKING, Final

import serial
import serial_asyncio_fast
from serial.rs485 import RS485Settings

from gateway.errors import PortUnavailableError

if TYPE_CHECKING:
    from collections.abc import Iterator, Sequence

    from gateway.config.model import BusConfig, GatewayConfig
    from gateway.config.problems import KeyPath
    from gateway.config.rs485 import Rs485Config
    from gateway.config.shared_bus import SharedBusConfig
    from gateway.wire.timing import LineFormat

_LOGGER = logging.getLogger(__name__)

# Names the kernel gives in the order adapters appear: USB serial converters (usbserial)
# and CDC ACM devices. They swap when adapters are replugged or enumerate in another order.
ENUMERATED_NAME: Final = re.compile(r"/dev/tty(USB|ACM)[0-9]+")
BY_ID: Final = "serial/by-id"  # udev's persistent names (60-serial.rules), under /dev
FTDI_DRIVER: Final = "ftdi_sio"
# ftdi_sio's default latency timer is 16 ms (drivers/usb/serial/ftdi_sio.c); above 2 ms it
# costs a 19200-baud line a good share of its throughput (bench/README.md).
LATENCY_WARN_S: Final = 0.002
UDEV_RULE: Final = "deploy/udev/99-gateway-ftdi-latency.rules"
SERVICE_UNIT: Final = "rs485-gateway"  # deploy/systemd/rs485-gateway.service


class PortReason(StrEnum):
    """Why a port is not open: what ``/healthz``, the metrics and the log name."""

    MISSING = "missing"  # no such device node: unplugged, renamed, or a typo
    PERMISSION = "permission_denied"  # the user is not in the device's group
    IN_USE = "in_use"  # another master holds it (the lock, or TIOCEXCL)
    NO_RS485 = "no_rs485_mode"  # rs485: configured, the driver has no TIOCSRS485
    DRIVER = "driver_error"  # anything else the driver said


@dataclass(frozen=True, slots=True, kw_only=True)
class SystemRoots:
    """Where ``/dev``, ``/sys`` and ``/proc`` are: the real ones, or a tree in a test."""

    dev: Path = Path("/dev")
    sys: Path = Path("/sys")
    proc: Path = Path("/proc")

    @property
    def by_id(self) -> Path:
        """The folder of udev's persistent names."""
        return self.dev / BY_ID

    def node(self, port: str) -> Path:
        """A configured ``/dev/...`` path under this tree's ``/dev``."""
        if port.startswith("/dev/"):
            return self.dev / port.removeprefix("/dev/")
        return Path(port)


@dataclass(frozen=True, slots=True, kw_only=True)
class PortOptions:
    """How to open one bus's port, beyond its line format.

    ``shared_bus`` holds how other programs can reach the line through the gateway that
    owns it (``shared_bus.listen``), for the message of a port in use.
    """

    rs485: Rs485Config | None = None
    shared_bus: tuple[str, ...] = ()
    roots: SystemRoots = field(default_factory=SystemRoots)


def port_options(bus: BusConfig, shared: SharedBusConfig) -> PortOptions:
    """A configured bus's options: its RS485 mode, and where the shared bus listens."""
    hints = []
    for listen in shared.listen:
        host = "127.0.0.1" if listen.host in {"0.0.0.0", "::"} else listen.host  # noqa: S104
        if listen.port == 0:  # any free port: the running gateway says which
            hints.append(f"{host}, the port its /healthz shows under shared_bus.listening")
        elif listen.framing == "rtu":
            hints.append(
                f"RTU over TCP at {host}:{listen.port} "
                f"(`gateway read --port socket://{host}:{listen.port} ...`)"
            )
        else:
            hints.append(f"Modbus TCP at {host}:{listen.port} (unit id: the device's address)")
    return PortOptions(rs485=bus.rs485, shared_bus=tuple(hints))


# --- names --------------------------------------------------------------------------------


def by_id_links(roots: SystemRoots) -> dict[str, Path]:
    """Every ``/dev/serial/by-id`` name and the node it points at, resolved."""
    try:
        entries = sorted(roots.by_id.iterdir())
    except OSError:
        return {}  # no adapter plugged in: udev removes the folder with the last one
    return {entry.name: entry.resolve() for entry in entries if entry.is_symlink()}


def by_id_names_of(port: str, roots: SystemRoots) -> list[str]:
    """The ``/dev/serial/by-id`` names (full paths) of the node ``port`` names now."""
    try:
        node = roots.node(port).resolve(strict=True)
    except OSError:
        return []
    return [f"/dev/{BY_ID}/{name}" for name, target in by_id_links(roots).items() if target == node]


def port_name_advice(port: str, roots: SystemRoots) -> str | None:
    """A warning for a kernel-enumerated name (``/dev/ttyUSB0``), with its by-id names."""
    if not ENUMERATED_NAME.fullmatch(port):
        return None
    names = by_id_names_of(port, roots)
    where = (
        f"use its stable name: {' or '.join(names)}"
        if names
        else (
            "use its stable name under /dev/serial/by-id/ (none points at it now: "
            "is the adapter plugged in?)"
        )
    )
    return (
        f"{port} is numbered in the order adapters appear and can name another adapter "
        f"after a reboot or a replug; {where}"
    )


def port_advice(config: GatewayConfig, roots: SystemRoots) -> Iterator[tuple[KeyPath, str]]:
    """``check-config``'s warnings about the ports of a valid config, by key path."""
    for index, bus in enumerate(config.buses):
        advice = port_name_advice(bus.port, roots)
        if advice is not None:
            yield ("buses", index, "port"), advice


def _available_names(roots: SystemRoots) -> str:
    links = by_id_links(roots)
    if not links:
        return (
            "no serial adapter is connected (nothing in /dev/serial/by-id): check the cable "
            "and the adapter, and `dmesg` for USB errors"
        )
    listed = ", ".join(f"/dev/{BY_ID}/{name} (-> {target.name})" for name, target in links.items())
    return f"serial adapters connected now: {listed}"


# --- opening --------------------------------------------------------------------------------


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
        raise _unavailable(port, exc, options) from exc
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
            f"{_strerror(cause)}). For a USB adapter: use one with automatic direction "
            "control and remove `rs485:` from the bus. For an RS485 HAT: load the driver "
            "its maker names in /boot/firmware/config.txt (e.g. `dtoverlay=sc16is752-spi1`: "
            "the sc16is7xx driver has the mode, and `linux,rs485-enabled-at-boot-time` in "
            "the overlay turns it on at boot), or use a HAT with automatic direction "
            "control and remove `rs485:`",
            port=port,
            reason=PortReason.NO_RS485,
        ) from exc


def _strerror(exc: BaseException) -> str:
    if isinstance(exc, OSError) and exc.strerror:
        return exc.strerror
    return str(exc)


def _errno(exc: BaseException) -> int | None:
    """The errno of an open failure: pyserial keeps it as its first argument."""
    if isinstance(exc, OSError) and exc.errno is not None:
        return exc.errno
    first = exc.args[0] if exc.args else None
    return first if isinstance(first, int) else None


def _unavailable(port: str, exc: BaseException, options: PortOptions) -> PortUnavailableError:
    roots = options.roots
    code = _errno(exc)
    if code == errno.ENOENT or (code is None and not roots.node(port).exists()):
        return PortUnavailableError(
            f"cannot open {port}: it does not exist; {_available_names(roots)}",
            port=port,
            reason=PortReason.MISSING,
        )
    if code in {errno.EACCES, errno.EPERM}:
        return PortUnavailableError(
            _permission_text(port, roots), port=port, reason=PortReason.PERMISSION
        )
    if code in {errno.EBUSY, errno.EAGAIN, errno.EWOULDBLOCK}:
        holders = lock_holders(port, roots)
        return PortUnavailableError(
            _in_use_text(port, holders, options, busy=code == errno.EBUSY),
            port=port,
            reason=PortReason.IN_USE,
            holder=holders[0] if holders else None,
        )
    return PortUnavailableError(
        f"cannot open {port}: {_strerror(exc)} (the driver's own error)",
        port=port,
        reason=PortReason.DRIVER,
    )


def _permission_text(port: str, roots: SystemRoots) -> str:
    user = _user_name(os.geteuid())
    try:
        info = roots.node(port).stat()
    except OSError:
        return f"cannot open {port}: permission denied for user {user}"
    group = _group_name(info.st_gid)
    return (
        f"cannot open {port}: permission denied (owner {_user_name(info.st_uid)}, group "
        f"{group}, mode {stat.S_IMODE(info.st_mode):04o}) for user {user}: add the user to {group} "
        f"(`sudo usermod -aG {group} {user}`, then log in again); the systemd unit needs "
        f"`SupplementaryGroups={group}`, a container `--group-add {group}`"
    )


def _user_name(uid: int) -> str:
    try:
        return pwd.getpwuid(uid).pw_name
    except KeyError:
        return str(uid)


def _group_name(gid: int) -> str:
    try:
        return grp.getgrgid(gid).gr_name
    except KeyError:
        return str(gid)


def _in_use_text(
    port: str, holders: Sequence[int], options: PortOptions, *, busy: bool = False
) -> str:
    roots = options.roots
    if busy and not holders:
        # EBUSY from open(): TIOCEXCL, set by a program that holds no lock on it, or left
        # by a process that died while another one still has the port open.
        return (
            f"cannot open {port}: the kernel refuses a second open (TIOCEXCL) and no "
            "process holds its lock: another program has it open (`fuser -v "
            f"{port}` names it), or one that had it ended while another still has it "
            "open. Close that program; two masters on one line corrupt each other's frames"
        )
    if holders:
        pid = holders[0]
        who = f"process {pid} ({describe_process(pid, roots)})"
        unit = systemd_unit_of(pid, roots)
        stop = (
            f"`systemctl stop {unit.removesuffix('.service')}`"
            if unit
            else f"`kill {pid}` or `systemctl stop {SERVICE_UNIT}` if it is the service"
        )
    else:
        who = "another program"
        stop = f"`systemctl stop {SERVICE_UNIT}` or the other `gateway` process"
    if options.shared_bus:
        listening = "; ".join(options.shared_bus)
        through = f"; or read through the running gateway's shared bus: {listening}"
    else:
        through = (
            "; or, if that gateway has `shared_bus.listen`, read through it on that address "
            "instead of the port"
        )
    return (
        f"cannot open {port}: it is in use by {who}, and two masters on one line "
        "corrupt each other's frames. "
        f"Stop it first ({stop}){through}"
    )


# --- who holds a port -------------------------------------------------------------------


def lock_holders(port: str, roots: SystemRoots) -> list[int]:
    """The PIDs that hold a lock on the port's node, from ``/proc/locks`` (proc(5))."""
    try:
        info = roots.node(port).stat()
        text = (roots.proc / "locks").read_text(encoding="ascii")
    except OSError:
        return []
    # "1: FLOCK  ADVISORY  WRITE 2735 00:1a:4 0 EOF": the PID, then the file system's
    # device (major:minor in hex) and the inode; "->" marks a waiter, not a holder.
    wanted = (os.major(info.st_dev), os.minor(info.st_dev), info.st_ino)
    pids = []
    for line in text.splitlines():
        fields = line.split()
        if len(fields) < 6 or fields[1] == "->":  # noqa: PLR2004 - the format above
            continue
        try:
            major, minor, inode = fields[5].split(":")
            where = (int(major, 16), int(minor, 16), int(inode))
            pid = int(fields[4])
        except ValueError:
            continue
        if where == wanted and pid > 0 and pid != os.getpid():
            pids.append(pid)
    return pids


def describe_process(pid: int, roots: SystemRoots) -> str:
    """A process's command line, shortened, for a message (``?`` if it cannot be read)."""
    try:
        raw = (roots.proc / str(pid) / "cmdline").read_bytes()
    except OSError:
        return "?"
    text = " ".join(part.decode(errors="replace") for part in raw.split(b"\0") if part)
    return text if len(text) <= 120 else text[:117] + "..."  # noqa: PLR2004 - one log line


def systemd_unit_of(pid: int, roots: SystemRoots) -> str | None:
    """The systemd service a process runs in, from its cgroup path (cgroups(7)), if any."""
    try:
        text = (roots.proc / str(pid) / "cgroup").read_text(encoding="utf-8")
    except OSError:
        return None
    for line in text.splitlines():
        for part in reversed(line.rpartition(":")[2].split("/")):
            if part.endswith(".service"):
                return part
    return None


# --- USB adapters: the latency timer -------------------------------------------------------


@dataclass(frozen=True, slots=True)
class UsbSerial:
    """A USB serial node behind a configured port, and its driver."""

    node: str  # ttyUSB0
    driver: str  # ftdi_sio, ch341, cp210x, ...

    @property
    def ftdi(self) -> bool:
        """Whether ftdi_sio drives it (the driver with a latency timer)."""
        return self.driver == FTDI_DRIVER


def usb_serial_of(port: str, roots: SystemRoots) -> UsbSerial | None:
    """The ``ttyUSBn`` node a port is (through a by-id link too), and its driver from sysfs.

    A port named ``ttyUSBn`` is that node even where its path is a bind mount or a link
    elsewhere (a container's ``--device``); any other name is followed to its node.
    """
    node = Path(port).name
    if not re.fullmatch(r"ttyUSB[0-9]+", node):
        try:
            node = roots.node(port).resolve(strict=True).name
        except OSError:
            return None
    if not re.fullmatch(r"ttyUSB[0-9]+", node):
        return None
    driver = roots.sys / "bus/usb-serial/devices" / node / "driver"
    try:
        return UsbSerial(node=node, driver=driver.resolve(strict=True).name)
    except OSError:
        return None


def latency_timer_file(usb: UsbSerial, roots: SystemRoots) -> Path:
    """ftdi_sio's ``latency_timer`` attribute of a node (milliseconds, 1..255)."""
    return roots.sys / "bus/usb-serial/devices" / usb.node / "latency_timer"


def read_latency_timer(usb: UsbSerial, roots: SystemRoots) -> float | None:
    """The adapter's latency timer in seconds, or ``None`` where it cannot be read."""
    try:
        text = latency_timer_file(usb, roots).read_text(encoding="ascii")
        return int(text.strip()) / 1000
    except (OSError, ValueError):
        return None


def ask_low_latency(device: serial.Serial) -> None:
    """Ask the driver for low-latency mode (``ASYNC_LOW_LATENCY``); not fatal if refused.

    ftdi_sio then sets its latency timer to 1 ms itself, where the kernel lets it (Linux
    before 6.1, with ``CAP_SYS_ADMIN``); otherwise the udev rule does it.
    """
    try:
        device.set_low_latency_mode(True)
    except (ValueError, OSError, AttributeError) as exc:
        _LOGGER.debug("%s: low-latency mode refused: %s", device.port, exc)


def tune_usb(device: serial.Serial, roots: SystemRoots) -> tuple[float | None, str | None]:
    """An FTDI port: low latency asked for; its latency timer (s) and the warning, if any.

    ``(None, None)`` for any other port. ``device.port`` is the configured path.
    """
    port = str(device.port)
    usb = usb_serial_of(port, roots)
    if usb is None or not usb.ftdi:
        return None, None
    ask_low_latency(device)
    latency_s = read_latency_timer(usb, roots)
    advice = None if latency_s is None else latency_advice(port, usb, latency_s)
    return latency_s, advice


def latency_advice(port: str, usb: UsbSerial, latency_s: float) -> str | None:
    """The warning for a latency timer above 2 ms, with the fix; ``None`` at 2 ms or less."""
    if latency_s <= LATENCY_WARN_S:
        return None
    where = f"/sys/bus/usb-serial/devices/{usb.node}/latency_timer"
    return (
        f"{port} ({usb.node}, {usb.driver}) holds received bytes up to "
        f"{latency_s * 1000:g} ms (its USB latency timer): answers arrive late and the "
        f"line carries fewer requests. Install the udev rule {UDEV_RULE} "
        f"(sets it to 1 ms at every plug-in), or once as root: `echo 1 > {where}`"
    )
