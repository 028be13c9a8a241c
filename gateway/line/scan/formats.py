"""The addresses and line formats a scan tries, and how long a probe waits for an answer.

The formats come from the profiles' interface registers (the baud rate and data format
enums), so a profile that adds a rate adds it to ``gateway scan --all-formats``.
"""

from __future__ import annotations

import re
from typing import TYPE_CHECKING, Final

from gateway.config import BAUDRATES
from gateway.errors import ConfigError
from gateway.profiles import builtin_profiles
from gateway.wire.timing import LineFormat

if TYPE_CHECKING:
    from collections.abc import Mapping

    from gateway.profiles import Profile

FIRST_ADDRESS: Final = 1
LAST_ADDRESS: Final = 247  # Modbus over serial line 2.2: unicast addresses 1..247
# A probe's answer must start within the digiLine t1 (max. 25 ms, S10 and H10/H20 manuals
# 5.1) with 5 ms to spare; the tecLine manual gives no figure. A sensor with a digiLine
# minimum response time (0x0305) set needs --timeout.
PROBE_RESPONSE_S: Final = 0.030
PROBE_MARGIN_S: Final = 0.010  # event-loop timers and USB adapters add a few ms
PROBE_REGISTERS: Final = 2

_RANGE = re.compile(r"\s*(\d+)\s*(?:-\s*(\d+)\s*)?")
_FORMAT_LABEL = re.compile(r"8([neo])([12])")
_BAUD_LABEL = re.compile(r"baud_(\d+)")


def parse_addresses(text: str) -> tuple[int, ...]:
    """Addresses from ``1-247``, ``7`` or ``1-10,20,30-40``: sorted, each once.

    Raises :class:`ConfigError` naming the option for anything else.
    """
    addresses: set[int] = set()
    for part in text.split(","):
        match = _RANGE.fullmatch(part)
        if match is None:
            raise ConfigError(
                f"--addresses {text!r}: expected N, N-M or a comma-separated list of them, "
                "e.g. 1-247 or 1-10,20"
            )
        first = int(match[1])
        last = int(match[2]) if match[2] is not None else first
        if not FIRST_ADDRESS <= first <= last <= LAST_ADDRESS:
            raise ConfigError(
                f"--addresses {text!r}: {part.strip()} is not a range within "
                f"{FIRST_ADDRESS}..{LAST_ADDRESS} (first <= last)"
            )
        addresses.update(range(first, last + 1))
    return tuple(sorted(addresses))


def supported_formats(profiles: Mapping[str, Profile] | None = None) -> tuple[LineFormat, ...]:
    """Every line format some family can be set to, from the profiles' interface registers.

    The baud rate enums (digiLine 0x0301, tecLine/Reiss 0x0401) and the data format enums
    (digiLine 0x0302, tecLine/Reiss 0x0402, labels such as ``8e1``) are the source, so a
    profile that adds a rate (Reiss 115200) adds it here. Ordered by baud rate, then
    8N1, 8E1, 8O1, 8N2.
    """
    profiles = builtin_profiles() if profiles is None else profiles
    rates: set[int] = set()
    characters: set[tuple[str, int]] = set()
    for profile in profiles.values():
        for point in profile.points:
            labels = point.format.enum.values()
            for label in labels:
                if (baud := _BAUD_LABEL.fullmatch(label)) is not None:
                    rates.add(int(baud[1]))
                elif (character := _FORMAT_LABEL.fullmatch(label)) is not None:
                    characters.add((character[1].upper(), int(character[2])))
    order = {("N", 1): 0, ("E", 1): 1, ("O", 1): 2, ("N", 2): 3}
    return tuple(
        LineFormat(baudrate=rate, parity=parity, stopbits=stopbits)  # type: ignore[arg-type]
        for rate in sorted(rates)
        for parity, stopbits in sorted(characters, key=lambda c: order.get(c, len(order)))
    )


def scan_formats(
    *, baudrate: int, parity: str, stopbits: int, every: bool = False
) -> tuple[LineFormat, ...]:
    """The given format, checked, and with ``every`` all :func:`supported_formats` after it.

    Raises :class:`ConfigError` naming the option for a format the config would refuse.
    """
    if parity not in {"N", "E", "O"} or stopbits not in {1, 2}:
        raise ConfigError("--parity must be N, E or O and --stopbits 1 or 2")
    if baudrate not in BAUDRATES:
        raise ConfigError(f"--baudrate {baudrate}: use one of {', '.join(map(str, BAUDRATES))}")
    given = LineFormat(baudrate=baudrate, parity=parity, stopbits=stopbits)  # type: ignore[arg-type]
    if not every:
        return (given,)
    return (given, *(fmt for fmt in supported_formats() if fmt != given))


def probe_timeout_s(line: LineFormat) -> float:
    """A probe's response timeout: its answer's wire time + 30 ms + a margin."""
    answer_bytes = 5 + 2 * PROBE_REGISTERS  # address, function, count, data, CRC
    return line.wire_s(answer_bytes) + PROBE_RESPONSE_S + PROBE_MARGIN_S
