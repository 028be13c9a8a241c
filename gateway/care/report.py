"""What sensor care says of one device: its state, the reasons, and the figures behind them."""

from __future__ import annotations

from dataclasses import dataclass, field
from datetime import UTC, datetime
from enum import StrEnum
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from collections.abc import Iterable

    from gateway.care.verifications import Verification


class CareState(StrEnum):
    """The overall verdict of a device, least to most urgent (the order is the severity)."""

    OK = "ok"  # nothing to do now
    DUE_SOON = "due_soon"  # calibrate (or plan service) within the next days
    DUE = "due"  # calibration overdue, or a limit since the last calibration reached
    UNKNOWN = "unknown"  # the records could not be read or do not agree
    MAINTENANCE = "maintenance"  # the sensor needs service: membrane, electrolyte, cap

    @property
    def severity(self) -> int:
        """0 for ``ok`` up to 4 for ``maintenance``: the worst finding decides."""
        return _ORDER.index(self)


_ORDER = tuple(CareState)
CARE_STATES: tuple[str, ...] = tuple(state.value for state in CareState)


@dataclass(frozen=True, slots=True, kw_only=True)
class Finding:
    """One thing care found, the state it calls for, in words a plant operator uses."""

    state: CareState
    text: str


@dataclass(frozen=True, slots=True, kw_only=True)
class Projection:
    """When a falling slope crosses its limit, from a least-squares fit over the history."""

    at: datetime  # the fitted line crosses the limit
    earliest: datetime  # with the fitted fall rate at the steep end of its 90 % interval
    latest: datetime | None  # at the shallow end; None: that end does not fall
    confidence: str  # "high" or "medium"

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready."""
        return {
            "at": _iso(self.at),
            "earliest": _iso(self.earliest),
            "latest": _iso(self.latest) if self.latest is not None else None,
            "confidence": self.confidence,
        }


@dataclass(frozen=True, slots=True, kw_only=True)
class Trend:
    """A least-squares line through (time, value) points, per week, with its fit."""

    per_week: float  # change of the value per week
    r2: float  # coefficient of determination, 0..1 (1: every point on the line)
    points: int  # how many calibrations it was fitted over
    since: datetime  # the oldest calibration in the fit

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready."""
        return {
            "per_week": round(self.per_week, 6),
            "r2": round(self.r2, 4),
            "points": self.points,
            "since": _iso(self.since),
        }


@dataclass(frozen=True, slots=True, kw_only=True)
class CareReport:
    """What one device needs and when; everything the publishers and the page show.

    ``key`` leaves out what only time changes (the ages), so a publisher compares keys to
    send a new document only when something a reader acts on has changed.
    """

    device: str
    bus: str
    profile: str
    kind: str  # "amperometric", "optical_hygienic" (H10/H20), "optical" (S10)
    state: CareState
    findings: tuple[Finding, ...]
    assessed_at: datetime
    interval_days: float | None  # the calibration interval in force
    interval_source: str  # where that interval comes from (manual, default, config)
    last_calibration: datetime | None = None
    due: datetime | None = None
    slope_ratio: float | None = None  # active slope / nominal slope
    slope_limit: float | None = None  # the ratio below which the sensor needs maintenance
    slope_trend: Trend | None = None
    projection: Projection | None = None
    projection_note: str = ""  # why there is no projection, if there is none
    cap_usage: float | None = None  # measurement counter / maximum (H10/H20)
    figures: dict[str, Any] = field(default_factory=dict)  # the other numbers, JSON-ready
    records: dict[str, Any] = field(default_factory=dict)  # the records used, JSON-ready
    # The newest grab sample compared with the sensor (passed or not), None: none yet.
    last_verification: Verification | None = None

    @property
    def reasons(self) -> tuple[str, ...]:
        """The findings' words, the most urgent first."""
        ranked = sorted(self.findings, key=lambda f: -f.state.severity)
        return tuple(f.text for f in ranked)

    @property
    def key(self) -> tuple[object, ...]:
        """What a published document depends on, besides the time it was assessed."""
        return (
            self.state,
            self.findings,
            self.last_calibration,
            self.due,
            None if self.slope_ratio is None else round(self.slope_ratio, 4),
            self.slope_trend,
            self.projection,
            self.projection_note,
            None if self.cap_usage is None else round(self.cap_usage, 4),
            repr(sorted(self.figures.items())),
            repr(sorted(self.records.items())),
            self.last_verification,
        )

    def as_dict(self) -> dict[str, Any]:
        """The care document (MQTT ``{base}/{device}/care``, ``gateway care --json``)."""
        return {
            "device": self.device,
            "bus": self.bus,
            "profile": self.profile,
            "state": self.state.value,
            "reasons": list(self.reasons),
            "last_calibration": _iso(self.last_calibration),
            "due": _iso(self.due),
            "interval_days": self.interval_days,
            "interval_source": self.interval_source,
            "slope_ratio": None if self.slope_ratio is None else round(self.slope_ratio, 4),
            "slope_limit": self.slope_limit,
            "slope_trend": self.slope_trend.as_dict() if self.slope_trend else None,
            "projection": self.projection.as_dict() if self.projection else None,
            "projection_note": self.projection_note or None,
            "cap_usage": None if self.cap_usage is None else round(self.cap_usage, 4),
            "figures": self.figures,
            "records": self.records,
            "last_verification": (
                self.last_verification.as_dict() if self.last_verification else None
            ),
            "assessed_at": _iso(self.assessed_at),
        }


def _iso(when: datetime | None) -> str | None:
    """A time as ISO 8601 in UTC, to the second (None stays None)."""
    if when is None:
        return None
    return when.astimezone(UTC).isoformat(timespec="seconds")


def care_order(reports: Iterable[CareReport]) -> list[CareReport]:
    """Most urgent first: by state, then the earliest due date, then the device's name."""
    far = datetime.max.replace(tzinfo=UTC)
    return sorted(
        reports,
        key=lambda r: (-r.state.severity, r.due or far, r.device),
    )
