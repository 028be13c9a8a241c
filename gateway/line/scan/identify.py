"""Identification without I/O: which profile the registers a device answered name.

From the registers the manuals name for it (specs/README.md, "Identification"):

- digiLine: the sensor type and sub-type codes (0x010A..0x010B) select the profile whose
  ``identify`` matches (S10, H10, H20).
- tecLine / Reiss: a Reiss cell has a sensor type string at 0x0300 (``CP4.0N-M0``, the
  suffix tells M0c from M3c), which a tecLine does not have. The tecLine variants share one
  register map and no register tells them apart: the variant whose factory address equals
  the found address is reported, or Cl2, and either way marked as a guess.
"""

from __future__ import annotations

import logging
import re
from dataclasses import dataclass
from typing import TYPE_CHECKING, Final

from gateway.errors import DecodeError
from gateway.wire import codec

if TYPE_CHECKING:
    from collections.abc import Iterable, Mapping, Sequence

    from gateway.profiles import Point, Profile

_LOGGER = logging.getLogger(__name__)

DIGILINE: Final = "digiline"
TECLINE: Final = "tecline"
REISS: Final = "reiss"
UNKNOWN: Final = "unknown"
TECLINE_FAMILY: Final = "jumo-tecline"
REISS_FAMILY: Final = "reiss-m0c-m3c"
# Reiss manual 4 "Gerätedaten", 0x0300 Sensortyp, example "CP4.0N-M0": the suffix names the
# variant (M0 = M0c, M3 = M3c).
_REISS_SUFFIX = re.compile(r"-M([03])\b")
_REISS_VARIANTS: Final = {"0": "reiss-m0c", "3": "reiss-m3c"}

# The identity blocks, as ``identified_by`` names them (specs/README.md, "Identification").
DIGILINE_BLOCK: Final = "digiLine sensor type"
TECLINE_BLOCK: Final = "tecLine device data"
REISS_BLOCK: Final = "Reiss sensor type"


@dataclass(frozen=True, slots=True)
class Families:
    """The profiles a scan identifies with, and the points it reads, resolved once."""

    digiline: tuple[Profile, ...]  # profiles with ``identify`` codes
    tecline: tuple[Profile, ...]
    reiss: tuple[Profile, ...]

    @classmethod
    def from_profiles(cls, profiles: Mapping[str, Profile]) -> Families:
        """Each family's profiles, by id."""
        ordered = sorted(profiles.values(), key=lambda p: p.id)
        return cls(
            digiline=tuple(p for p in ordered if p.identify),
            tecline=tuple(p for p in ordered if p.family == TECLINE_FAMILY),
            reiss=tuple(p for p in ordered if p.family == REISS_FAMILY),
        )

    def digiline_probe(self) -> tuple[int, int]:
        """First address and count covering every identify point (0x010A..0x010B)."""
        reference = self.digiline[0]
        addresses = sorted(reference.point(name).address for name in reference.identify)
        return addresses[0], addresses[-1] - addresses[0] + 1

    def tecline_probe(self) -> tuple[Point, Point]:
        """Hardware and firmware version (0x0308, 0x0309)."""
        reference = self.tecline[0]
        return reference.point("hardware_version"), reference.point("firmware_version")


def span(first: int, count: int) -> str:
    """Registers as ``0x0308..0x0309`` (one: ``0x0300``), as the manuals print them."""
    last = first + count - 1
    return f"0x{first:04X}" if count == 1 else f"0x{first:04X}..0x{last:04X}"


def plain(value: codec.Decoded) -> object:
    """A decoded value as JSON-ready data: numbers and text as they are, the rest as text."""
    return value if value is None or isinstance(value, (str, int, float)) else str(value)


def decoded(profile: Profile, point: Point, registers: Sequence[int] | None) -> object:
    """The point's value from the registers read; ``None`` without them or when undecodable."""
    if registers is None:
        return None
    try:
        value = codec.decode(point.format, registers, float_order=profile.float_order)
    except DecodeError as exc:
        _LOGGER.debug("%s: %s", point.name, exc)
        return None
    return plain(value)


def primary_identify(profile: Profile) -> str:
    """The identify point with the lowest address: the family's sensor type."""
    return min(profile.identify, key=lambda name: profile.point(name).address)


def match_identify(
    candidates: Sequence[Profile], codes: Mapping[int, int]
) -> tuple[list[Profile], str]:
    """Profiles whose identify codes all match; else those whose sensor type matches."""

    def matches(profile: Profile, names: Iterable[str]) -> bool:
        return all(
            codes.get(profile.point(name).address) == profile.identify[name] for name in names
        )

    exact = [p for p in candidates if matches(p, p.identify)]
    if exact:
        return exact, ""
    partial = [p for p in candidates if matches(p, [primary_identify(p)])]
    if not partial:
        return [], ""
    shown = ", ".join(f"0x{a:04X}={code}" for a, code in sorted(codes.items()))
    return partial, f"sensor type known but sub-type unexpected ({shown})"


def _by_factory_address(profiles: Sequence[Profile], address: int) -> Profile | None:
    for profile in profiles:
        if profile.serial is not None and profile.serial.address == address:
            return profile
    return None


def tecline_variant(
    profiles: Sequence[Profile], address: int
) -> tuple[Profile, bool, tuple[str, ...]]:
    """The tecLine registers do not name the variant: go by the factory address, else Cl2."""
    by_address = _by_factory_address(profiles, address)
    if by_address is not None:
        note = (
            f"tecLine variant guessed from the factory default address {address} "
            f"({by_address.id}); no register tells the variants apart"
        )
        return by_address, True, (note,)
    default = next(p for p in profiles if p.id == "jumo-tecline-cl2")
    note = (
        "tecLine variant cannot be read from the registers: jumo-tecline-cl2 is a guess; "
        "check the nameplate (Cl2, TC, ClO2, O3, H2O2, PAA, Br, Cl2 OM)"
    )
    return default, True, (note,)


def reiss_variant(
    profiles: Sequence[Profile], sensor_type: str, address: int
) -> tuple[Profile, bool, tuple[str, ...]]:
    """M0c or M3c from the sensor type string's suffix; else by factory address, a guess."""
    by_id = {p.id: p for p in profiles}
    suffix = _REISS_SUFFIX.search(sensor_type)
    if suffix is not None and _REISS_VARIANTS[suffix[1]] in by_id:
        return by_id[_REISS_VARIANTS[suffix[1]]], False, ()
    guess = _by_factory_address(profiles, address) or profiles[0]
    note = f"Reiss sensor type {sensor_type!r} names no variant: {guess.id} is a guess"
    return guess, True, (note,)
