"""Aged simulated sensors: the records laid out at start, read back as a master reads them."""

from __future__ import annotations

from datetime import UTC, datetime, timedelta, timezone
from pathlib import Path
from typing import Any

import pytest

from gateway.cli.demo import DEMO_SENSORS
from gateway.errors import ConfigError
from gateway.profiles import get_profile
from gateway.simulator import SimulatedBus, build_bus, load_settings, parse_settings
from gateway.simulator.aging import (
    AgingSettings,
    amperometric_values,
    calibration_count,
    calibration_times,
    first_calibration,
    h10_values,
    local_stamp,
    logbook,
    measurement_counter,
    operating_seconds,
    s10_values,
    slope_fraction,
)
from gateway.wire import codec, encoding, frames
from gateway.wire.codec import BitfieldValue, EnumValue
from tests.simulator.helpers import ClockedMaster

# The simulator's wall clock in these tests: 45 s past a minute, so stamps must drop them.
NOW = datetime(2025, 6, 10, 12, 30, 45, tzinfo=UTC)
WEEK_S = 7 * 24 * 3600
DAY_S = 24 * 3600
# The plant's tecLine Cl2 that needs care: newest slope 44 % of nominal, 6 % a week less.
CARE_CELL = {
    "weeks_in_service": 8,
    "calibration_interval_days": 7,
    "last_calibration_days": 9,
    "slope_start": 0.8,
    "slope_decay_per_week": 0.06,
}
CL2_NOMINAL = 22.0  # tecLine annex 7.5 example, the simulator's Cl2 cell
# Calibrations 9, 16, 23, 30, 37, 44 and 51 days before NOW fit into 8 weeks (56 days);
# the first, 51 days ago, is where the slope starts falling.
CALIBRATED = [
    datetime(2025, 6, 1, 12, 30, tzinfo=UTC),
    datetime(2025, 5, 25, 12, 30, tzinfo=UTC),
    datetime(2025, 5, 18, 12, 30, tzinfo=UTC),
    datetime(2025, 5, 11, 12, 30, tzinfo=UTC),
    datetime(2025, 5, 4, 12, 30, tzinfo=UTC),
]
# 22 * (0.8 - 0.06 * weeks since the first): 6, 5, 4, 3 and 2 weeks.
SPANS = [22 * 0.44, 22 * 0.50, 22 * 0.56, 22 * 0.62, 22 * 0.68]


def aging(**keys: Any) -> AgingSettings:
    return AgingSettings.model_validate(keys)


def aged_bus(*devices: dict[str, Any]) -> SimulatedBus:
    bus = build_bus(parse_settings({"devices": list(devices)}), clock=lambda: NOW)
    bus.start(0.0)
    return bus


def read(master: ClockedMaster, address: int, name: str) -> codec.Decoded:
    """One point over the wire, decoded with the device's profile."""
    point = master.bus.devices[address].profile.point(name)
    response = master.ask(frames.read_request(address, point.address, point.count))
    return codec.decode(point.format, response.registers)


def write(master: ClockedMaster, address: int, name: str, value: object) -> None:
    point = master.bus.devices[address].profile.point(name)
    registers = encoding.encode(point.format, value)
    master.ask(frames.write_request(address, point.address, registers))


def local(instant: datetime) -> datetime:
    """The zone-less stamp the gateway would write at ``instant`` on this host."""
    return instant.astimezone().replace(tzinfo=None)


# --- pure: time ----------------------------------------------------------------------------


def test_the_calibrations_that_fit_in_service_newest_first_to_the_minute() -> None:
    settings = aging(**CARE_CELL)
    assert calibration_count(settings) == 7
    assert calibration_times(settings, NOW, limit=5) == tuple(CALIBRATED)
    assert first_calibration(settings, NOW) == datetime(2025, 4, 20, 12, 30, tzinfo=UTC)
    assert len(calibration_times(settings, NOW, limit=10)) == 7


def test_a_calibration_older_than_the_sensor_leaves_no_record() -> None:
    settings = aging(weeks_in_service=1, last_calibration_days=8)
    assert calibration_count(settings) == 0
    assert calibration_times(settings, NOW, limit=5) == ()
    # Slopes then fall from the start of service.
    assert first_calibration(settings, NOW) == datetime(2025, 6, 3, 12, 30, tzinfo=UTC)
    assert (
        amperometric_values(
            settings, now=NOW, profile=get_profile("jumo-tecline-cl2"), nominal_slope=22.0
        ).values
        == {}
    )


def test_the_start_of_service_counts_as_in_service() -> None:
    # 14 days in service, calibrated 0 and 7 and 14 days ago: three.
    assert calibration_count(aging(weeks_in_service=2, last_calibration_days=0)) == 3


def test_a_stamp_is_local_wall_clock_time_without_seconds() -> None:
    plus_two = timezone(timedelta(hours=2))
    assert local_stamp(NOW, plus_two) == datetime(2025, 6, 10, 14, 30)
    # The host's zone as at that instant (its summer time, not today's).
    assert local_stamp(NOW) == NOW.astimezone().replace(tzinfo=None, second=0)


def test_the_slope_falls_linearly_and_never_to_zero() -> None:
    settings = aging(slope_start=0.8, slope_decay_per_week=0.06)
    assert slope_fraction(settings, 0) == pytest.approx(0.8)
    assert slope_fraction(settings, 6) == pytest.approx(0.44)
    assert slope_fraction(settings, 100) == pytest.approx(0.01)


# --- pure: what each family gets ---------------------------------------------------------


def test_the_tecline_history_with_falling_slopes_and_the_active_calibration() -> None:
    plus_two = timezone(timedelta(hours=2))
    profile = get_profile("jumo-tecline-cl2")
    values = amperometric_values(
        aging(**CARE_CELL), now=NOW, profile=profile, nominal_slope=22.0, zone=plus_two
    ).values
    for k, (at, span) in enumerate(zip(CALIBRATED, SPANS, strict=True)):
        assert values[f"history_{k}_x_zero"] == 0.0
        assert values[f"history_{k}_x_span"] == pytest.approx(span)
        assert values[f"history_{k}_stamp"] == at.astimezone(plus_two).replace(tzinfo=None)
    assert values["history_0_stamp"] == datetime(2025, 6, 1, 14, 30)
    assert (values["x_zero"], values["x_span"], values["calibration_stamp"]) == (
        values["history_0_x_zero"],
        values["history_0_x_span"],
        values["history_0_stamp"],
    )


def test_a_short_service_fills_only_the_newest_history_entries() -> None:
    settings = aging(weeks_in_service=2, last_calibration_days=2, calibration_interval_days=7)
    values = amperometric_values(
        settings, now=NOW, profile=get_profile("reiss-m0c"), nominal_slope=10.0
    ).values
    assert {name for name in values if name.endswith("_stamp")} == {
        "history_0_stamp",
        "history_1_stamp",
        "calibration_stamp",
    }
    # The first calibration (9 days ago) at 0.95, the newest one week later at 0.89.
    assert values["history_1_x_span"] == pytest.approx(9.5)
    assert values["history_0_x_span"] == pytest.approx(8.9)


def test_the_logbook_alternates_end_value_and_zero_point_newest_first() -> None:
    settings = aging(weeks_in_service=9, evaluation="warning", cap_changes=300)
    counter_s = 9 * WEEK_S
    entries = logbook(settings, now=NOW, counter_s=counter_s, entries=10)
    assert [e.entry_type for e in entries] == [21, 20] * 5
    assert [e.rating for e in entries] == ["warning"] + ["ok"] * 9
    assert {e.sensor_replacement_counter for e in entries} == {255}  # a uint8 in the entry
    newest, zero = entries[0], entries[1]
    assert newest.date == CALIBRATED[0]
    assert zero.date == CALIBRATED[0] - timedelta(minutes=15)
    # The counter now, less the time since the entry (9 days and 45 s; 15 min more).
    assert newest.operating_seconds == counter_s - 9 * DAY_S - 45
    assert zero.operating_seconds == counter_s - 9 * DAY_S - 45 - 900
    assert newest.values == (35.0, 20.0, 0.0, 9.09, 1013.25, 0.0)
    assert newest.units == ("°", "°C", "", "mg/l", "mbar", "")
    # 8 calibrations in 63 days, the first 58 days ago: the newest is 7 weeks later.
    assert zero.values[0] == pytest.approx(60.0 + 0.05 * 7)
    assert entries[9].values[0] == pytest.approx(60.0 + 0.05 * 3)
    assert entries[9].date == CALIBRATED[4] - timedelta(minutes=15)


def test_the_counters_of_a_digiline_sensor() -> None:
    assert operating_seconds(aging(weeks_in_service=0)) == 3_600_000  # as without aging
    assert operating_seconds(aging(weeks_in_service=8)) == 8 * WEEK_S
    assert measurement_counter(aging(weeks_in_service=8)) == 800_000
    assert measurement_counter(aging(weeks_in_service=12)) == 1_000_000  # the maximum


def test_h10_values_flag_the_counter_at_its_maximum_and_the_cap() -> None:
    profile = get_profile("jumo-digiline-odo-h10")
    full = h10_values(aging(weeks_in_service=10, cap_missing=True), now=NOW, profile=profile)
    assert full.values["measurement_counter"] == 1_000_000
    assert full.flags == {
        "error_register": {"measurement_counter_overflow": True},
        "status": {"cap_missing": True},
    }
    used = h10_values(aging(weeks_in_service=9), now=NOW, profile=profile)
    assert used.flags["error_register"] == {"measurement_counter_overflow": False}


def test_s10_values_set_the_cap_bits_of_its_status_word() -> None:
    aged = s10_values(aging(cap_replacement_recommended=True), now=NOW)
    assert aged.flags == {"status": {"cap_replacement_recommended": True, "cap_missing": False}}
    assert aged.values["commissioning_date"] == datetime(2025, 4, 15, 12, 30, tzinfo=UTC)


# --- settings ------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("block", "message"),
    [
        ({"weeks": 8}, "devices.0.aging.weeks: Extra inputs are not permitted"),
        ({"weeks_in_service": 521}, "devices.0.aging.weeks_in_service"),
        ({"calibration_interval_days": 0}, "devices.0.aging.calibration_interval_days"),
        ({"evaluation": "bad"}, "devices.0.aging.evaluation"),
        (
            {"weeks_in_service": 1, "hours_outside_temperature": 200},
            "more than the 1.0 weeks in service",
        ),
    ],
)
def test_an_aging_block_is_checked_at_load(block: dict[str, Any], message: str) -> None:
    device = {"profile": "jumo-tecline-cl2", "address": 20, "aging": block}
    with pytest.raises(ConfigError, match=message):
        parse_settings({"devices": [device]})


def test_every_key_has_a_default() -> None:
    settings = parse_settings({"devices": [{"profile": "reiss-m0c", "address": 10, "aging": {}}]})
    assert settings.devices[0].aging == AgingSettings()
    assert (
        parse_settings({"devices": [{"profile": "reiss-m0c", "address": 10}]}).devices[0].aging
        is None
    )


# --- on the bus ----------------------------------------------------------------------------


def test_a_tecline_cell_in_service_as_a_master_reads_it() -> None:
    cell = {"profile": "jumo-tecline-cl2", "address": 20, "aging": CARE_CELL, "animate": False}
    master = ClockedMaster(aged_bus(cell))
    for k, (at, span) in enumerate(zip(CALIBRATED, SPANS, strict=True)):
        assert read(master, 20, f"history_{k}_x_zero") == 0.0
        assert read(master, 20, f"history_{k}_x_span") == pytest.approx(span, rel=1e-6)
        assert read(master, 20, f"history_{k}_stamp") == local(at)
    assert read(master, 20, "x_span") == pytest.approx(9.68, rel=1e-6)
    assert read(master, 20, "calibration_stamp") == local(CALIBRATED[0])
    # The cell's real slope now: 51 days after the first calibration.
    slope = 22 * (0.8 - 0.06 * 51 / 7)
    assert read(master, 20, "cell_current") == pytest.approx(0.5 * slope, abs=1e-4)
    assert read(master, 20, "concentration") == pytest.approx(0.5 * slope / 9.68, abs=1e-4)


def test_a_cells_slope_keeps_falling_at_run_time() -> None:
    bus = aged_bus(
        {"profile": "jumo-tecline-cl2", "address": 20, "aging": CARE_CELL, "animate": False}
    )
    sensor = bus.devices[20]
    sensor.tick(7 * DAY_S)  # a week later
    assert sensor.get("cell_current") == pytest.approx(0.5 * 22 * (0.8 - 0.06 * 58 / 7), abs=1e-4)
    sensor.tick(52 * WEEK_S)  # long after: the floor
    assert sensor.get("cell_current") == pytest.approx(0.5 * 22 * 0.01, abs=1e-4)


def test_a_calibration_by_a_master_still_moves_the_aged_history() -> None:
    master = ClockedMaster(
        aged_bus({"profile": "jumo-tecline-cl2", "address": 20, "aging": CARE_CELL})
    )
    stamp = datetime(2025, 6, 10, 14, 0)  # a YYMMDDHHMM stamp has no zone
    write(master, 20, "x_zero", 0.0)
    write(master, 20, "x_span", 8.0)
    write(master, 20, "calibration_stamp", stamp)
    assert read(master, 20, "history_0_stamp") == stamp
    assert read(master, 20, "history_0_x_span") == pytest.approx(8.0)
    assert read(master, 20, "history_1_stamp") == local(CALIBRATED[0])
    assert read(master, 20, "history_1_x_span") == pytest.approx(9.68, rel=1e-6)
    assert read(master, 20, "history_4_stamp") == local(CALIBRATED[3])  # the oldest dropped


H10_AGED = {
    "weeks_in_service": 9,
    "evaluation": "warning",
    "cap_changes": 2,
    "cip_cycles": 3,
    "sip_cycles": 2,
    "hours_outside_temperature": 12.5,
    "cap_missing": True,
}


def test_an_h10_in_service_as_a_master_reads_it() -> None:
    bus = aged_bus({"profile": "jumo-digiline-odo-h10", "address": 2, "aging": H10_AGED})
    assert bus.devices[2].get("measurement_counter") == 900_000  # before any measurement
    master = ClockedMaster(bus)
    counter_s = 9 * WEEK_S
    first = [read(master, 2, f"logbook_1_{part}") for part in ("entry_type", "rating", "date")]
    assert [v.label if isinstance(v, EnumValue) else v for v in first] == [
        "end_value",
        "warning",
        CALIBRATED[0],
    ]
    assert read(master, 2, "logbook_1_operating_seconds") == counter_s - 9 * DAY_S - 45
    assert read(master, 2, "logbook_1_sensor_replacement_counter") == 2
    assert read(master, 2, "logbook_1_oxygen") == pytest.approx(9.09, rel=1e-6)
    assert read(master, 2, "logbook_1_oxygen_unit") == "mg/l"
    zero_type = read(master, 2, "logbook_2_entry_type")
    assert isinstance(zero_type, EnumValue)
    assert zero_type.label == "zero_point"
    assert read(master, 2, "logbook_2_date") == CALIBRATED[0] - timedelta(minutes=15)
    assert read(master, 2, "logbook_2_phase") == pytest.approx(60.35, rel=1e-6)
    assert read(master, 2, "zero_point_phase") == pytest.approx(60.35, rel=1e-6)
    assert read(master, 2, "logbook_10_date") == CALIBRATED[4] - timedelta(minutes=15)
    assert read(master, 2, "logbook_10_operating_seconds") == (counter_s - 37 * DAY_S - 45 - 900)
    # The counter runs on from the time in service; measurements go on counting.
    seconds = read(master, 2, "operating_seconds")
    assert isinstance(seconds, int)
    assert counter_s <= seconds <= counter_s + int(master.now) + 1
    counted = read(master, 2, "measurement_counter")
    assert isinstance(counted, int)
    assert 900_000 < counted <= 900_000 + int(master.now) + 1
    assert read(master, 2, "measurement_counter_max") == 1_000_000
    assert read(master, 2, "sensor_replacement_counter") == 2
    assert read(master, 2, "cip_cycles_since_calibration") == 3
    assert read(master, 2, "sip_cycles_since_calibration") == 2
    assert read(master, 2, "hours_outside_operating_temperature") == 12.5
    assert read(master, 2, "commissioning_date") == datetime(2025, 4, 8, 12, 30, tzinfo=UTC)
    status = read(master, 2, "status")
    assert isinstance(status, BitfieldValue)
    assert "cap_missing" in status.active
    errors = read(master, 2, "error_register")
    assert isinstance(errors, BitfieldValue)
    assert errors.active == ()


def test_an_h10_whose_counter_reaches_its_maximum_flags_the_overflow() -> None:
    aged = {"weeks_in_service": 10, "measurement_counter_max": 1_000_000}
    master = ClockedMaster(
        aged_bus({"profile": "jumo-digiline-odo-h20", "address": 3, "aging": aged})
    )
    errors = read(master, 3, "error_register")
    assert isinstance(errors, BitfieldValue)
    assert errors.active == ("measurement_counter_overflow",)
    write(master, 3, "measurement_counter_control", "reset")  # 6.2.9: back to 0
    master.now += 1.0  # the post-write wait, and a measurement
    errors = read(master, 3, "error_register")
    assert isinstance(errors, BitfieldValue)
    assert errors.active == ()


def test_a_new_h10_calibration_still_pushes_the_aged_logbook() -> None:
    master = ClockedMaster(
        aged_bus({"profile": "jumo-digiline-odo-h10", "address": 2, "aging": H10_AGED}),
        gap_s=0.7,
    )
    write(master, 2, "zero_point_calibration_trigger", 1)
    entry_type = read(master, 2, "logbook_1_entry_type")
    assert isinstance(entry_type, EnumValue)
    assert entry_type.label == "zero_point"
    assert read(master, 2, "logbook_2_date") == CALIBRATED[0]  # the aged newest, one down
    rating = read(master, 2, "logbook_2_rating")
    assert isinstance(rating, EnumValue)
    assert rating.label == "warning"


def test_an_s10_in_service_as_a_master_reads_it() -> None:
    aged = {"weeks_in_service": 8, "cap_replacement_recommended": True, "cap_changes": 3}
    master = ClockedMaster(
        aged_bus({"profile": "jumo-digiline-odo-s10", "address": 1, "aging": aged})
    )
    seconds = read(master, 1, "operating_seconds")
    assert isinstance(seconds, int)
    assert 8 * WEEK_S <= seconds <= 8 * WEEK_S + int(master.now) + 1
    status = read(master, 1, "status")
    assert isinstance(status, BitfieldValue)
    assert status.active == ("cap_replacement_recommended",)
    assert read(master, 1, "sensor_replacement_counter") == 3
    assert read(master, 1, "commissioning_date") == datetime(2025, 4, 15, 12, 30, tzinfo=UTC)


@pytest.mark.parametrize(
    "profile", ["jumo-tecline-cl2", "reiss-m3c", "jumo-digiline-odo-h10", "jumo-digiline-odo-h20"]
)
def test_without_aging_a_device_starts_as_it_always_did(profile: str) -> None:
    """No ``aging:`` block: the registers do not depend on the wall clock."""
    device = {"profile": profile, "address": 5, "animate": False}
    now = aged_bus(device).devices[5]
    other = build_bus(parse_settings({"devices": [device]}))
    other.start(0.0)
    assert other.devices[5].registers == now.registers
    if profile.startswith("jumo-digiline"):
        assert now.get("measurement_counter") == 1  # the first measurement
        assert now.get("logbook_1_date") is None
    else:
        assert now.get("history_0_stamp") is None
        assert now.get("x_span") == now.get("nominal_slope")


# --- the plant and the demo ----------------------------------------------------------------


def _care(bus: SimulatedBus) -> dict[int, object]:
    """What each sensor shows that care looks at: slope, counter use, status bits."""
    shown: dict[int, object] = {}
    for address, device in bus.devices.items():
        if device.profile.family in {"jumo-tecline", "reiss-m0c-m3c"}:
            span, nominal = device.get("x_span"), device.get("nominal_slope")
            assert isinstance(span, float)
            assert isinstance(nominal, float)
            shown[address] = round(span / nominal, 2)
        elif device.profile.family == "jumo-digiline-odo-h10-h20":
            shown[address] = device.get("measurement_counter")
        else:
            status = device.get("status")
            assert isinstance(status, BitfieldValue)
            shown[address] = status.active
    return shown


def test_the_plant_has_one_sensor_of_each_kind_needing_care() -> None:
    example = Path(__file__).parents[2] / "config" / "simulator-plant.yaml"
    bus = build_bus(load_settings(example), clock=lambda: NOW)
    bus.start(0.0)
    assert _care(bus) == {
        1: ("cap_replacement_recommended",),
        2: 900_000,  # of 1000000
        3: 160_000,
        20: 0.44,
        80: 0.88,
        10: 0.88,
        30: 0.88,
    }


def test_the_demo_has_one_sensor_of_each_kind_needing_care() -> None:
    bus = aged_bus(*DEMO_SENSORS)
    assert _care(bus) == {
        1: ("cap_replacement_recommended",),
        2: 900_000,
        3: 160_000,
        20: 0.44,
        10: 0.88,
        30: 0.88,
    }
