"""Where a serial port's names are, and which of them lasts: by-id against ``/dev/ttyUSBn``.

The kernel numbers USB serial nodes (``/dev/ttyUSB0``, ``/dev/ttyACM0``) in the order the
adapters appear, so two adapters swap names at a replug or a reboot and a bus would poll
the other line's sensors. udev gives each adapter a name of its own under
``/dev/serial/by-id``, from its vendor, model and serial number: the name a config should
use. ``check-config`` and the gateway's start warn of a numbered name with the by-id names
that point at it now; a port that is missing is told with the adapters connected now.

Every file system root is a :class:`SystemRoots`, so tests run on a fake ``/dev``, ``/sys``
and ``/proc`` tree where the machine has no adapter to show.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path
from typing import Final

# Names the kernel gives in the order adapters appear: USB serial converters (usbserial)
# and CDC ACM devices. They swap when adapters are replugged or enumerate in another order.
ENUMERATED_NAME: Final = re.compile(r"/dev/tty(USB|ACM)[0-9]+")
BY_ID: Final = "serial/by-id"  # udev's persistent names (60-serial.rules), under /dev


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


def connected_adapters(roots: SystemRoots) -> str:
    """The serial adapters connected now, by their by-id names, for a port that is missing."""
    links = by_id_links(roots)
    if not links:
        return (
            "no serial adapter is connected (nothing in /dev/serial/by-id): check the cable "
            "and the adapter, and `dmesg` for USB errors"
        )
    listed = ", ".join(f"/dev/{BY_ID}/{name} (-> {target.name})" for name, target in links.items())
    return f"serial adapters connected now: {listed}"
