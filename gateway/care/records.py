"""Which of a device's points sensor care reads, and those points' values in care's words.

The records are points the gateway polls anyway (diagnostics, configuration, identity):
care reads nothing of its own. A value that could not be read is kept apart with the
reason, so the verdict can say which record it is missing.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from datetime import datetime
from typing import TYPE_CHECKING, Final, Protocol, TypeAlias

from gateway.care.rules import HISTORY, CareKind, care_ring
from gateway.wire.codec import BitfieldValue, EnumValue

if TYPE_CHECKING:
    from collections.abc import Iterable, Mapping, Sequence

    from gateway.profiles import Profile, Ring
    from gateway.wire import codec

# The fields of each entry that care judges (the logbook has more); how many entries a ring
# has, how the sensor numbers them and their fields are the profile's (``Profile.ring``).
HISTORY_FIELDS: Final = ("x_zero", "x_span", "stamp")
LOGBOOK_FIELDS: Final = (
    "entry_type",
    "manual_change",
    "rating",
    "operating_seconds",
    "date",
    "sensor_replacement_counter",
    "phase",
)
_CURRENT: Final[Mapping[CareKind, tuple[str, ...]]] = {
    CareKind.AMPEROMETRIC: ("x_zero", "x_span", "calibration_stamp", "nominal_slope", "unit"),
    CareKind.OPTICAL_HYGIENIC: (
        "operating_seconds",
        "sensor_replacement_counter",
        "measurement_counter",
        "measurement_counter_max",
        "cip_cycles_since_calibration",
        "sip_cycles_since_calibration",
        "hours_outside_operating_temperature",
        "error_register",
        "status",
    ),
    CareKind.OPTICAL: ("operating_seconds", "commissioning_date", "status"),
}
# The bits of the status and error words that care judges; the others (such as the H10's
# "new values", which changes with every measurement) do not make it assess again.
CARE_BITS: Final[Mapping[str, frozenset[str]]] = {
    "status": frozenset(
        {"cap_missing", "cap_replacement_recommended", "measurement_count_exceeded"}
    ),
    "error_register": frozenset({"measurement_counter_overflow"}),
}
# Shown in the care document when the profile has them; the verdict does not need them.
OPTIONAL: Final = frozenset({"cap_serial_number", "cap_part_number", "commissioning_date"})


def care_points(profile: Profile, kind: CareKind) -> tuple[str, ...]:
    """The points of ``profile`` that care reads, those the verdict needs first."""
    names = [name for name in _CURRENT[kind] if profile.has_point(name)]
    ring = care_ring(profile, kind)
    if ring is not None:
        judged = HISTORY_FIELDS if ring.name == HISTORY else LOGBOOK_FIELDS
        names += ring.points(*(f for f in ring.fields if f in judged))
    names += [name for name in sorted(OPTIONAL) if profile.has_point(name) and name not in names]
    return tuple(names)


def same_record(name: str, before: codec.Decoded, after: codec.Decoded) -> bool:
    """Whether a new value of a record changes nothing care judges."""
    bits = CARE_BITS.get(name)
    if bits is not None and isinstance(before, BitfieldValue) and isinstance(after, BitfieldValue):
        old, new = dict(before.flags), dict(after.flags)
        return all(old.get(bit) == new.get(bit) for bit in bits)
    return before == after


@dataclass(frozen=True, slots=True)
class Records:
    """A device's care records: each point's value, or why it could not be read."""

    values: Mapping[str, codec.Decoded] = field(default_factory=dict)
    unreadable: Mapping[str, str] = field(default_factory=dict)  # point -> reason

    def number(self, name: str) -> float | None:
        """A finite numeric value, or None (absent, unreadable, a fault, not a number)."""
        value = self.values.get(name)
        if isinstance(value, bool) or not isinstance(value, int | float):
            return None
        return float(value) if math.isfinite(value) else None

    def date(self, name: str) -> datetime | None:
        """A date-time value, or None."""
        value = self.values.get(name)
        return value if isinstance(value, datetime) else None

    def label(self, name: str) -> str | None:
        """An enumeration's label (a code the manual does not name: ``code_N``), or None."""
        value = self.values.get(name)
        if isinstance(value, EnumValue):
            return value.label if value.known else f"code_{value.code}"
        return None

    def flag(self, name: str, bit: str) -> bool | None:
        """One bit of a bit field, or None when the field was not read."""
        value = self.values.get(name)
        if isinstance(value, BitfieldValue):
            return dict(value.flags).get(bit, False)
        return None

    def missing(self, names: Iterable[str]) -> dict[str, str]:
        """Of ``names``, those without a value, with the reason (``not read yet``)."""
        return {
            name: self.unreadable.get(name, "not read yet")
            for name in names
            if name not in self.values or name in self.unreadable
        }


# --- the entries of the sensors' own rings ---------------------------------------------------
#
# The history and the logbook are rings that overwrite: the gateway copies each entry into
# its records as it appears (``gateway.records.history``, a floor above), and hands care the
# whole copied history back through :data:`PastEntries`. These are the entries as care reads
# them from the current ring, and as that copy gives them back.


@dataclass(frozen=True, slots=True, kw_only=True)
class Calibration:
    """One tecLine/Reiss history entry (annex 7.2 / Reiss 5.1): a calibration in force once.

    ``stamp`` is zone-less, as the sensor keeps it (the wall-clock time of whoever
    calibrated). ``number`` is where the sensor's history holds it now (0 newest), None for
    an entry given back from the copy; it is not part of the entry's identity.
    """

    x_zero: float
    x_span: float
    stamp: datetime
    number: int | None = field(default=None, compare=False)


@dataclass(frozen=True, slots=True, kw_only=True)
class LogbookEntry:
    """One H10/H20 calibration logbook entry (6.1.6), the fields care judges.

    ``number`` is where the sensor's logbook holds it now (1 newest), None for an entry
    given back from the copy; it is not part of the entry's identity.
    """

    kind: str  # the entry type's label: zero_point, end_value
    manual: bool
    rating: str
    operating_s: float | None
    date: datetime | None
    cap_counter: float | None
    phase: float | None
    number: int | None = field(default=None, compare=False)

    def as_dict(self) -> dict[str, object]:
        """As the care document shows it."""
        return {
            "entry": self.number,
            "type": self.kind,
            "manual_change": self.manual,
            "rating": self.rating,
            "operating_seconds": self.operating_s,
            "date": None if self.date is None else self.date.isoformat(timespec="seconds"),
            "cap_changes": self.cap_counter,
            "phase": self.phase,
        }


SensorEntry: TypeAlias = Calibration | LogbookEntry


class PastEntries(Protocol):
    """The seam to the copy of the rings, which lives a floor above care (the records).

    Given a device's name and the entries its ring holds now, it keeps those it had not
    yet and gives back every entry it holds of that sensor, oldest first (the ring's own
    among them; only the ring's while the copy cannot be made). The app wires it
    (:meth:`gateway.care.book.CareBook.keep_history`).
    """

    def __call__(self, device: str, ring: Sequence[SensorEntry], /) -> Sequence[SensorEntry]:
        """Keep what ``ring`` holds that was not kept yet; every entry kept, oldest first."""
        ...


def history_entries(records: Records, ring: Ring) -> tuple[Calibration, ...]:
    """The filled entries of the tecLine/Reiss history, newest first.

    An entry is filled when its stamp is set (a sensor keeps 0 in the ones never used) and
    both its values are numbers; one the bus could not read is left out, not guessed.
    """
    entries = []
    for number in ring.numbers:
        zero, span, stamp = (
            records.number(ring.point(number, "x_zero")),
            records.number(ring.point(number, "x_span")),
            records.date(ring.point(number, "stamp")),
        )
        if zero is None or span is None or stamp is None:
            continue
        entries.append(Calibration(x_zero=zero, x_span=span, stamp=stamp, number=number))
    return tuple(entries)


def logbook_entries(records: Records, ring: Ring) -> tuple[LogbookEntry, ...]:
    """The filled H10/H20 logbook entries, in the device's own order (1 newest)."""
    entries = []
    for number in ring.numbers:
        prefix = ring.point(number, "")
        kind = records.label(f"{prefix}entry_type")
        if kind is None or kind == "none" or kind.startswith("code_"):
            continue  # 6.1.6 "kein Eintrag", or erased flash
        entries.append(
            LogbookEntry(
                kind=kind,
                manual=records.label(f"{prefix}manual_change") == "manual",
                rating=records.label(f"{prefix}rating") or "none",
                operating_s=records.number(f"{prefix}operating_seconds"),
                date=records.date(f"{prefix}date"),
                cap_counter=records.number(f"{prefix}sensor_replacement_counter"),
                phase=records.number(f"{prefix}phase"),
                number=number,
            )
        )
    return tuple(entries)


def ring_entries(records: Records, ring: Ring | None) -> tuple[SensorEntry, ...]:
    """The entries of the ring a sensor keeps (none for the S10), as the sensor orders them."""
    if ring is None:
        return ()
    if ring.name == HISTORY:
        return history_entries(records, ring)
    return logbook_entries(records, ring)
