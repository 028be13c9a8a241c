"""What care's rules found so far for one device, and the dates they speak of.

Shared by the rules of every family (:mod:`~gateway.care.amperometric`,
:mod:`~gateway.care.optical`) and the verdict that gathers them
(:func:`~gateway.care.assess.assess`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from datetime import datetime, timedelta, tzinfo
from typing import TYPE_CHECKING, Any, Final

from gateway.care.report import CareState, Finding

if TYPE_CHECKING:
    from collections.abc import Sequence

    from gateway.care.records import Records
    from gateway.care.report import Projection, Trend
    from gateway.care.rules import CareRules
    from gateway.care.verifications import Verification

# A stamp this far ahead of the gateway's clock is in the future (a stamp has minutes only).
FUTURE_TOLERANCE: Final = timedelta(minutes=10)


@dataclass(slots=True)
class Draft:
    """What the rules found so far; becomes a :class:`~gateway.care.report.CareReport`."""

    findings: list[Finding] = field(default_factory=list)
    last_calibration: datetime | None = None
    passed: Verification | None = None  # the latest passed verification: a check too
    due: datetime | None = None
    slope_ratio: float | None = None
    slope_trend: Trend | None = None
    projection: Projection | None = None
    projection_note: str = ""
    cap_usage: float | None = None
    figures: dict[str, Any] = field(default_factory=dict)
    records: dict[str, Any] = field(default_factory=dict)

    def add(self, state: CareState, text: str) -> None:
        """One more finding: ``state`` and why, in an operator's words."""
        self.findings.append(Finding(state=state, text=text))


@dataclass(frozen=True, slots=True)
class Words:
    """Dates as an operator reads them: ``Tue 3 Dec 2024``, in the plant's zone."""

    zone: tzinfo | None

    def local(self, when: datetime) -> datetime:
        """``when`` in the plant's zone (the host's, where none is set)."""
        return when.astimezone(self.zone) if self.zone is not None else when.astimezone()

    def day(self, when: datetime) -> str:
        """The day of ``when`` as an operator writes it: ``Tue 3 Dec 2024``."""
        local = self.local(when)
        return f"{local:%a} {local.day} {local:%b %Y}"

    def stamp(self, naive: datetime) -> datetime:
        """A zone-less tecLine/Reiss stamp as an aware time."""
        return naive.replace(tzinfo=self.zone) if self.zone is not None else naive.astimezone()


def missing_records(records: Records, names: Sequence[str], draft: Draft, what: str) -> bool:
    """Add an ``unknown`` for records not read; True if any is missing."""
    missing = records.missing(names)
    if not missing:
        return False
    by_reason: dict[str, list[str]] = {}
    for name, reason in sorted(missing.items()):
        by_reason.setdefault(reason, []).append(name)
    # One reason once, with every record it stands for (a closed port is one reason).
    listed = "; ".join(f"{', '.join(names)} ({reason})" for reason, names in by_reason.items())
    draft.add(CareState.UNKNOWN, f"{what} could not be read: {listed}")
    return True


def due_from(
    draft: Draft,
    rules: CareRules,
    last: datetime,
    *,
    now: datetime,
    words: Words,
    what: str = "calibrate",
) -> None:
    """Due, due soon or fine, from the last check and the interval in force.

    The last check is the last calibration, or the last passed grab-sample verification
    if that is later: tecLine annex 7.3.4's weekly check is a comparison with a reference
    sample, which a passed verification is.
    """
    interval = rules.calibration_interval_days
    if interval is None:
        return
    every = "weekly" if interval == 7 else f"every {interval:g} days"  # noqa: PLR2004
    context = f"last {words.day(last)}, {every}"
    checked = draft.passed
    if checked is not None and checked.at > last:
        context = (
            f"grab sample passed {words.day(checked.at)}, calibrated {words.day(last)}, {every}"
        )
        last = checked.at
    due = last + timedelta(days=interval)
    draft.due = due
    if now >= due:
        late = (now - due).days
        since = f"for {late} day{'s' if late != 1 else ''}" if late else "since today"
        draft.add(CareState.DUE, f"{what}: overdue {since}, due {words.day(due)} ({context})")
    elif now >= due - timedelta(days=rules.due_soon_days):
        draft.add(CareState.DUE_SOON, f"{what} by {words.day(due)} ({context})")
    else:
        draft.add(CareState.OK, f"{what} by {words.day(due)} ({context})")
