"""Grab-sample verification: the acceptance rule, its judgement, and what a record keeps of it.

A drinking-water utility compares the online chlorine value with a DPD grab sample and
keeps the comparison (EPA Method 334.0, "Determination of residual chlorine in drinking
water using an on-line chlorine analyzer", EPA 815-B-09-013, 2009: the online value within
±0.1 mg/L or ±15 % of the grab sample's, whichever is larger). The rule is stored in the record
with its name and parameters, so a record says by what it passed or failed, also after
the config changed.

Decimal arithmetic on the values as entered (the reference) and as the sensor's float32
can hold them (seven significant digits): a deviation exactly on the limit passes, as the
rule says ("within"), and no binary rounding turns 2.00 - 1.70 into 0.30000000000000004.

Pure: no I/O. :func:`care_verification` hands a verification's record to sensor care.
"""

from __future__ import annotations

from dataclasses import dataclass
from datetime import UTC, datetime
from decimal import Decimal
from typing import TYPE_CHECKING, Final

from gateway.care.verifications import Verification

if TYPE_CHECKING:
    from gateway.config.verification import VerificationConfig
    from gateway.profiles import Profile
    from gateway.records.model import Record

FLOAT32_DIGITS: Final = 7  # significant decimal digits a float32 holds


@dataclass(frozen=True, slots=True, kw_only=True)
class AcceptanceRule:
    """Pass within the larger of ``absolute`` (in ``unit``) and ``relative`` times the reference."""

    name: str
    absolute: float
    relative: float
    unit: str | None  # the unit ``absolute`` is in; None: the sensor's, whatever it is
    source: str = ""

    def limit(self, reference: Decimal) -> Decimal:
        """The deviation allowed at ``reference``."""
        return max(_decimal(self.absolute), _decimal(self.relative) * abs(reference))

    def as_dict(self) -> dict[str, object]:
        """The rule as a record stores it: name and every parameter."""
        return {
            "name": self.name,
            "absolute": self.absolute,
            "relative": self.relative,
            "unit": self.unit,
            "source": self.source,
        }


EPA_334: Final = AcceptanceRule(
    name="EPA 334.0",
    absolute=0.1,
    relative=0.15,
    unit="mg/l",
    source="EPA Method 334.0 (EPA 815-B-09-013, September 2009): the on-line analyzer's "
    "reading within ±0.1 mg/L or ±15 % of the grab sample's, whichever is larger",
)
OXYGEN_DEFAULT: Final = AcceptanceRule(
    name="gateway default for dissolved oxygen",
    absolute=0.2,
    relative=0.05,
    unit="mg/l",
    source="the gateway's default (no manual of the digiLine O-DO sensors gives one); set "
    "verification.rules to your plant's",
)
# Which built-in rule a family's process value is judged by (profile data: the family).
BUILT_IN: Final = {
    "jumo-tecline": EPA_334,
    "reiss-m0c-m3c": EPA_334,
    "jumo-digiline-odo-s10": OXYGEN_DEFAULT,
    "jumo-digiline-odo-h10-h20": OXYGEN_DEFAULT,
}


def rule_for(config: VerificationConfig, *, device: str, profile: Profile) -> AcceptanceRule | None:
    """The rule of a device: the config's by device, profile or family, else the built-in."""
    for key in (device, profile.id, profile.family):
        configured = config.rules.get(key)
        if configured is not None:
            return AcceptanceRule(
                name=configured.name,
                absolute=configured.absolute,
                relative=configured.relative,
                unit=configured.unit,
                source=configured.source or f"the config's verification.rules.{key}",
            )
    return BUILT_IN.get(profile.family)


def same_unit(one: str | None, other: str | None) -> bool:
    """Whether two units are the same (``mg/l``, ``mg/L``, ``ppm`` in water are one)."""
    if one is None or other is None:
        return True
    aliases = {"ppm": "mg/l"}
    first, second = one.strip().lower(), other.strip().lower()
    return aliases.get(first, first) == aliases.get(second, second)


def _decimal(value: float) -> Decimal:
    return Decimal(repr(value))


def sensor_decimal(value: float) -> Decimal:
    """A sensor's float32 value at the precision it has (seven significant digits)."""
    return Decimal(f"{value:.{FLOAT32_DIGITS}g}")


@dataclass(frozen=True, slots=True, kw_only=True)
class Judgement:
    """A verification's verdict: the deviation (sensor - reference) against the limit."""

    reference: Decimal
    sensor: Decimal
    deviation: Decimal
    limit: Decimal
    passed: bool

    def as_dict(self) -> dict[str, object]:
        """The numbers as a record keeps them (exact decimals, as text-free JSON numbers)."""
        return {
            "reference": float(self.reference),
            "sensor_value": float(self.sensor),
            "deviation": float(self.deviation),
            "limit": float(self.limit),
            "passed": self.passed,
        }


def judge(rule: AcceptanceRule, *, reference: float, sensor: float) -> Judgement:
    """Whether ``sensor`` is within ``rule`` of ``reference``; on the limit passes."""
    given = _decimal(reference)
    read = sensor_decimal(sensor)
    deviation = read - given
    limit = rule.limit(given)
    return Judgement(
        reference=given,
        sensor=read,
        deviation=deviation,
        limit=limit,
        passed=abs(deviation) <= limit,
    )


def care_verification(record: Record) -> Verification | None:
    """A verification record as sensor care weighs it (``None`` for another kind)."""
    body = record.body
    if body.get("kind") != "verification":
        return None
    data = body.get("data") or {}
    try:
        at = datetime.fromisoformat(str(data["sampled_at"]))
        rule = data.get("rule") or {}
        return Verification(
            at=at if at.tzinfo is not None else at.replace(tzinfo=UTC),
            passed=bool(data["passed"]),
            reference=float(data["reference"]),
            sensor_value=float(data["sensor_value"]),
            deviation=float(data["deviation"]),
            limit=float(data["limit"]),
            unit=data.get("unit"),
            rule=str(rule.get("name", "")),
            record=record.seq,
        )
    except (KeyError, TypeError, ValueError):
        return None  # a record of an older layout: care does without it
