"""A grab-sample verification as sensor care reads it: when, how far off, and whether it passed.

The verification itself (its record, its acceptance rule, the sensor's value at the
sample's time) lives a floor above, with the records; care only needs its outcome. A
passed one is the check the tecLine manual asks for weekly (annex 7.3.4: compare the
measured value with a reference, such as a DPD grab sample for chlorine), so the due date
runs from it as from a calibration; a failed one calls for a calibration
(:func:`~gateway.care.assess.assess`). This is the value the app hands
:meth:`~gateway.care.book.CareBook.verified`, built from each verification record.
"""

from __future__ import annotations

from dataclasses import dataclass
from datetime import UTC, datetime
from typing import Any


@dataclass(frozen=True, slots=True, kw_only=True)
class Verification:
    """One grab sample compared with the sensor's value, as its record judged it.

    ``at`` is when the sample was taken (aware; the sensor's value is the one it read
    then), not when it was entered. ``deviation`` is the sensor's value minus the
    reference, ``limit`` the largest deviation the rule allows (positive), both in
    ``unit``. ``rule`` names the acceptance rule (``"EPA 334.0"``); ``record`` is the
    number of the record that holds it, None where it has none (a test, a dry run).

    Example::

        Verification(at=datetime(2026, 12, 2, 8, 10, tzinfo=UTC), passed=False,
                     reference=0.50, sensor_value=0.75, deviation=0.25, limit=0.10,
                     unit="mg/L", rule="EPA 334.0", record=42)
    """

    at: datetime
    passed: bool
    reference: float
    sensor_value: float
    deviation: float
    limit: float
    unit: str | None
    rule: str
    record: int | None = None

    def __post_init__(self) -> None:
        """Refuse a zone-less time: it would be compared with UTC calibration stamps."""
        if self.at.tzinfo is None or self.at.utcoffset() is None:
            msg = f"a verification's time must carry its zone (UTC), got {self.at.isoformat()}"
            raise ValueError(msg)

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready, as the care document (``last_verification``) shows it."""
        return {
            "at": self.at.astimezone(UTC).isoformat(timespec="seconds"),
            "passed": self.passed,
            "reference": self.reference,
            "sensor_value": self.sensor_value,
            "deviation": round(self.deviation, 6),
            "limit": round(self.limit, 6),
            "unit": self.unit,
            "rule": self.rule,
            "record": self.record,
        }


def later(kept: Verification | None, new: Verification | None) -> Verification | None:
    """Of a verification kept and a new one, the one whose sample was taken last.

    A verification may be entered late (``gateway verify --sampled-at``), so the newest
    entry is not always the newest sample; at the same time the new one wins. None: none
    of the two.
    """
    if kept is None:
        return new
    if new is None or new.at < kept.at:
        return kept
    return new
