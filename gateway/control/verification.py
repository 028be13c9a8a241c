"""A grab-sample verification of one device: judged by its rule, recorded, nothing written.

The same act from every way in (``gateway verify``, MQTT's ``…/command/verify``, the
page): a :class:`VerificationRequest` checked where it comes in, the sensor's value at the
sample's time (the running gateway's :class:`~gateway.records.recent.RecentValues`, or a
read now from the command line without one), the device's acceptance rule
(:func:`gateway.records.verification.rule_for`), and one record of kind ``verification``
by the current actor, with the rule's name and parameters, the deviation and the verdict.
A verification writes nothing to the sensor.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import TYPE_CHECKING, Final

from gateway.errors import CommandRejectedError
from gateway.profiles.model import PollGroup
from gateway.records.model import Kind, PointChange, Result
from gateway.records.verification import judge, same_unit
from gateway.wire.codec import DataType

if TYPE_CHECKING:
    from collections.abc import Awaitable, Callable, Mapping

    from gateway.control.writes import SafeWriter
    from gateway.profiles import Profile
    from gateway.profiles.model import Point
    from gateway.records.model import Record
    from gateway.records.recent import RecentValues, ValueAt
    from gateway.records.verification import AcceptanceRule, Judgement

MAX_TEXT: Final = 200  # a method's or an instrument's name
_KEYS: Final = frozenset(
    {"reference", "unit", "method", "instrument", "sampled_at", "point", "reason"}
)
_NUMBER_TYPES: Final = frozenset({DataType.FLOAT32})


@dataclass(frozen=True, slots=True, kw_only=True)
class VerificationRequest:
    """What the operator entered: the reference, how it was analysed, when it was sampled."""

    reference: float
    method: str
    unit: str | None = None
    instrument: str = ""
    sampled_at: datetime | None = None  # None: now
    point: str | None = None  # None: the device's process value
    reason: str = ""

    @classmethod
    def from_arguments(cls, arguments: Mapping[str, object]) -> VerificationRequest:
        """From a JSON object (MQTT, the page, the command line's request to a gateway)."""
        unknown = sorted(set(arguments) - _KEYS)
        if unknown:
            allowed = ", ".join(sorted(_KEYS))
            raise CommandRejectedError(f"unknown keys {unknown}; allowed: {allowed}")
        reference = arguments.get("reference")
        if isinstance(reference, bool) or not isinstance(reference, int | float):
            raise CommandRejectedError(f"reference must be a number, got {reference!r}")
        if not math.isfinite(reference) or reference < 0:
            raise CommandRejectedError(f"reference must be 0 or more, got {reference!r}")
        method = _text(arguments, "method", required=True)
        sampled = arguments.get("sampled_at")
        sampled_at = None
        if sampled is not None:
            if not isinstance(sampled, str):
                raise CommandRejectedError("sampled_at must be an ISO 8601 time as text")
            sampled_at = parse_time(sampled)
        return cls(
            reference=float(reference),
            method=method,
            unit=_text(arguments, "unit") or None,
            instrument=_text(arguments, "instrument"),
            sampled_at=sampled_at,
            point=_text(arguments, "point") or None,
            reason=_text(arguments, "reason"),
        )

    def as_dict(self) -> dict[str, object]:
        """JSON-ready: what the command line sends a running gateway."""
        return {
            "reference": self.reference,
            "method": self.method,
            "unit": self.unit,
            "instrument": self.instrument or None,
            "sampled_at": None if self.sampled_at is None else self.sampled_at.isoformat(),
            "point": self.point,
            "reason": self.reason or None,
        }


def _text(arguments: Mapping[str, object], key: str, *, required: bool = False) -> str:
    value = arguments.get(key)
    if value is None:
        if required:
            raise CommandRejectedError(f"{key} is needed (e.g. DPD, photometer, titration)")
        return ""
    if not isinstance(value, str) or len(value) > MAX_TEXT:
        raise CommandRejectedError(f"{key} must be text of at most {MAX_TEXT} characters")
    text = " ".join(value.split())
    if required and not text:
        raise CommandRejectedError(f"{key} must not be empty")
    return text


def parse_time(text: str) -> datetime:
    """An ISO 8601 time; one without a zone is UTC (as the records are)."""
    try:
        moment = datetime.fromisoformat(text.strip())
    except ValueError as exc:
        raise CommandRejectedError(f"{text!r} is not an ISO 8601 time") from exc
    return moment if moment.tzinfo is not None else moment.replace(tzinfo=UTC)


def verifiable_point(profile: Profile, name: str | None = None) -> Point:
    """The point a verification compares: the named one, else the first process value."""
    if name is not None:
        point = profile.point(name)
        if point.format.dtype not in _NUMBER_TYPES:
            raise CommandRejectedError(f"{name} is not a measured value to verify")
        return point
    for point in profile.points_in(PollGroup.PROCESS):
        if point.format.dtype in _NUMBER_TYPES:
            return point
    raise CommandRejectedError(f"{profile.id} has no process value to verify")


@dataclass(frozen=True, slots=True, kw_only=True)
class Verified:
    """A verification's outcome: its record, the verdict, the value compared."""

    record: Record
    judgement: Judgement
    rule: AcceptanceRule
    value: ValueAt

    def as_dict(self) -> dict[str, object]:
        """JSON-ready: the MQTT result, the page's and the command line's answer."""
        return {
            "record": self.record.seq,
            "passed": self.judgement.passed,
            **self.judgement.as_dict(),
            "unit": self.value.unit,
            "sensor_time": self.value.at.isoformat(timespec="seconds"),
            "rule": self.rule.as_dict(),
        }


async def verify(
    writer: SafeWriter,
    request: VerificationRequest,
    *,
    rule: AcceptanceRule | None,
    value_at: Callable[[str, Point, datetime], Awaitable[ValueAt]],
    now: datetime,
) -> Verified:
    """Judge the device's value at the sample's time by ``rule``; record it; write nothing.

    A :class:`CommandRejectedError` (nothing recorded) for a device without a rule, a unit
    other than the sensor's or the rule's, a time out of the window.
    """
    device = writer.device
    if writer.recorder is None:
        raise CommandRejectedError(f"{device}: no record store to record a verification in")
    profile = writer.link.profile
    point = verifiable_point(profile, request.point)
    if rule is None:
        raise CommandRejectedError(
            f"{device} ({profile.id}) has no acceptance rule: set verification.rules."
            f"{device} (name, absolute, relative, unit) in the config"
        )
    at = request.sampled_at or now
    value = await value_at(device, point, at)
    if not same_unit(request.unit, value.unit):
        raise CommandRejectedError(
            f"the reference is in {request.unit}, but {device} reports {point.name} in "
            f"{value.unit}: enter it in the sensor's unit"
        )
    if not same_unit(rule.unit, value.unit):
        raise CommandRejectedError(
            f"the rule {rule.name!r} is in {rule.unit}, but {device} reports {point.name} in "
            f"{value.unit}: set verification.rules.{device} in the sensor's unit"
        )
    judgement = judge(rule, reference=request.reference, sensor=value.value)
    verdict = "passed" if judgement.passed else "failed"
    record = await writer.recorder.act(
        Kind.VERIFICATION,
        action=f"grab-sample verification ({request.method})",
        result=Result.PASSED if judgement.passed else Result.NOT_PASSED,
        note=(
            f"{verdict}: the sensor read {judgement.sensor} {value.unit or ''} against "
            f"{judgement.reference}, {judgement.deviation:+} off, "
            f"{'within' if judgement.passed else 'more than'} the {judgement.limit} "
            f"{rule.name} allows"
        ),
        points=(PointChange(point=point.name, unit=value.unit, as_found=value.value),),
        data={
            **judgement.as_dict(),
            "unit": value.unit,
            "method": request.method,
            "instrument": request.instrument or None,
            "sampled_at": at.astimezone(UTC).isoformat(timespec="seconds"),
            "sensor_time": value.at.isoformat(timespec="seconds"),
            "entered_late_s": round((now - at).total_seconds(), 1),
            "rule": rule.as_dict(),
        },
    )
    return Verified(record=record, judgement=judgement, rule=rule, value=value)


class Verifier:
    """The running gateway's verifications: its recent values, its rules, its writers.

    One per running gateway; MQTT's ``…/command/verify``, the page and ``gateway verify``
    (through the metrics port, from this machine) all come here.
    """

    def __init__(
        self,
        writers: Mapping[str, SafeWriter],
        recent: RecentValues,
        rules: Callable[[str, Profile], AcceptanceRule | None],
        *,
        clock: Callable[[], datetime] = lambda: datetime.now(UTC),
    ) -> None:
        """Verify the devices of ``writers`` against ``recent`` values by ``rules``."""
        self.writers = writers
        self.recent = recent
        self.rules = rules
        self._clock = clock

    async def verify(self, device: str, request: VerificationRequest) -> Verified:
        """Verify ``device`` for the current actor; refused (nothing recorded) if it cannot be."""
        writer = self.writers.get(device)
        if writer is None:
            known = ", ".join(sorted(self.writers)) or "none"
            raise CommandRejectedError(f"no device {device!r} (devices: {known})")
        now = self._clock()
        recent = self.recent

        async def value_at(name: str, point: Point, at: datetime) -> ValueAt:
            return recent.value_at(name, point.name, at, now=now)

        return await verify(
            writer,
            request,
            rule=self.rules(device, writer.link.profile),
            value_at=value_at,
            now=now,
        )
