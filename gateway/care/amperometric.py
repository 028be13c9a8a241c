"""Care of the amperometric cells (tecLine, Reiss): the calibration, its history, the slope.

The active calibration and the sensor's ring of earlier ones (the profile's history
layout), checked against each other; the slope against its nominal value and the limit
of the rules; its trend over the calibrations since the last service, projected to the
limit (tecLine annex 7.5).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from datetime import datetime, timedelta
from itertools import pairwise
from typing import TYPE_CHECKING, Any, Final

from gateway.care.draft import FUTURE_TOLERANCE, Draft, Words, due_from, missing_records
from gateway.care.records import HISTORY_FIELDS, Calibration
from gateway.care.report import CareState
from gateway.care.trend import fit, project

if TYPE_CHECKING:
    from collections.abc import Sequence

    from gateway.care.records import Records
    from gateway.care.rules import CareRules

# A rise of the slope ratio by more than this between two calibrations is a service (new
# membrane cap and electrolyte) or the nominal slope restored (annex 7.5): the trend is
# fitted over the calibrations since the last one. Ours; the manuals name none.
SERVICE_RISE: Final = 0.10
# Calibrations that agree to this relative difference are the same (float32 read back).
_SAME: Final = 1e-4


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


def assess_amperometric(
    records: Records,
    rules: CareRules,
    draft: Draft,
    *,
    now: datetime,
    words: Words,
    past: Sequence[Calibration],
) -> None:
    """The tecLine's and the Reiss's care: the calibration records, their history, the slope.

    ``past``: the calibrations the gateway copied before the sensor's ring overwrote them.
    """
    current = ("x_zero", "x_span", "calibration_stamp")
    ring = rules.ring
    if ring is None:
        draft.add(CareState.UNKNOWN, "its profile declares no calibration history")
        return
    entries, stamps = ring.points("x_zero", "x_span"), ring.points("stamp")
    if missing_records(records, (*current, *entries, *stamps), draft, "The calibration records"):
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
    due_from(draft, rules, active.stamp, now=now, words=words, what="check the calibration")
    if ratios:
        _slope_trend(rules, draft, ratios, now=now, words=words)


def _history_consistent(
    active: _Calibration,
    history: Sequence[_Calibration],
    draft: Draft,
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
    history: Sequence[_Calibration], past: Sequence[Calibration], words: Words
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
    draft: Draft,
    history: Sequence[_Calibration],
) -> list[tuple[datetime, float]]:
    """The active slope against the nominal one; the history's ratios, oldest first.

    ``history`` newest first: the sensor's entries, then any copied before it overwrote
    them (whose ratios the trend fits; the sensor's own are shown).
    """
    if missing_records(records, ("nominal_slope", "unit"), draft, "The nominal slope and unit"):
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
    draft: Draft,
    ratios: Sequence[tuple[datetime, float]],
    *,
    now: datetime,
    words: Words,
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
