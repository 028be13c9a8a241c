"""The verdict of sensor care for one device, from its records, its rules and the time.

Pure: the records come in as values (:class:`~gateway.care.records.Records`), the time as
an argument. Each rule adds a :class:`Finding` with the state it calls for, in words a
plant operator uses; the most urgent finding is the device's state. A record that is
missing, unreadable or inconsistent gives a named ``unknown``, never a made-up date.

Grab-sample verifications (:class:`~gateway.care.verifications.Verification`) count with
the sensor's own records: a passed one is the check the tecLine manual asks for weekly
(annex 7.3.4), so the due date runs from it as from a calibration; a failed one, with no
calibration since, calls for one.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from datetime import UTC, datetime, timedelta, tzinfo
from itertools import pairwise
from typing import TYPE_CHECKING, Any, Final

from gateway.care.records import (
    HISTORY_FIELDS,
    Calibration,
    LogbookEntry,
    Records,
    logbook_entries,
)
from gateway.care.report import CareReport, CareState, Finding
from gateway.care.rules import CareKind, CareRules
from gateway.care.trend import fit, project
from gateway.care.verifications import later

if TYPE_CHECKING:
    from collections.abc import Sequence

    from gateway.care.records import SensorEntry
    from gateway.care.report import Projection, Trend
    from gateway.care.verifications import Verification

# A stamp this far ahead of the gateway's clock is in the future (a stamp has minutes only).
FUTURE_TOLERANCE: Final = timedelta(minutes=10)
# A rise of the slope ratio by more than this between two calibrations is a service (new
# membrane cap and electrolyte) or the nominal slope restored (annex 7.5): the trend is
# fitted over the calibrations since the last one. Ours; the manuals name none.
SERVICE_RISE: Final = 0.10
# Calibrations that agree to this relative difference are the same (float32 read back).
_SAME: Final = 1e-4
ZERO_POINT_ENTRY: Final = "zero_point"  # 6.1.6 entry type 20


@dataclass(slots=True)
class _Draft:
    """What the rules found so far; becomes a :class:`CareReport`."""

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
        self.findings.append(Finding(state=state, text=text))


def assess(
    records: Records,
    rules: CareRules,
    *,
    device: str,
    bus: str,
    profile: str,
    now: datetime,
    zone: tzinfo | None = None,
    past: Sequence[SensorEntry] = (),
    last_verification: Verification | None = None,
    last_passed: Verification | None = None,
) -> CareReport:
    """The care report of one device at ``now`` (aware).

    ``zone``: the zone of the tecLine/Reiss stamps, which carry none (the gateway writes
    them in the host's local time); None: the host's local zone. Dates in the reasons are
    shown in it too. ``past``: the entries of the sensor's ring that the gateway copied
    before the ring overwrote them (:class:`~gateway.care.records.PastEntries`), any
    order; those older than the oldest the sensor still holds lengthen the trends.
    ``last_verification``: the device's newest grab-sample verification, passed or not;
    ``last_passed``: its newest passed one (None: none yet). Where the rules have a
    calibration interval, the due date runs from the later of the last calibration and
    the last passed verification; a failed verification with no calibration since makes
    the device ``due``.
    """
    latest = later(last_passed, last_verification)
    draft = _Draft(passed=last_passed)
    words = _Words(zone)
    if rules.kind is CareKind.AMPEROMETRIC:
        earlier = [e for e in past if isinstance(e, Calibration)]
        _amperometric(records, rules, draft, now=now, words=words, past=earlier)
    elif rules.kind is CareKind.OPTICAL_HYGIENIC:
        earlier_entries = [e for e in past if isinstance(e, LogbookEntry)]
        _optical_hygienic(records, rules, draft, now=now, words=words, past=earlier_entries)
    else:
        _optical(records, draft)
    if latest is not None and not latest.passed:
        _failed_sample(draft, rules, latest, words=words)
    state = max((f.state for f in draft.findings), key=lambda s: s.severity, default=CareState.OK)
    return CareReport(
        device=device,
        bus=bus,
        profile=profile,
        kind=rules.kind.value,
        state=state,
        findings=tuple(draft.findings),
        assessed_at=now,
        interval_days=rules.calibration_interval_days,
        interval_source=rules.interval_source,
        last_calibration=draft.last_calibration,
        due=draft.due,
        slope_ratio=draft.slope_ratio,
        slope_limit=rules.slope_limit if rules.kind is CareKind.AMPEROMETRIC else None,
        slope_trend=draft.slope_trend,
        projection=draft.projection,
        projection_note=draft.projection_note,
        cap_usage=draft.cap_usage,
        figures=draft.figures,
        records=draft.records,
        last_verification=latest,
    )


@dataclass(frozen=True, slots=True)
class _Words:
    """Dates as an operator reads them: ``Tue 3 Dec 2024``, in the plant's zone."""

    zone: tzinfo | None

    def local(self, when: datetime) -> datetime:
        return when.astimezone(self.zone) if self.zone is not None else when.astimezone()

    def day(self, when: datetime) -> str:
        local = self.local(when)
        return f"{local:%a} {local.day} {local:%b %Y}"

    def stamp(self, naive: datetime) -> datetime:
        """A zone-less tecLine/Reiss stamp as an aware time."""
        return naive.replace(tzinfo=self.zone) if self.zone is not None else naive.astimezone()


def _missing(records: Records, names: Sequence[str], draft: _Draft, what: str) -> bool:
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


def _due(
    draft: _Draft,
    rules: CareRules,
    last: datetime,
    *,
    now: datetime,
    words: _Words,
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


# What a failed grab sample asks for, by family. The S10 keeps no calibration that Modbus
# can read, so only another grab sample, passed, clears its failure.
_AFTER_A_FAILED_SAMPLE: Final = {
    CareKind.AMPEROMETRIC: "calibrate (tecLine annex 7.3.4)",
    CareKind.OPTICAL_HYGIENIC: "calibrate",
    CareKind.OPTICAL: (
        "calibrate it as its operating manual says, then take another grab sample (the S10 "
        "keeps no calibration record that Modbus can read)"
    ),
}


def _failed_sample(draft: _Draft, rules: CareRules, failed: Verification, *, words: _Words) -> None:
    """A failed verification with no calibration since: ``due``, with how far off it was.

    Calibration stamps carry minutes only, so a calibration stamped in the minute the
    sample was taken counts as after it (a sample is taken, then the sensor calibrated).
    """
    sampled = failed.at.replace(second=0, microsecond=0)
    if draft.last_calibration is not None and draft.last_calibration >= sampled:
        return
    local = words.local(failed.at)
    decimals = _decimals(max(abs(failed.reference), abs(failed.sensor_value)))

    def amount(value: float) -> str:
        figure = f"{value:.{decimals}f}"
        return figure if failed.unit is None else f"{figure} {failed.unit}"

    direction = "high" if failed.deviation > 0 else "low"
    record = "" if failed.record is None else f" (record {failed.record})"
    draft.add(
        CareState.DUE,
        f"the grab sample of {local:%Y-%m-%d %H:%M %Z} read {amount(failed.reference)}, the "
        f"sensor {amount(failed.sensor_value)}: {amount(abs(failed.deviation))} {direction}, "
        f"more than the {amount(failed.limit)} {failed.rule} allows{record}: "
        f"{_AFTER_A_FAILED_SAMPLE[rules.kind]}",
    )


def _decimals(size: float) -> int:
    """The decimals a grab-sample kit reads to at this size: 0.50 mg/L, 95.0 %, 150 µg/L.

    Every figure of one sample is shown with the same, so they line up as the operator
    wrote them down.
    """
    if size < 10:  # noqa: PLR2004
        return 2
    if size < 100:  # noqa: PLR2004
        return 1
    return 0


# --- tecLine and Reiss -------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class _Calibration:
    index: int | None  # history entry; None: the active calibration
    x_zero: float
    x_span: float
    stamp: datetime | None  # aware

    def as_dict(self) -> dict[str, Any]:
        data: dict[str, Any] = {} if self.index is None else {"entry": self.index}
        return data | {
            "x_zero": self.x_zero,
            "x_span": self.x_span,
            "stamp": None if self.stamp is None else self.stamp.isoformat(timespec="minutes"),
        }


def _amperometric(
    records: Records,
    rules: CareRules,
    draft: _Draft,
    *,
    now: datetime,
    words: _Words,
    past: Sequence[Calibration],
) -> None:
    current = ("x_zero", "x_span", "calibration_stamp")
    ring = rules.ring
    if ring is None:
        draft.add(CareState.UNKNOWN, "its profile declares no calibration history")
        return
    entries, stamps = ring.points("x_zero", "x_span"), ring.points("stamp")
    if _missing(records, (*current, *entries, *stamps), draft, "The calibration records"):
        return

    def calibration(index: int | None) -> _Calibration:
        names = current if index is None else [ring.point(index, f) for f in HISTORY_FIELDS]
        zero, span, stamp = (
            records.number(names[0]),
            records.number(names[1]),
            records.date(names[2]),
        )
        return _Calibration(
            index=index,
            x_zero=math.nan if zero is None else zero,
            x_span=math.nan if span is None else span,
            stamp=None if stamp is None else words.stamp(stamp),
        )

    active = calibration(None)
    history = [calibration(i) for i in ring.numbers]
    draft.records = {
        "active": active.as_dict(),
        "history": [entry.as_dict() for entry in history],
        "nominal_slope": records.number("nominal_slope"),
        "unit": records.label("unit"),
    }
    if active.stamp is None:
        draft.add(
            CareState.DUE,
            "never calibrated: the calibration stamp is 0 (sensors leave the factory "
            "uncalibrated, tecLine annex 7.5.1): calibrate its slope",
        )
        return
    if not _history_consistent(active, history, draft, now=now):
        return
    draft.last_calibration = active.stamp
    earlier = _older_than_the_ring(history, past, words)
    ratios = _slope(records, rules, draft, [*history, *earlier])
    _due(draft, rules, active.stamp, now=now, words=words, what="check the calibration")
    if ratios:
        _slope_trend(rules, draft, ratios, now=now, words=words)


def _history_consistent(
    active: _Calibration,
    history: Sequence[_Calibration],
    draft: _Draft,
    *,
    now: datetime,
) -> bool:
    """The history as annex 7.2 keeps it: entry 0 the active one, newest first, none ahead."""
    assert active.stamp is not None  # noqa: S101 - checked by the caller
    if active.stamp > now + FUTURE_TOLERANCE:
        draft.add(
            CareState.UNKNOWN,
            f"the last calibration is stamped {active.stamp:%Y-%m-%d %H:%M}, in the future: "
            "the clock of whoever calibrated it was wrong; check it and calibrate again "
            "(an earlier stamp overwrites history entry 0, tecLine annex 7.2)",
        )
        return False
    newest = history[0]
    if newest.stamp != active.stamp:
        draft.add(
            CareState.UNKNOWN,
            "the date stamp of the active calibration (0x020A) is not that of history entry "
            "0, as the sensor keeps them (tecLine annex 7.2); calibrate again",
        )
        return False
    same = math.isclose(newest.x_span, active.x_span, rel_tol=_SAME) and math.isclose(
        newest.x_zero, active.x_zero, rel_tol=_SAME, abs_tol=1e-6
    )
    if not same:
        # X_Zero/X_Span written, the date stamp not yet: annex 7.2 activates a calibration
        # only when its stamp is written, so history entry 0 is still the one in force.
        draft.add(
            CareState.OK,
            "a new X_Zero/X_Span is written but not active: write its date stamp (0x020A) "
            "to activate it (tecLine annex 7.2)",
        )
    filled = [entry for entry in history if entry.stamp is not None]
    if [entry.index for entry in filled] != list(range(len(filled))):
        draft.add(
            CareState.UNKNOWN, "the calibration history has an empty entry between filled ones"
        )
        return False
    for newer, older in pairwise(filled):
        assert newer.stamp is not None  # noqa: S101 - filled
        assert older.stamp is not None  # noqa: S101 - filled
        if older.stamp >= newer.stamp:
            draft.add(
                CareState.UNKNOWN,
                f"the calibration history is out of order: entry {older.index} "
                f"({older.stamp:%Y-%m-%d %H:%M}) is not older than entry {newer.index} "
                f"({newer.stamp:%Y-%m-%d %H:%M}); a calibration was stamped with a wrong "
                "clock (tecLine annex 7.2)",
            )
            return False
    bad = [e for e in filled if not (math.isfinite(e.x_span) and e.x_span > 0)]
    if bad:
        draft.add(
            CareState.UNKNOWN,
            f"history entry {bad[0].index} has a slope of {bad[0].x_span:g}, which no "
            "calibration can have",
        )
        return False
    return True


def _older_than_the_ring(
    history: Sequence[_Calibration], past: Sequence[Calibration], words: _Words
) -> list[_Calibration]:
    """Of the copied calibrations, those older than any the sensor holds, newest first.

    Within the span of its ring the sensor's own entries stand (an entry 0 overwritten by
    a calibration stamped no later is gone from the sensor, and from the trend); the copy
    only lengthens it back in time, beyond what the ring holds.
    """
    stamps = [entry.stamp for entry in history if entry.stamp is not None]
    if not stamps:
        return []
    oldest = min(stamps)
    earlier = {
        stamp: _Calibration(index=None, x_zero=entry.x_zero, x_span=entry.x_span, stamp=stamp)
        for entry in past
        if (stamp := words.stamp(entry.stamp)) < oldest
    }
    return [earlier[stamp] for stamp in sorted(earlier, reverse=True)]


def _slope(
    records: Records,
    rules: CareRules,
    draft: _Draft,
    history: Sequence[_Calibration],
) -> list[tuple[datetime, float]]:
    """The active slope against the nominal one; the history's ratios, oldest first.

    ``history`` newest first: the sensor's entries, then any copied before it overwrote
    them (whose ratios the trend fits; the sensor's own are shown).
    """
    if _missing(records, ("nominal_slope", "unit"), draft, "The nominal slope and unit"):
        return []
    facts, limit = rules.slope, rules.slope_limit
    if facts is None or limit is None:
        draft.add(CareState.UNKNOWN, "its profile gives no slope limit or units to judge by")
        return []
    nominal = records.number("nominal_slope")
    unit = records.label("unit") or ""
    if nominal is None or nominal <= 0:
        draft.add(CareState.UNKNOWN, f"the nominal slope (0x030A) reads {nominal}: not usable")
        return []
    nominal_in_unit = facts.nominal_in(nominal, unit)
    if nominal_in_unit is None:
        draft.add(
            CareState.UNKNOWN,
            f"the concentration unit {unit!r} (0x0200) has no known relation to ppm, so the "
            "slope cannot be compared with the nominal slope (nA/ppm)",
        )
        return []
    ratios = [
        (entry.stamp, entry.x_span / nominal_in_unit)
        for entry in reversed(history)
        if entry.stamp is not None
    ]
    ratio = ratios[-1][1]
    draft.slope_ratio = ratio
    draft.figures["nominal_slope_in_unit"] = nominal_in_unit
    if ratio < limit:
        draft.add(
            CareState.MAINTENANCE,
            f"slope {ratio:.0%} of nominal, below {limit:.0%}: service the sensor "
            "(membrane cap and electrolyte, as its operating manual says; tecLine annex "
            "7.3.4), then calibrate",
        )
    else:
        draft.add(CareState.OK, f"slope {ratio:.0%} of nominal")
    return ratios


def _slope_trend(
    rules: CareRules,
    draft: _Draft,
    ratios: Sequence[tuple[datetime, float]],
    *,
    now: datetime,
    words: _Words,
) -> None:
    """The trend since the last service, and when it crosses the limit."""
    start = 0
    for i in range(1, len(ratios)):
        if ratios[i][1] - ratios[i - 1][1] > SERVICE_RISE:
            start = i
    run = ratios[start:]
    fitted = fit(run)
    if fitted is None:
        since = f" since the service of {words.day(run[0][0])}" if start else ""
        draft.projection_note = (
            f"no projection: {len(run)} calibration{'s' if len(run) != 1 else ''}{since}; "
            "at least 3 are needed"
        )
        return
    draft.slope_trend = fitted.trend()
    ratio, limit = ratios[-1][1], rules.slope_limit
    if limit is None:  # no ratios were made without one (_slope)
        return
    if ratio < limit:
        draft.projection_note = "no projection: the slope is already below the limit"
        return
    projection, note = project(fitted, limit=limit, newest=ratios[-1][0], min_r2=rules.min_fit_r2)
    draft.projection, draft.projection_note = projection, note
    if projection is None:
        return
    falling = -fitted.slope
    days = max(0, (projection.at - now).days)
    text = (
        f"slope falling {falling:.1%} of nominal a week: at this rate below "
        f"{limit:.0%} about {words.day(projection.at)} (in {_about(days)}, "
        f"{projection.confidence} confidence)"
    )
    if projection.at - now <= timedelta(days=rules.projection_warn_days):
        draft.add(CareState.DUE_SOON, f"{text}: plan membrane cap and electrolyte")
    else:
        draft.add(CareState.OK, text)


def _about(days: int) -> str:
    """A span of days as an operator says it."""
    if days < 14:  # noqa: PLR2004
        return f"{days} day{'s' if days != 1 else ''}"
    return f"about {round(days / 7)} weeks"


# --- O-DO H10/H20 ------------------------------------------------------------------------


def _optical_hygienic(
    records: Records,
    rules: CareRules,
    draft: _Draft,
    *,
    now: datetime,
    words: _Words,
    past: Sequence[LogbookEntry],
) -> None:
    _cap(records, rules, draft)
    _since_calibration(records, rules, draft)
    ring = rules.ring
    if ring is None:
        draft.add(CareState.UNKNOWN, "its profile declares no calibration logbook")
        return
    logbook = ring.points("entry_type", "date")
    if _missing(records, (*logbook, "operating_seconds"), draft, "The calibration logbook"):
        return
    entries = logbook_entries(records, ring)
    draft.records["logbook"] = [entry.as_dict() for entry in entries]
    if not entries:
        draft.add(CareState.DUE, "never calibrated: the calibration logbook is empty")
        return
    ordered = _logbook_order(records, entries, draft, now=now)
    if ordered is None:
        return
    newest = ordered[-1]
    assert newest.date is not None  # noqa: S101 - checked by _logbook_order
    draft.last_calibration = newest.date
    _due(draft, rules, newest.date, now=now, words=words)
    if newest.rating == "warning":
        draft.add(
            CareState.DUE,
            f"the sensor rated its last calibration ({words.day(newest.date)}) 'warning': "
            "calibrate again; if the warning stays, check the sensor cap",
        )
    # The copied entries older than any the logbook holds lengthen the cap's history.
    oldest = ordered[0]
    earlier = sorted(
        (e for e in past if e.date is not None and e.operating_s is not None),
        key=lambda e: (e.date, e.operating_s),
    )
    whole = [e for e in earlier if _before(e, oldest)] + ordered
    _cap_history(records, draft, whole)
    zero_points = [
        (e.date, e.phase)
        for e in whole
        if e.kind == ZERO_POINT_ENTRY
        and e.phase is not None
        and e.date is not None
        and e.cap_counter == newest.cap_counter
    ]
    drift = fit(zero_points)
    if drift is not None:
        draft.figures["zero_point_phase_drift_per_week"] = round(drift.slope, 6)
        draft.figures["zero_point_phase_drift_r2"] = round(drift.r2, 4)
        draft.figures["zero_point_phase_drift_points"] = drift.points


def _before(entry: LogbookEntry, oldest: LogbookEntry) -> bool:
    """Whether a copied entry is older than the oldest the logbook holds (dated ones only)."""
    assert entry.date is not None  # noqa: S101 - dated entries only
    assert oldest.date is not None  # noqa: S101 - ordered entries are dated
    return (entry.date, entry.operating_s or 0.0) < (oldest.date, oldest.operating_s or 0.0)


def _logbook_order(
    records: Records, entries: Sequence[LogbookEntry], draft: _Draft, *, now: datetime
) -> list[LogbookEntry] | None:
    """The entries oldest first, if dates and the operating-hours counter agree."""
    undated = [e.number for e in entries if e.date is None or e.operating_s is None]
    if undated:
        draft.add(CareState.UNKNOWN, f"logbook entry {undated[0]} has no date or operating time")
        return None
    ordered = sorted(entries, key=lambda e: (e.date, e.operating_s))
    ahead = [e for e in ordered if e.date is not None and e.date > now + FUTURE_TOLERANCE]
    if ahead:
        draft.add(
            CareState.UNKNOWN,
            f"logbook entry {ahead[0].number} is dated {ahead[0].date:%Y-%m-%d %H:%M %z}, in the "
            "future: the calibration date (0x300A) was set from a wrong clock",
        )
        return None
    for older, newer in pairwise(ordered):
        assert older.operating_s is not None  # noqa: S101 - dated entries only
        assert newer.operating_s is not None  # noqa: S101 - dated entries only
        if newer.operating_s < older.operating_s:
            draft.add(
                CareState.UNKNOWN,
                f"the logbook is out of order: entry {newer.number} is dated after entry "
                f"{older.number} but has fewer operating hours; a calibration date was set "
                "from a wrong clock",
            )
            return None
    operating = records.number("operating_seconds")
    if (
        operating is not None
        and ordered[-1].operating_s is not None
        and (ordered[-1].operating_s > operating)
    ):
        draft.add(
            CareState.UNKNOWN,
            f"logbook entry {ordered[-1].number} has more operating hours than the sensor has now",
        )
        return None
    return ordered


def _cap(records: Records, rules: CareRules, draft: _Draft) -> None:
    """Cap usage from the measurement counter (6.2.9), and the cap status bits."""
    counter = records.number("measurement_counter")
    maximum = records.number("measurement_counter_max")
    overflow = records.flag("error_register", "measurement_counter_overflow")
    exceeded = records.flag("status", "measurement_count_exceeded")
    draft.figures["measurement_counter"] = counter
    draft.figures["measurement_counter_max"] = maximum
    if counter is not None and maximum is not None and maximum > 0:
        usage = counter / maximum
        draft.cap_usage = usage
        if usage < 1 and not overflow and not exceeded:
            if usage >= rules.cap_usage_warn:
                draft.add(
                    CareState.DUE_SOON,
                    f"the cap has used {usage:.0%} of its {maximum:,.0f} measurements: "
                    "order a replacement cap",
                )
            else:
                draft.add(
                    CareState.OK,
                    f"cap {usage:.0%} used ({counter:,.0f} of {maximum:,.0f} measurements)",
                )
    if overflow or exceeded or (draft.cap_usage is not None and draft.cap_usage >= 1):
        draft.add(
            CareState.MAINTENANCE,
            "the measurement counter has reached its maximum (counter overflow, H10/H20 "
            "manual 6.2.9): replace the sensor cap and reset the counter (0x2093)",
        )
    if records.flag("status", "cap_missing"):
        draft.add(CareState.MAINTENANCE, "no sensor cap detected: fit a cap")
    for name in ("cap_serial_number", "cap_part_number"):
        if isinstance(value := records.values.get(name), str):
            draft.figures[name] = value


def _since_calibration(records: Records, rules: CareRules, draft: _Draft) -> None:
    """CIP/SIP cycles and hours outside the temperature range against their limits."""
    for name, limit, words in (
        ("cip_cycles_since_calibration", rules.cip_cycles_limit, "CIP cycles"),
        ("sip_cycles_since_calibration", rules.sip_cycles_limit, "SIP cycles"),
        (
            "hours_outside_operating_temperature",
            rules.hours_outside_temperature_limit,
            "hours outside the operating temperature",
        ),
    ):
        value = records.number(name)
        draft.figures[name] = value
        if value is not None and limit is not None and value >= limit:
            draft.add(
                CareState.DUE,
                f"{value:g} {words} since the last calibration (limit {limit:g}): calibrate",
            )


def _cap_history(records: Records, draft: _Draft, ordered: Sequence[LogbookEntry]) -> None:
    """Cap changes, and the operating time of this cap as far as the logbook shows it."""
    changes = records.number("sensor_replacement_counter")
    operating = records.number("operating_seconds")
    draft.figures["cap_changes"] = changes
    on_this_cap = [e for e in ordered if e.cap_counter == changes and e.operating_s is not None]
    if operating is not None and on_this_cap:
        first = on_this_cap[0].operating_s
        assert first is not None  # noqa: S101 - filtered above
        draft.figures["cap_operating_days_at_least"] = round((operating - first) / 86400, 1)


# --- O-DO S10 ------------------------------------------------------------------------------


def _optical(records: Records, draft: _Draft) -> None:
    if _missing(records, ("status",), draft, "The status word"):
        return
    operating = records.number("operating_seconds")
    draft.figures["operating_days"] = None if operating is None else round(operating / 86400, 1)
    commissioned = records.date("commissioning_date")
    draft.records["commissioning_date"] = (
        commissioned.astimezone(UTC).isoformat(timespec="seconds") if commissioned else None
    )
    if records.flag("status", "cap_missing"):
        draft.add(CareState.MAINTENANCE, "no sensor cap detected (S10 status bit 2): fit a cap")
    if records.flag("status", "cap_replacement_recommended"):
        draft.add(
            CareState.MAINTENANCE,
            "the sensor recommends replacing its cap (S10 status bit 10): replace the cap",
        )
    draft.add(
        CareState.OK,
        "the S10 keeps no calibration record that Modbus can read: calibrate it as its "
        "operating manual says",
    )
