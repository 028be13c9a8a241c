"""Registers a write changes besides those written: what the bus must read again after it.

Writing a tecLine/Reiss date stamp activates the calibration and moves the history; an
H10/H20 calibration trigger fills the calibration registers and a new logbook entry and
clears the cycles since calibration. What was written is read again anyway; these ranges
are read at once too, so sensor care sees a calibration within one read, whoever wrote
it (the gateway, or another master on the shared bus). Sources are the manuals' sections.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Final

if TYPE_CHECKING:
    from collections.abc import Mapping

    from gateway.profiles.model import Profile


@dataclass(frozen=True, slots=True)
class WriteEffect:
    """A write within ``first``..``last`` changes the registers ``reads`` as well."""

    first: int
    last: int
    reads: tuple[tuple[int, int], ...]  # (address, count)


_AMPEROMETRIC: Final = (
    # tecLine annex 7.2 / Reiss 5.1: writing DateTime (0x020A) activates the calibration and
    # pushes (or overwrites) the history 0x0210-0x022D; the active one is 0x0206-0x020B.
    WriteEffect(first=0x020A, last=0x020B, reads=((0x0206, 0x022E - 0x0206),)),
)
EFFECTS: Final[Mapping[str, tuple[WriteEffect, ...]]] = {
    "jumo-tecline": _AMPEROMETRIC,
    "reiss-m0c-m3c": _AMPEROMETRIC,
    "jumo-digiline-odo-h10-h20": (
        # 6.2.4: the triggers 0x3003 (zero point) and 0x3005 (end value) take the last
        # measurement into 0x203D-0x204C and write a logbook entry (6.1.6: 10 x 0x31 from
        # 0x0600); the cycles since calibration 0x205F-0x2062 start again.
        WriteEffect(
            first=0x3003,
            last=0x3006,
            reads=((0x203D, 0x204D - 0x203D), (0x0600, 10 * 0x31), (0x205F, 4)),
        ),
        # 6.2.9: 0x2093 = 2 resets the measurement counter 0x2091.
        WriteEffect(first=0x2093, last=0x2094, reads=((0x2091, 2),)),
    ),
}


def touched_by_write(profile: Profile, address: int, count: int) -> tuple[tuple[int, int], ...]:
    """The other register ranges (address, count) a write of ``count`` at ``address`` changes."""
    last = address + count - 1
    return tuple(
        read
        for effect in EFFECTS.get(profile.family, ())
        if address <= effect.last and last >= effect.first
        for read in effect.reads
    )
