"""Care of the optical oxygen sensors: the H10/H20's logbook and cap, the S10's status.

The H10/H20 (optical, hygienic) keep a calibration logbook and count their cap's use: the
due date runs from the newest calibration, the zero point's drift is fitted over the
logbook, and the cap's wear and history come from its counters (H10/H20 6.1.6). The S10
keeps no calibration that Modbus can read: only its status word speaks of its care.
"""

from __future__ import annotations

from datetime import UTC, datetime
from itertools import pairwise
from typing import TYPE_CHECKING, Final

from gateway.care.draft import FUTURE_TOLERANCE, Draft, Words, due_from, missing_records
from gateway.care.records import LogbookEntry, logbook_entries
from gateway.care.report import CareState
from gateway.care.trend import fit

if TYPE_CHECKING:
    from collections.abc import Sequence

    from gateway.care.records import Records
    from gateway.care.rules import CareRules

ZERO_POINT_ENTRY: Final = "zero_point"  # 6.1.6 entry type 20


def assess_optical_hygienic(
    records: Records,
    rules: CareRules,
    draft: Draft,
    *,
    now: datetime,
    words: Words,
    past: Sequence[LogbookEntry],
) -> None:
    """The H10/H20's care: the calibration logbook, the zero point's drift, the cap.

    ``past``: the logbook entries the gateway copied before the ring overwrote them.
    """
    _cap(records, rules, draft)
    _since_calibration(records, rules, draft)
    ring = rules.ring
    if ring is None:
        draft.add(CareState.UNKNOWN, "its profile declares no calibration logbook")
        return
    logbook = ring.points("entry_type", "date")
    if missing_records(records, (*logbook, "operating_seconds"), draft, "The calibration logbook"):
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
    due_from(draft, rules, newest.date, now=now, words=words)
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
    records: Records, entries: Sequence[LogbookEntry], draft: Draft, *, now: datetime
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


def _cap(records: Records, rules: CareRules, draft: Draft) -> None:
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


def _since_calibration(records: Records, rules: CareRules, draft: Draft) -> None:
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


def _cap_history(records: Records, draft: Draft, ordered: Sequence[LogbookEntry]) -> None:
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


def assess_optical(records: Records, draft: Draft) -> None:
    """The S10's care: its status word only (it keeps no calibration Modbus can read)."""
    if missing_records(records, ("status",), draft, "The status word"):
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
