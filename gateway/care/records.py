"""Which of a device's points sensor care reads, and those points' values in care's words.

The records are points the gateway polls anyway (diagnostics, configuration, identity):
care reads nothing of its own. A value that could not be read is kept apart with the
reason, so the verdict can say which record it is missing.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from datetime import datetime
from typing import TYPE_CHECKING, Final

from gateway.care.rules import CareKind
from gateway.wire.codec import BitfieldValue, EnumValue

if TYPE_CHECKING:
    from collections.abc import Iterable, Mapping

    from gateway.profiles import Profile
    from gateway.wire import codec

HISTORY: Final = "history"  # tecLine annex 7.2 / Reiss 5.1: entries 0 (newest) to 4
LOGBOOK: Final = "logbook"  # H10/H20 6.1.6: entries 1 to 10
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
    repeat, wanted = (
        (HISTORY, HISTORY_FIELDS) if kind is CareKind.AMPEROMETRIC else (LOGBOOK, LOGBOOK_FIELDS)
    )
    names = [name for name in _CURRENT[kind] if profile.has_point(name)]
    if kind is not CareKind.OPTICAL:
        names += [
            point.name
            for point in profile.points
            if point.repeat == repeat and point.name.endswith(tuple(f"_{f}" for f in wanted))
        ]
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
