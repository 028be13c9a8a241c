"""The verdict of sensor care for one device, from its records, its rules and the time.

Pure: the records come in as values (:class:`~gateway.care.records.Records`), the time as
an argument. Each rule adds a :class:`~gateway.care.report.Finding` with the state it
calls for, in words a plant operator uses; the most urgent finding is the device's
state. A record that is missing, unreadable or inconsistent gives a named ``unknown``,
never a made-up date.

Grab-sample verifications (:class:`~gateway.care.verifications.Verification`) count with
the sensor's own records: a passed one is the check the tecLine manual asks for weekly
(annex 7.3.4), so the due date runs from it as from a calibration; a failed one, with no
calibration since, calls for one.

The rules of each family have a module of their own: the amperometric cells' in
:mod:`~gateway.care.amperometric`, the optical sensors' in :mod:`~gateway.care.optical`;
what they share (the draft of the findings, the dates in an operator's words, the due
date) in :mod:`~gateway.care.draft`.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Final

from gateway.care.amperometric import assess_amperometric
from gateway.care.draft import Draft, Words
from gateway.care.optical import assess_optical, assess_optical_hygienic
from gateway.care.records import Calibration, LogbookEntry
from gateway.care.report import CareReport, CareState
from gateway.care.rules import CareKind
from gateway.care.verifications import later

if TYPE_CHECKING:
    from collections.abc import Sequence
    from datetime import datetime, tzinfo

    from gateway.care.records import Records, SensorEntry
    from gateway.care.rules import CareRules
    from gateway.care.verifications import Verification


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
    draft = Draft(passed=last_passed)
    words = Words(zone)
    if rules.kind is CareKind.AMPEROMETRIC:
        earlier = [e for e in past if isinstance(e, Calibration)]
        assess_amperometric(records, rules, draft, now=now, words=words, past=earlier)
    elif rules.kind is CareKind.OPTICAL_HYGIENIC:
        earlier_entries = [e for e in past if isinstance(e, LogbookEntry)]
        assess_optical_hygienic(records, rules, draft, now=now, words=words, past=earlier_entries)
    else:
        assess_optical(records, draft)
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


def _failed_sample(draft: Draft, rules: CareRules, failed: Verification, *, words: Words) -> None:
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
