"""The peer of the peers bench: modbus2mqtt 0.73 (spicierModbus2mqtt), as its users run it.

Installed from PyPI into a venv of its own, in the system's temporary directory and reused
while its pins stay the same (nothing of it is kept in the repository), configured with
the CSV file it reads, started as its ``modbus2mqtt`` command.

What its 0.73 source (``modbus2mqtt.py``, ``dataTypes.py``) means for a fair setup:

- A ``poll`` row reads one block of registers at its own rate; ``ref`` rows take points
  out of it. It plans nothing, so the bench writes the blocks a careful user would: the
  points of a device merged wherever the registers between them are documented (the
  profile's readable runs), up to the family's read limit.
- It publishes a value only when it changed unless ``--always-publish`` is given; the
  values are still here, so it is given, as our gateway publishes every poll by default.
- Data types, by what its ``combine`` functions do: ``float32BE`` puts the second
  register in the high half (CDAB, the default of every family here), ``float32LE`` the
  first (ABCD). No type swaps the bytes inside a word, so BADC and DCBA are out of reach.
  ``uint32LE`` is high word first, as our profiles store 32-bit integers and bit fields.
- The serial port always has one stop bit (``stopbits = 1`` in its code), and is told
  no parity here, as a pseudo-terminal refuses one. Neither changes the bytes the
  simulator sees; on a real 8E1 or 8N2 line the first would matter.
"""

from __future__ import annotations

import csv
import io
import subprocess
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Final

if TYPE_CHECKING:
    from collections.abc import Sequence

    from gateway.profiles import Point, Profile
    from gateway.wire.timing import LineFormat

PEER: Final = "modbus2mqtt 0.73"
# Installed with --no-deps, then its real needs pinned: its metadata asks for `pymodbus`
# unpinned, but its poll() passes `slave=`, which pymodbus 3.10.0 renamed `device_id`, so
# 3.9.2 is the last release it runs with; and it asks for `serial`, which on PyPI is not
# pyserial but an unrelated package whose serial/__init__.py replaces pyserial's and breaks
# pymodbus's serial client. pyserial and paho-mqtt (its callback API VERSION1 path) pinned
# to what this bench was checked with.
PACKAGE: Final = "modbus2mqtt==0.73"
DEPENDENCIES: Final = ("pymodbus==3.9.2", "pyserial==3.5", "paho-mqtt==2.2.0")
VENV: Final = Path(tempfile.gettempdir()) / "gateway-bench-peers" / "modbus2mqtt-0.73"
TOPIC: Final = "peer"

# Point data types (the profiles' names) -> the peer's type names, read from dataTypes.py.
_INTEGER_TYPES: Final = {
    "uint16": "uint16",
    "enum": "uint16",
    "bitfield": "uint16",
    "int16": "int16",
    "uint32": "uint32LE",
    "enum32": "uint32LE",
    "bitfield32": "uint32LE",
    "int32": "int32LE",
}
_FLOAT_TYPES: Final = {"CDAB": "float32BE", "ABCD": "float32LE"}


class PeerUnsupportedError(Exception):
    """Something the peer cannot be configured to read."""


@dataclass(frozen=True, slots=True)
class Block:
    """One ``poll`` row: a block of holding registers and the points taken out of it."""

    address: int
    count: int
    points: tuple[Point, ...]


def ensure_venv() -> Path:
    """The peer's ``modbus2mqtt`` command, installing it first unless the venv has its pins.

    The stamp file records the pip lines the venv was made with; other pins rebuild it.
    """
    stamp = VENV / "bench-pins.txt"
    pins = "\n".join((PACKAGE, *DEPENDENCIES))
    command = VENV / "bin" / "modbus2mqtt"
    if command.exists() and stamp.exists() and stamp.read_text(encoding="utf-8") == pins:
        return command
    print(f"installing {PEER} into {VENV} ...", flush=True)
    subprocess.run([sys.executable, "-m", "venv", "--clear", str(VENV)], check=True)  # noqa: S603
    pip = [str(VENV / "bin" / "python"), "-m", "pip", "install", "--quiet"]
    subprocess.run([*pip, "--no-deps", PACKAGE], check=True)  # noqa: S603
    subprocess.run([*pip, *DEPENDENCIES], check=True)  # noqa: S603
    stamp.write_text(pins, encoding="utf-8")
    return command


def peer_type(point: Point, profile: Profile) -> str:
    """The peer's data type for a point, or :class:`PeerUnsupportedError`."""
    dtype = point.dtype.value
    if dtype == "float32":
        order = profile.float_order.value
        if order not in _FLOAT_TYPES:
            raise PeerUnsupportedError(f"{profile.id}: no peer type for {order} floats")
        return _FLOAT_TYPES[order]
    if dtype not in _INTEGER_TYPES:
        raise PeerUnsupportedError(f"{profile.id}.{point.name}: no peer type for {dtype}")
    return _INTEGER_TYPES[dtype]


def _documented(profile: Profile, first: int, last: int) -> bool:
    """Whether every register from ``first`` to ``last`` lies in a documented run."""
    runs = sorted(profile.readable)
    address = first
    for start, end in runs:
        if start <= address <= end:
            address = end + 1
            if address > last:
                return True
    return first > last


def hand_blocks(profile: Profile, points: Sequence[Point]) -> list[Block]:
    """The blocks a careful user writes: merged across documented registers only.

    A gap the manual does not document may answer with an exception, so it is never
    bridged; the read limit of the family is kept.
    """
    blocks: list[Block] = []
    for point in sorted(points, key=lambda p: p.address):
        if blocks:
            block = blocks[-1]
            end = block.address + block.count
            fits = point.last + 1 - block.address <= profile.limits.max_read
            if fits and _documented(profile, end, point.address - 1):
                count = max(end, point.last + 1) - block.address
                blocks[-1] = Block(block.address, count, (*block.points, point))
                continue
        blocks.append(Block(point.address, point.count, (point,)))
    return blocks


@dataclass(frozen=True, slots=True)
class PeerDevice:
    """One sensor as the peer sees it: a name (its topic), an address and blocks."""

    name: str
    address: int
    profile: Profile
    blocks: tuple[Block, ...]


def config_csv(devices: Sequence[PeerDevice], *, interval_s: float) -> str:
    """The peer's configuration file: a ``poll`` row per block, a ``ref`` row per point."""
    out = io.StringIO()
    rows = csv.writer(out, lineterminator="\n")
    rows.writerow(["type", "topic", "col2", "col3", "col4", "col5", "col6"])
    for device in devices:
        for block in device.blocks:
            row = ["poll", device.name, device.address, block.address, block.count]
            rows.writerow([*row, "holding_register", interval_s])
            for point in block.points:
                rows.writerow(
                    [
                        "ref",
                        point.name,
                        point.address,
                        "r",
                        peer_type(point, device.profile),
                        "",
                        "",
                    ]
                )
    return out.getvalue()


def command(
    executable: Path, *, port: Path, line: LineFormat, broker: int, config: Path
) -> list[str]:
    """The peer's command line: our line, our broker, its own topic prefix."""
    return [
        str(executable),
        "--rtu",
        str(port),
        "--rtu-baud",
        str(line.baudrate),
        # The line is a pseudo-terminal, which refuses a parity setting on this kernel
        # (tcsetattr EINVAL: the peer stops at start). Our gateway opens a pty without
        # parity too and keeps the configured format's timing; the simulator referees
        # the configured format whatever the port is told.
        "--rtu-parity",
        "none",
        "--mqtt-host",
        "127.0.0.1",
        "--mqtt-port",
        str(broker),
        "--mqtt-topic",
        f"{TOPIC}/",
        "--config",
        str(config),
        "--always-publish",
        "--verbosity",
        "1",  # errors only: what a service would log
    ]


def parse_topic(topic: str) -> tuple[str, str] | None:
    """``(device, point)`` of a value topic (``peer/{device}/state/{point}``), else None."""
    parts = topic.split("/")
    if len(parts) == 4 and parts[0] == TOPIC and parts[2] == "state":  # noqa: PLR2004
        return parts[1], parts[3]
    return None
