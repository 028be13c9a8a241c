"""Grab-sample verifications in sensor care, without I/O: the due date, the failure, the book.

A passed verification is the check tecLine annex 7.3.4 asks for weekly (the measured value
against a reference sample), so the due date runs from it as from a calibration; a failed
one (EPA Method 334.0: more than the larger of 0.1 mg/L and 15 % of the DPD reference off)
with no calibration since makes the device ``due``. The records are those of
``test_care``: a tecLine's history, an H10's logbook, an S10's status word.
"""

from __future__ import annotations

from dataclasses import replace
from datetime import UTC, datetime, timedelta
from typing import TYPE_CHECKING

import pytest

from gateway.care import (
    CareBook,
    CareState,
    Records,
    Verification,
    assess,
    care_points,
    resolve,
)
from gateway.care.rules import CareKind
from gateway.wire import codec
from gateway.wire.codec import BitfieldValue
from tests.care.test_care import (
    H10,
    NOW,
    S10,
    TECLINE,
    _samples,
    history,
    logbook,
    weekly_zero_points,
)

if TYPE_CHECKING:
    from gateway.care import CareReport

# What the care document held before verifications: every one of these stays as it was.
DOCUMENT_KEYS = {
    "device",
    "bus",
    "profile",
    "state",
    "reasons",
    "last_calibration",
    "due",
    "interval_days",
    "interval_source",
    "slope_ratio",
    "slope_limit",
    "slope_trend",
    "projection",
    "projection_note",
    "cap_usage",
    "figures",
    "records",
    "assessed_at",
}


def grab(
    at: datetime,
    *,
    reference: float = 0.50,
    sensor: float = 0.52,
    limit: float = 0.10,
    unit: str | None = "mg/L",
    record: int | None = None,
) -> Verification:
    """A DPD grab sample against the sensor, judged as EPA 334.0 would with ``limit``."""
    deviation = sensor - reference
    return Verification(
        at=at,
        passed=abs(deviation) <= limit,
        reference=reference,
        sensor_value=sensor,
        deviation=deviation,
        limit=limit,
        unit=unit,
        rule="EPA 334.0",
        record=record,
    )


def tecline(
    calibrated: datetime,
    *,
    latest: Verification | None = None,
    passed: Verification | None = None,
) -> CareReport:
    """A tecLine calibrated once at ``calibrated`` (slope 90 % of nominal), assessed at NOW."""
    rules = resolve(TECLINE, [])
    assert rules is not None
    return assess(
        Records(values=history([0.9], calibrated)),
        rules,
        device="pool",
        bus="b",
        profile=TECLINE.id,
        now=NOW,
        zone=UTC,
        last_verification=latest,
        last_passed=passed,
    )


def texts(report: CareReport) -> str:
    return " | ".join(report.reasons)


def grab_sample_findings(report: CareReport) -> list[str]:
    return [f.text for f in report.findings if f.text.startswith("the grab sample")]


# --- the due date ----------------------------------------------------------------------------


def test_a_passed_verification_later_than_the_calibration_moves_the_due_date() -> None:
    """Calibrated 9 days ago (weekly: 2 days overdue), a grab sample passed 2 days ago: the
    weekly check was done then, so it is next due in 5 days."""
    calibrated = NOW - timedelta(days=9)
    assert tecline(calibrated).state is CareState.DUE
    sample = grab(NOW - timedelta(days=2))
    report = tecline(calibrated, latest=sample, passed=sample)
    assert report.due == sample.at + timedelta(days=7)
    assert report.state is CareState.OK
    assert report.last_calibration == calibrated  # a verification is not a calibration
    assert "check the calibration by Wed 2 Dec 2026" in texts(report)
    assert "grab sample passed Wed 25 Nov 2026, calibrated Wed 18 Nov 2026, weekly" in texts(report)


def test_a_passed_verification_earlier_than_the_calibration_changes_nothing() -> None:
    calibrated = NOW - timedelta(days=3)
    sample = grab(NOW - timedelta(days=5))
    report = tecline(calibrated, latest=sample, passed=sample)
    alone = tecline(calibrated)
    assert report.due == alone.due == calibrated + timedelta(days=7)
    assert report.findings == alone.findings
    assert report.last_verification == sample


def test_a_passed_verification_moves_an_h10_due_date_by_its_own_interval() -> None:
    """Every family with a calibration interval: the H10's 30 days (gateway default)."""
    rules = resolve(H10, [])
    assert rules is not None
    values = logbook(weekly_zero_points([60.0]))  # calibrated 3 days ago
    sample = grab(NOW - timedelta(days=1), reference=8.0, sensor=8.1, limit=0.5, unit="mg/L")
    report = assess(
        Records(values=values),
        rules,
        device="dig",
        bus="b",
        profile=H10.id,
        now=NOW,
        zone=UTC,
        last_verification=sample,
        last_passed=sample,
    )
    assert report.due == sample.at + timedelta(days=30)
    assert report.last_calibration == NOW - timedelta(days=3)
    assert report.state is CareState.OK


def test_a_passed_verification_does_not_pass_a_sensor_never_calibrated() -> None:
    """Sensors leave the factory uncalibrated (annex 7.5.1): a grab sample is no calibration."""
    rules = resolve(TECLINE, [])
    assert rules is not None
    sample = grab(NOW - timedelta(days=1))
    values = history([], NOW) | {"x_zero": 0.0, "x_span": 0.0, "calibration_stamp": None}
    report = assess(
        Records(values=values),
        rules,
        device="pool",
        bus="b",
        profile=TECLINE.id,
        now=NOW,
        zone=UTC,
        last_verification=sample,
        last_passed=sample,
    )
    assert report.state is CareState.DUE
    assert report.due is None
    assert "never calibrated" in texts(report)


# --- a failed verification -------------------------------------------------------------------


def test_a_failed_verification_makes_the_sensor_due_with_its_deviation() -> None:
    """0.50 mg/L by DPD, 0.75 on the sensor: 0.25 off, more than EPA 334.0's 0.10."""
    calibrated = NOW - timedelta(days=3)
    failed = grab(datetime(2026, 11, 27, 8, 10, 30, tzinfo=UTC), sensor=0.75, record=42)
    assert not failed.passed
    report = tecline(calibrated, latest=failed)
    assert report.state is CareState.DUE
    assert report.due == calibrated + timedelta(days=7)  # the interval still runs
    assert grab_sample_findings(report) == [
        (
            "the grab sample of 2026-11-27 08:10 UTC read 0.50 mg/L, the sensor 0.75 mg/L: "
            "0.25 mg/L high, more than the 0.10 mg/L EPA 334.0 allows (record 42): calibrate "
            "(tecLine annex 7.3.4)"
        )
    ]
    assert report.reasons[0] == grab_sample_findings(report)[0]  # the most urgent first


def test_a_failed_verification_after_a_passed_one_is_the_one_that_counts() -> None:
    calibrated = NOW - timedelta(days=6)
    passed = grab(NOW - timedelta(days=2))
    failed = grab(NOW - timedelta(days=1), reference=2.00, sensor=1.60, limit=0.30)
    report = tecline(calibrated, latest=failed, passed=passed)
    assert report.state is CareState.DUE
    assert report.due == passed.at + timedelta(days=7)
    assert "0.40 mg/L low, more than the 0.30 mg/L EPA 334.0 allows" in texts(report)
    assert report.last_verification == failed


def test_a_grab_sample_that_passes_after_a_failed_one_clears_it() -> None:
    """The second sample (a mistaken first one, the DPD kit repeated) passes: ok again."""
    calibrated = NOW - timedelta(days=6)
    failed = grab(NOW - timedelta(hours=3), sensor=0.75)
    again = grab(NOW - timedelta(hours=2))
    report = tecline(calibrated, latest=failed, passed=again)  # the newer of the two counts
    assert report.state is CareState.OK
    assert report.last_verification == again
    assert grab_sample_findings(report) == []


def test_a_calibration_after_a_failed_verification_clears_it() -> None:
    failed = grab(NOW - timedelta(days=2), sensor=0.75)
    report = tecline(NOW - timedelta(days=1), latest=failed)
    assert report.state is CareState.OK
    assert grab_sample_findings(report) == []
    assert report.last_verification == failed  # still shown, no longer judged
    assert report.due == NOW - timedelta(days=1) + timedelta(days=7)


def test_a_calibration_stamped_in_the_minute_of_the_sample_counts_as_after_it() -> None:
    """Stamps carry minutes (YYMMDDHHMM): a sample at 08:10:40 and a calibration stamped
    08:10 are sample, then calibration; a calibration stamped 08:09 was before it."""
    failed = grab(datetime(2026, 11, 27, 8, 10, 40, tzinfo=UTC), sensor=0.75)
    after = tecline(datetime(2026, 11, 27, 8, 10, tzinfo=UTC), latest=failed)
    assert after.state is CareState.OK
    before = tecline(datetime(2026, 11, 27, 8, 9, tzinfo=UTC), latest=failed)
    assert before.state is CareState.DUE


def test_a_failed_verification_of_an_h10_calls_for_a_calibration() -> None:
    rules = resolve(H10, [])
    assert rules is not None
    failed = grab(NOW - timedelta(days=1), reference=8.0, sensor=7.2, limit=0.5)
    report = assess(
        Records(values=logbook(weekly_zero_points([60.0]))),
        rules,
        device="dig",
        bus="b",
        profile=H10.id,
        now=NOW,
        zone=UTC,
        last_verification=failed,
    )
    assert report.state is CareState.DUE
    assert grab_sample_findings(report) == [
        (
            "the grab sample of 2026-11-26 12:00 UTC read 8.00 mg/L, the sensor 7.20 mg/L: "
            "0.80 mg/L low, more than the 0.50 mg/L EPA 334.0 allows: calibrate"
        )
    ]


def test_a_failed_verification_of_an_s10_asks_for_another_grab_sample() -> None:
    """The S10 keeps no calibration Modbus can read: only a passed sample clears it."""
    rules = resolve(S10, [])
    assert rules is not None
    flags = (("cap_missing", False), ("cap_replacement_recommended", False))
    values: dict[str, codec.Decoded] = {
        "operating_seconds": 864_000,
        "status": BitfieldValue(raw=0, flags=flags),
    }
    failed = grab(NOW - timedelta(days=1), reference=95.0, sensor=88.0, limit=5.0, unit=None)
    report = assess(
        Records(values=values),
        rules,
        device="s",
        bus="b",
        profile=S10.id,
        now=NOW,
        zone=UTC,
        last_verification=failed,
    )
    assert report.state is CareState.DUE
    assert report.due is None  # no interval: a passed sample moves nothing
    (text,) = grab_sample_findings(report)
    assert "read 95.0, the sensor 88.0: 7.0 low, more than the 5.0 EPA 334.0 allows" in text
    assert "then take another grab sample" in text


# --- the care document -----------------------------------------------------------------------


def test_the_report_carries_the_last_verification_and_keeps_every_field() -> None:
    failed = grab(datetime(2026, 11, 27, 8, 10, 30, tzinfo=UTC), sensor=0.75, record=42)
    report = tecline(NOW - timedelta(days=3), latest=failed)
    document = report.as_dict()
    assert set(document) == DOCUMENT_KEYS | {"last_verification"}
    assert document["last_verification"] == {
        "at": "2026-11-27T08:10:30+00:00",
        "passed": False,
        "reference": 0.5,
        "sensor_value": 0.75,
        "deviation": 0.25,
        "limit": 0.1,
        "unit": "mg/L",
        "rule": "EPA 334.0",
        "record": 42,
    }
    none = tecline(NOW - timedelta(days=3)).as_dict()
    assert none["last_verification"] is None
    assert {k: v for k, v in document.items() if k not in {"state", "reasons"}} | {
        "last_verification": None
    } == {k: v for k, v in none.items() if k not in {"state", "reasons"}}


def test_a_new_verification_changes_the_report_key() -> None:
    """Publishers send a new care document when the key changes."""
    calibrated = NOW - timedelta(days=3)
    first = grab(NOW - timedelta(days=5))  # before the calibration: judged the same
    assert tecline(calibrated).key != tecline(calibrated, latest=first, passed=first).key


def test_a_verification_needs_an_aware_time() -> None:
    with pytest.raises(ValueError, match="zone"):
        grab(datetime(2026, 11, 27, 8, 10))  # the mistake under test


# --- the book --------------------------------------------------------------------------------


def _book() -> CareBook:
    book = CareBook(clock=lambda: NOW, zone=UTC)
    rules = resolve(TECLINE, [])
    points = care_points(TECLINE, CareKind.AMPEROMETRIC)
    book.add_device(bus="b", device="pool", profile=TECLINE, rules=rules, polled=points)
    return book


def test_the_book_assesses_again_on_a_verification_and_bumps_the_version() -> None:
    book = _book()
    book.observe(_samples(history([0.9], NOW - timedelta(days=9)), at=0.0))
    overdue = book.report("pool")
    assert overdue is not None
    assert overdue.state is CareState.DUE
    assert book.version("pool") == 1
    passed = grab(NOW - timedelta(days=1))
    book.verified("pool", passed)
    checked = book.report("pool")
    assert checked is not None
    assert checked.state is CareState.OK
    assert checked.due == passed.at + timedelta(days=7)
    assert book.version("pool") == 2
    book.verified("pool", passed)  # the same once more (a record read again): no change
    assert book.version("pool") == 2
    failed = grab(NOW - timedelta(hours=1), sensor=0.75)
    book.verified("pool", failed)
    due = book.report("pool")
    assert due is not None
    assert due.state is CareState.DUE
    assert due.last_verification == failed
    assert due.due == passed.at + timedelta(days=7)  # the passed one is kept apart
    assert book.version("pool") == 3


def test_the_book_keeps_the_sample_taken_last_whatever_the_order_at_start() -> None:
    """At start the records hand over every verification; a late entry is an older sample."""
    book = CareBook(clock=lambda: NOW, zone=UTC)
    older_failed = grab(NOW - timedelta(days=4), sensor=0.75)
    newer_passed = grab(NOW - timedelta(days=2))
    book.verified("pool", newer_passed)  # before the device is even added
    book.verified("pool", older_failed)
    rules = resolve(TECLINE, [])
    points = care_points(TECLINE, CareKind.AMPEROMETRIC)
    book.add_device(bus="b", device="pool", profile=TECLINE, rules=rules, polled=points)
    assert book.report("pool") is None  # nothing assessed before the records are read
    book.observe(_samples(history([0.9], NOW - timedelta(days=9)), at=0.0))
    report = book.report("pool")
    assert report is not None
    assert report.last_verification == newer_passed
    assert report.state is CareState.OK
    # A reload adds the device afresh; its verifications stay.
    book.add_device(bus="b", device="pool", profile=TECLINE, rules=rules, polled=points)
    book.observe(_samples(history([0.9], NOW - timedelta(days=9)), at=1.0))
    again = book.report("pool")
    assert again is not None
    assert again.last_verification == newer_passed


def test_a_verification_of_a_device_care_does_not_follow_is_kept_quietly() -> None:
    book = _book()
    book.verified("elsewhere", replace(grab(NOW), record=7))
    assert book.report("elsewhere") is None
    assert book.version("elsewhere") == 0
