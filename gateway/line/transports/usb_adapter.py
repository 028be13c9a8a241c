"""A USB serial adapter's tuning: the FTDI latency timer, read, lowered where allowed, warned of.

An FTDI chip holds received bytes until its buffer fills or its latency timer runs out:
ftdi_sio's default is 16 ms, so every answer of a device arrives up to 16 ms late and a
19200-baud line carries a good share fewer requests (bench/README.md). The gateway asks the
driver for low-latency mode when it opens the port (ftdi_sio then sets the timer to 1 ms
itself, where the kernel lets it), reads the timer back from sysfs for the metrics, and
warns once with the fix (the udev rule, or one ``echo`` as root) when it stays above 2 ms.

The adapter is found from the configured port through its ``/dev/serial/by-id`` link to the
``ttyUSBn`` node, and its driver in sysfs; other drivers (ch341, cp210x) and other ports
(a UART, a pseudo-terminal) have no such timer and are left alone.
"""

from __future__ import annotations

import logging
import re
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Final

if TYPE_CHECKING:
    import serial

    from gateway.line.transports.port_names import SystemRoots

_LOGGER = logging.getLogger(__name__)

FTDI_DRIVER: Final = "ftdi_sio"
# ftdi_sio's default latency timer is 16 ms (drivers/usb/serial/ftdi_sio.c); above 2 ms it
# costs a 19200-baud line a good share of its throughput (bench/README.md).
LATENCY_WARN_S: Final = 0.002
UDEV_RULE: Final = "deploy/udev/99-gateway-ftdi-latency.rules"


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
