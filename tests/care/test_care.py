"""Sensor care's rules, without I/O: records as the sensors hold them, verdicts by hand.

The tecLine figures follow annex 7 of jumo-tecline.modbus.en.txt: a nominal slope of
22 nA/ppm (7.5.1's free-chlorine example), X_Span in nA per unit of 0x0200, the 30 % limit
of 7.3.4, the history newest first (7.2). The H10/H20 logbook follows 6.1.6 and the
counter 6.2.9 of jumo-digiline-odo-h10-h20.modbus.de.txt; the S10 bits its status word.
"""

from __future__ import annotations

import statistics
from datetime import UTC, datetime, timedelta
from typing import TYPE_CHECKING, Any

import pytest

from gateway.care import (
    CareBook,
    CareState,
    Records,
    assess,
    care_order,
    care_points,
    resolve,
)
from gateway.care.rules import CareKind, rules_for
from gateway.config import check_config, parse_config
from gateway.config.care import CareSettings
from gateway.line.samples import Quality, Sample
from gateway.profiles import get_profile
from gateway.wire import codec
from gateway.wire.codec import BitfieldValue, EnumValue

if TYPE_CHECKING:
    from pathlib import Path

    from gateway.care import CareReport

NOW = datetime(2026, 11, 27, 12, 0, tzinfo=UTC)
NOMINAL = 22.0  # nA/ppm, tecLine annex 7.5.1
PPM = EnumValue(code=3, label="ppm")
PPB = EnumValue(code=5, label="ppb")
TECLINE = get_profile("jumo-tecline-cl2")
H10 = get_profile("jumo-digiline-odo-h10")
S10 = get_profile("jumo-digiline-odo-s10")


def history(
    ratios: list[float], newest: datetime, *, every: timedelta = timedelta(days=7)
) -> dict[str, Any]:
    """A tecLine's records: entry 0 newest (ratio[0]), one calibration ``every`` before it.

    Stamps are zone-less, as the codec decodes YYMMDDHHMM; entries past the list are 0
    (never set), as a sensor keeps them.
    """
    values: dict[str, Any] = {"nominal_slope": NOMINAL, "unit": PPM}
    for index in range(5):
        if index < len(ratios):
            stamp: datetime | None = (newest - index * every).replace(tzinfo=None)
            span = ratios[index] * NOMINAL
        else:
            stamp, span = None, 0.0
        values |= {
            f"history_{index}_x_zero": 0.0,
            f"history_{index}_x_span": span,
            f"history_{index}_stamp": stamp,
        }
    values |= {
        "x_zero": values["history_0_x_zero"],
        "x_span": values["history_0_x_span"],
        "calibration_stamp": values["history_0_stamp"],
    }
    return values


def tecline(values: dict[str, Any], *, now: datetime = NOW, **settings: Any) -> CareReport:
    rules = resolve(TECLINE, [("test", CareSettings(**settings))] if settings else [])
    assert rules is not None
    return assess(
        Records(values=values), rules, device="pool", bus="b", profile=TECLINE.id, now=now, zone=UTC
    )


def texts(report: CareReport) -> str:
    return " | ".join(report.reasons)


# --- tecLine / Reiss -------------------------------------------------------------------------


def test_a_weekly_falling_slope_is_projected_to_the_30_percent_limit() -> None:
    """0.80 ... 0.56 of 22 nA/ppm, a week apart: 6 % a week; from 0.56 the 0.26 left to 30 %
    take 0.26 / 0.06 = 4 1/3 weeks = 30 days 8 hours after the newest calibration."""
    newest = datetime(2026, 11, 18, 10, 0, tzinfo=UTC)
    report = tecline(history([0.56, 0.62, 0.68, 0.74, 0.80], newest))
    assert report.slope_ratio == pytest.approx(12.32 / 22.0)
    assert report.last_calibration == newest
    assert report.due == datetime(2026, 11, 25, 10, 0, tzinfo=UTC)  # weekly, annex 7.3.4
    assert report.state is CareState.DUE  # 2 days 2 hours overdue
    assert "overdue for 2 days" in texts(report)
    assert report.slope_trend is not None
    assert report.slope_trend.per_week == pytest.approx(-0.06)
    assert report.slope_trend.r2 == pytest.approx(1.0)
    assert report.slope_trend.points == 5
    assert report.projection is not None
    expected = datetime(2026, 12, 18, 18, 0, tzinfo=UTC)
    assert abs((report.projection.at - expected).total_seconds()) < 1
    assert report.projection.confidence == "high"
    assert report.projection.earliest == report.projection.at  # a perfect fit: no spread
    # 21 days away: told, but not yet a reason to act (projection_warn_days 14).
    assert CareState.DUE_SOON not in {f.state for f in report.findings}


def test_a_projection_within_two_weeks_calls_for_membrane_and_electrolyte() -> None:
    """0.44 falling 6 % a week: 30 % in 0.14 / 0.06 = 2 1/3 weeks = 16 1/3 days after the
    newest calibration, 9 days ago: 7 1/3 days from now, inside the 14-day warning."""
    newest = NOW - timedelta(days=9)
    report = tecline(history([0.44, 0.50, 0.56, 0.62, 0.68], newest))
    assert report.projection is not None
    left = report.projection.at - NOW
    assert left == pytest.approx(timedelta(days=7, hours=8), abs=timedelta(seconds=1))
    warning = [f for f in report.findings if f.state is CareState.DUE_SOON]
    assert len(warning) == 1
    assert "plan membrane cap and electrolyte" in warning[0].text
    assert "in 7 days" in warning[0].text
    assert report.state is CareState.DUE  # the calibration is overdue as well


def test_a_slope_below_30_percent_of_nominal_needs_maintenance() -> None:
    """Annex 7.3.4: below 30 % of 0x030A, follow the sensor's maintenance instructions."""
    report = tecline(history([0.29, 0.35, 0.41], NOW - timedelta(days=1)))
    assert report.state is CareState.MAINTENANCE
    assert report.slope_ratio == pytest.approx(0.29)
    assert "below 30%" in texts(report)
    assert report.projection is None
    assert report.projection_note == "no projection: the slope is already below the limit"


def test_the_slope_in_another_unit_is_compared_in_ppm() -> None:
    """X_Span in nA/ppb (0x0200 = 5): 0.01232 nA/ppb is 12.32 nA/ppm, 56 % of 22."""
    values = history([0.56], NOW - timedelta(days=1))
    values |= {"unit": PPB, "x_span": 0.01232, "history_0_x_span": 0.01232}
    report = tecline(values)
    assert report.slope_ratio == pytest.approx(0.56)
    assert report.state is CareState.OK


def test_no_projection_from_fewer_than_three_calibrations() -> None:
    report = tecline(history([0.50, 0.60], NOW - timedelta(days=1)))
    assert report.slope_trend is None
    assert report.projection is None
    assert report.projection_note == "no projection: 2 calibrations; at least 3 are needed"


def test_no_projection_from_scattered_calibrations_and_it_says_its_fit() -> None:
    """The fit's r² checked against the standard library's own correlation."""
    ratios = [0.66, 0.60, 0.68, 0.62, 0.70]  # newest first; no rise above 0.10
    report = tecline(history(ratios, NOW - timedelta(days=1)))
    weeks = [-4.0, -3.0, -2.0, -1.0, 0.0]
    r2 = statistics.correlation(weeks, list(reversed(ratios))) ** 2
    assert report.slope_trend is not None
    assert report.slope_trend.r2 == pytest.approx(r2)
    assert r2 < 0.8
    assert report.projection is None
    assert report.projection_note.startswith("no projection: the 5 calibrations do not lie")


def test_the_trend_starts_again_after_a_service() -> None:
    """A rise back to nominal (new membrane cap, or annex 7.5's nominal slope restored)
    starts a new run: the 0.40 and 0.46 before it are not in the fit."""
    report = tecline(history([0.88, 0.94, 1.00, 0.40, 0.46], NOW - timedelta(days=1)))
    assert report.slope_trend is not None
    assert report.slope_trend.points == 3
    assert report.slope_trend.per_week == pytest.approx(-0.06)


def test_a_sensor_never_calibrated_says_so() -> None:
    """Annex 7.5.1: delivered uncalibrated; the stamp reads 0 (decoded as no date)."""
    report = tecline(history([], NOW))
    assert report.state is CareState.DUE
    assert report.last_calibration is None
    assert report.due is None
    assert texts(report).startswith("never calibrated")


def test_a_stamp_in_the_future_is_unknown_not_a_date() -> None:
    """The annex's last representable stamp, 4212312359 = 2042-12-31 23:59, read back."""
    stamp = codec.decode(codec.Format(dtype=codec.DataType.YYMMDDHHMM, count=2), [0xFB12, 0xC927])
    assert stamp == datetime(2042, 12, 31, 23, 59)
    values = history([0.9], NOW) | {"calibration_stamp": stamp, "history_0_stamp": stamp}
    report = tecline(values)
    assert report.state is CareState.UNKNOWN
    assert report.due is None
    assert "in the future" in texts(report)


def test_a_history_out_of_order_is_unknown() -> None:
    """Annex 7.2: an earlier stamp overwrites entry 0 only, so entry 0 ends up older than
    entry 1: the clock of whoever calibrated was wrong, and the history says nothing sure."""
    values = history([0.7, 0.8, 0.9], NOW - timedelta(days=1))
    earlier = values["history_2_stamp"] - timedelta(days=1)
    values |= {"history_0_stamp": earlier, "calibration_stamp": earlier}
    report = tecline(values)
    assert report.state is CareState.UNKNOWN
    assert "out of order" in texts(report)


def test_a_calibration_written_but_not_stamped_is_not_yet_in_force() -> None:
    """Annex 7.2: X_Span written, the date stamp not yet: entry 0 is still the one in force."""
    values = history([0.7, 0.8, 0.9], NOW - timedelta(days=1)) | {"x_span": 0.5 * NOMINAL}
    report = tecline(values)
    assert report.state is CareState.OK
    assert report.slope_ratio == pytest.approx(0.7)
    assert "written but not active" in texts(report)


def test_an_active_stamp_that_is_not_history_entry_0_is_unknown() -> None:
    values = history([0.7, 0.8, 0.9], NOW - timedelta(days=1))
    values["calibration_stamp"] -= timedelta(minutes=1)
    report = tecline(values)
    assert report.state is CareState.UNKNOWN
    assert "not that of history entry 0" in texts(report)


def test_an_unreadable_record_is_named() -> None:
    rules = resolve(TECLINE, [])
    assert rules is not None
    values = history([0.7], NOW - timedelta(days=1))
    del values["history_3_stamp"]
    report = assess(
        Records(values=values, unreadable={"history_3_stamp": "the sensor sent undecodable"}),
        rules,
        device="pool",
        bus="b",
        profile=TECLINE.id,
        now=NOW,
        zone=UTC,
    )
    assert report.state is CareState.UNKNOWN
    assert "history_3_stamp (the sensor sent undecodable)" in texts(report)


@pytest.mark.parametrize(
    ("age_days", "state"),
    [
        (5.9, CareState.OK),
        (6.0, CareState.DUE_SOON),
        (6.99, CareState.DUE_SOON),
        (7.0, CareState.DUE),
    ],
)
def test_due_soon_and_due_from_the_weekly_interval(age_days: float, state: CareState) -> None:
    """Weekly (annex 7.3.4), due soon one day ahead (our default, README)."""
    report = tecline(history([0.9], NOW - timedelta(days=age_days)))
    assert report.state is state


def test_a_configured_interval_wins_and_says_where_it_comes_from() -> None:
    report = tecline(history([0.9], NOW - timedelta(days=5)), calibration_interval_days=3)
    assert report.state is CareState.DUE
    assert report.interval_days == 3
    assert report.interval_source == "configured: test"


# --- O-DO H10/H20 --------------------------------------------------------------------------


def logbook(
    entries: list[tuple[int, datetime, float, int, float]], **current: Any
) -> dict[str, Any]:
    """H10 records: entries (type 20/21, date, operating s, cap counter, phase), index 1 first."""
    labels = {20: "zero_point", 21: "end_value"}
    values: dict[str, Any] = {
        "operating_seconds": 10_000_000,
        "sensor_replacement_counter": 2,
        "measurement_counter": 100_000,
        "measurement_counter_max": 1_000_000,
        "cip_cycles_since_calibration": 3,
        "sip_cycles_since_calibration": 1,
        "hours_outside_operating_temperature": 0.0,
        "error_register": BitfieldValue(raw=0, flags=(("measurement_counter_overflow", False),)),
        "status": BitfieldValue(raw=0, flags=(("cap_missing", False),)),
    } | current
    for index in range(1, 11):
        prefix = f"logbook_{index}_"
        if index <= len(entries):
            kind, date, seconds, cap, phase = entries[index - 1]
            values |= {
                f"{prefix}entry_type": EnumValue(code=kind, label=labels[kind]),
                f"{prefix}manual_change": EnumValue(code=1, label="calibration"),
                f"{prefix}rating": EnumValue(code=1, label="ok"),
                f"{prefix}operating_seconds": seconds,
                f"{prefix}date": date,
                f"{prefix}sensor_replacement_counter": cap,
                f"{prefix}phase": phase,
            }
        else:
            values |= {
                f"{prefix}entry_type": EnumValue(code=0, label="none"),
                f"{prefix}date": None,
            }
    return values


def h10(values: dict[str, Any], **settings: Any) -> CareReport:
    rules = resolve(H10, [("test", CareSettings(**settings))] if settings else [])
    assert rules is not None
    return assess(
        Records(values=values), rules, device="dig", bus="b", profile=H10.id, now=NOW, zone=UTC
    )


WEEK = 7 * 86400


def weekly_zero_points(phases: list[float]) -> list[tuple[int, datetime, float, int, float]]:
    """Zero-point entries a week apart, newest first, the operating counter a week apart."""
    return [
        (20, NOW - timedelta(days=3 + 7 * i), 10_000_000 - 3 * 86400 - i * WEEK, 2, phase)
        for i, phase in enumerate(phases)
    ]


def test_an_h10_with_a_recent_logbook_is_ok_and_its_phase_drift_is_fitted() -> None:
    """Zero-point phases 60.15, 60.10, 60.05, 60.00 a week apart: 0.05 ° a week."""
    report = h10(logbook(weekly_zero_points([60.15, 60.10, 60.05, 60.00])))
    assert report.state is CareState.OK
    assert report.last_calibration == NOW - timedelta(days=3)
    assert report.due == NOW - timedelta(days=3) + timedelta(days=30)
    assert report.figures["zero_point_phase_drift_per_week"] == pytest.approx(0.05)
    assert report.cap_usage == pytest.approx(0.1)
    assert report.figures["cap_operating_days_at_least"] == pytest.approx(
        (3 * WEEK + 3 * 86400) / 86400, abs=0.05
    )


def test_an_h10_cap_near_its_measurement_maximum_is_due_soon_and_at_it_maintenance() -> None:
    """6.2.9: at 0x2095 the sensor sets "counter overflow" (0x2005 bit 7)."""
    entries = weekly_zero_points([60.0])
    assert h10(logbook(entries, measurement_counter=950_000)).state is CareState.DUE_SOON
    overflow = BitfieldValue(raw=0x80, flags=(("measurement_counter_overflow", True),))
    report = h10(logbook(entries, measurement_counter=1_000_000, error_register=overflow))
    assert report.state is CareState.MAINTENANCE
    assert report.cap_usage == pytest.approx(1.0)
    assert "replace the sensor cap" in texts(report)


def test_an_h10_warning_rating_and_cycle_limits_make_a_calibration_due() -> None:
    values = logbook(weekly_zero_points([60.0]), cip_cycles_since_calibration=12)
    values["logbook_1_rating"] = EnumValue(code=2, label="warning")
    report = h10(values, cip_cycles_limit=10)
    assert report.state is CareState.DUE
    assert "'warning'" in texts(report)
    assert "12 CIP cycles since the last calibration (limit 10)" in texts(report)
    assert h10(logbook(weekly_zero_points([60.0]), cip_cycles_since_calibration=12)).state is (
        CareState.OK  # no limit configured: shown, not judged
    )


def test_an_h10_logbook_whose_dates_and_operating_hours_disagree_is_unknown() -> None:
    entries = weekly_zero_points([60.0, 60.0])
    newest = entries[0]
    entries[0] = (newest[0], newest[1], entries[1][2] - 1, newest[3], newest[4])
    report = h10(logbook(entries))
    assert report.state is CareState.UNKNOWN
    assert "out of order" in texts(report)


def test_an_empty_logbook_says_never_calibrated() -> None:
    report = h10(logbook([]))
    assert report.state is CareState.DUE
    assert "the calibration logbook is empty" in texts(report)


# --- O-DO S10 --------------------------------------------------------------------------------


def s10(**bits: bool) -> CareReport:
    rules = resolve(S10, [])
    assert rules is not None
    flags = tuple(
        (name, bits.get(name, False)) for name in ("cap_missing", "cap_replacement_recommended")
    )
    values: dict[str, codec.Decoded] = {
        "operating_seconds": 864_000,
        "status": BitfieldValue(raw=0, flags=flags),
    }
    return assess(Records(values=values), rules, device="s", bus="b", profile=S10.id, now=NOW)


def test_an_s10_recommending_a_new_cap_needs_maintenance() -> None:
    assert s10().state is CareState.OK
    assert s10().due is None  # the S10 keeps no calibration record over Modbus
    report = s10(cap_replacement_recommended=True)
    assert report.state is CareState.MAINTENANCE
    assert "replacing its cap" in texts(report)
    assert s10(cap_missing=True).state is CareState.MAINTENANCE


# --- points, order, settings -------------------------------------------------------------


def test_care_reads_only_points_of_the_profile() -> None:
    names = care_points(TECLINE, CareKind.AMPEROMETRIC)
    assert {"x_span", "calibration_stamp", "nominal_slope", "history_4_stamp"} <= set(names)
    assert all(TECLINE.has_point(name) for name in names)
    assert {"logbook_10_date", "measurement_counter_max"} <= set(
        care_points(H10, CareKind.OPTICAL_HYGIENIC)
    )


def test_reports_are_ordered_by_urgency() -> None:
    ok = tecline(history([0.9], NOW - timedelta(days=1)))
    due = tecline(history([0.9], NOW - timedelta(days=8)))
    low = tecline(history([0.2], NOW - timedelta(days=1)))
    assert [r.state for r in care_order([ok, due, low])] == [
        CareState.MAINTENANCE,
        CareState.DUE,
        CareState.OK,
    ]


def test_the_narrowest_setting_wins() -> None:
    config = parse_config(
        "buses: [{name: b, port: /dev/null}]\n"
        "devices:\n"
        "  - {name: a, bus: b, address: 1, profile: jumo-tecline-cl2}\n"
        "  - {name: c, bus: b, address: 2, profile: reiss-m0c, care: {calibration_interval_days: 2}}\n"
        "  - {name: d, bus: b, address: 3, profile: jumo-digiline-odo-h10, care: {enabled: false}}\n"
        "care:\n"
        "  due_soon_days: 2\n"
        "  profiles: {reiss-m0c-m3c: {calibration_interval_days: 14}, jumo-tecline-cl2: {slope_limit: 0.4}}\n",
        environ={},
    )
    a, c, d = config.devices
    rules_a, rules_c = rules_for(config, a), rules_for(config, c)
    assert rules_a is not None
    assert rules_c is not None
    assert (rules_a.calibration_interval_days, rules_a.slope_limit, rules_a.due_soon_days) == (
        7.0,
        0.4,
        2,
    )
    assert rules_c.calibration_interval_days == 2
    assert rules_c.interval_source == "configured: devices.c.care"
    assert rules_for(config, d) is None


def test_check_config_names_an_unknown_care_key_and_its_line(tmp_path: Path) -> None:
    path = tmp_path / "plant.yaml"
    path.write_text(
        "buses: [{name: b, port: /dev/null}]\n"
        "devices:\n"
        "  - name: a\n"
        "    bus: b\n"
        "    address: 1\n"
        "    profile: jumo-tecline-cl2\n"
        "    care:\n"
        "      calibration_interval: 3\n"
        "care:\n"
        "  profiles:\n"
        "    jumo-tecline-cl3: {due_soon_days: 1}\n",
        encoding="utf-8",
    )
    problems = check_config(path, environ={})
    found = {(p.key, p.line) for p in problems}
    assert ("devices[0].care.calibration_interval", 8) in found
    assert ("care.profiles.jumo-tecline-cl3", 11) in found
    assert len(problems) == 2


def _samples(values: dict[str, Any], *, at: float) -> list[Sample]:
    return [
        Sample(
            bus="b",
            device="pool",
            profile=TECLINE.id,
            point=name,
            value=value,
            fault=None,
            unit=None,
            quality=Quality.GOOD,
            monotonic=at,
            time=NOW,
            group="diagnostics",
        )
        for name, value in values.items()
    ]


def test_the_book_assesses_on_a_change_and_once_a_minute_otherwise() -> None:
    """Status words come every poll: the same records are not assessed again within a minute,
    but a changed one at once, and time alone again after a minute (a calibration falls due)."""
    clock = [NOW]
    book = CareBook(clock=lambda: clock[0], zone=UTC)
    rules = resolve(TECLINE, [])
    points = care_points(TECLINE, CareKind.AMPEROMETRIC)
    book.add_device(bus="b", device="pool", profile=TECLINE, rules=rules, polled=points)
    values = history([0.9], NOW - timedelta(days=6, hours=23))
    values |= {"serial_number": "0104714601", "part_number": "00705172"}
    book.observe(_samples({k: v for k, v in values.items() if k != "unit"}, at=0.0))
    assert book.report("pool") is None  # the unit not read yet: no verdict
    book.observe(_samples(values, at=1.0))
    first = book.report("pool")
    assert first is not None
    assert first.state is CareState.DUE_SOON
    assert book.version("pool") == 1
    clock[0] = NOW + timedelta(hours=2)  # now overdue, but nothing changed
    book.observe(_samples(values, at=2.0))
    assert book.report("pool") is first
    book.observe(_samples(values, at=61.0))  # a minute on: time alone is assessed
    due = book.report("pool")
    assert due is not None
    assert due.state is CareState.DUE
    assert book.version("pool") == 2
    book.observe(_samples(values | {"nominal_slope": 2 * NOMINAL}, at=62.0))  # a change
    changed = book.report("pool")
    assert changed is not None
    assert changed.slope_ratio == pytest.approx(0.45)
    assert book.version("pool") == 3


def test_a_status_bit_care_does_not_judge_does_not_make_it_assess_again() -> None:
    """The S10's "oxygen invalid" changes nothing care judges; "cap replacement" does."""
    book = CareBook(clock=lambda: NOW)
    rules = resolve(S10, [])
    book.add_device(bus="b", device="pool", profile=S10, rules=rules, polled=["status"])

    def status(**bits: bool) -> BitfieldValue:
        names = ("oxygen_invalid", "cap_missing", "cap_replacement_recommended")
        flags = tuple((name, bits.get(name, False)) for name in names)
        return BitfieldValue(raw=0, flags=flags)

    book.observe(_samples({"status": status()}, at=0.0))
    first = book.report("pool")
    book.observe(_samples({"status": status(oxygen_invalid=True)}, at=1.0))
    assert book.report("pool") is first
    book.observe(_samples({"status": status(cap_replacement_recommended=True)}, at=2.0))
    changed = book.report("pool")
    assert changed is not None
    assert changed.state is CareState.MAINTENANCE
