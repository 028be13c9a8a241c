"""Operations on one sensor against the simulator: bytes written, waits kept, tables read.

What was written is read from the simulator's write log, timing from its referee and its
frame log; values are compared with what the simulated sensor holds.
"""

from __future__ import annotations

import json
from datetime import UTC, date, datetime, timedelta, timezone
from typing import TYPE_CHECKING

import pytest

from gateway.config import FlashPolicy
from gateway.control.flash import FlashLedger
from gateway.control.operations import (
    OPERATION_NAMES,
    calibration_log,
    measure,
    operations_for,
    run_operation,
    set_clock,
)
from gateway.control.writes import SafeWriter
from gateway.errors import CommandRejectedError, OperationTimeoutError
from gateway.profiles import builtin_profiles, get_profile
from gateway.simulator.behaviour import SINGLE_MEASUREMENT_S, H10Behaviour
from gateway.wire import codec
from tests.rigs import PLANT, link_rig, link_target, target

if TYPE_CHECKING:
    from pathlib import Path

    from gateway.line.engine.devices import DeviceTarget
    from gateway.simulator.device import SimulatedDevice
    from tests.rigs import LinkRig

DAY = date(2026, 11, 22)
NO_FLASH = FlashPolicy(allowed=frozenset(), daily_budget=4)
H10_POST_WRITE_WAIT_S = 0.25  # H10/H20 manual 6.1.5
DAY_NOW = datetime(2026, 11, 22, 12, tzinfo=UTC)  # the gateway clock where it does not matter


def targets() -> list[DeviceTarget]:
    return [
        link_target("s10", "jumo-digiline-odo-s10", 1),
        link_target("h10", "jumo-digiline-odo-h10", 2),
        link_target("h20", "jumo-digiline-odo-h20", 3),
        link_target("cl2", "jumo-tecline-cl2", 20),
        link_target("m0c", "reiss-m0c", 10),
    ]


def writer(
    rig: LinkRig, device: str, ledger: FlashLedger, policy: FlashPolicy = NO_FLASH
) -> SafeWriter:
    return SafeWriter(rig.links[device], policy=policy, ledger=ledger, today=lambda: DAY)


@pytest.fixture
def ledger(tmp_path: Path) -> FlashLedger:
    return FlashLedger(tmp_path / "flash.sqlite")


def plant_with(address: int, **values: object) -> list[dict[str, object]]:
    """The plant with configured (held) values on one device."""
    return [
        {**entry, "values": values} if entry["address"] == address else entry for entry in PLANT
    ]


# --- which operation applies -----------------------------------------------------------


def test_operations_follow_the_profiles() -> None:
    expected = {
        "jumo-digiline-odo-s10": ["set_clock"],
        "jumo-digiline-odo-h10": ["set_clock", "measure", "calibration_log", "calibrations"],
        "jumo-digiline-odo-h20": ["set_clock", "measure", "calibration_log", "calibrations"],
    }
    assert OPERATION_NAMES == ("set_clock", "measure", "calibration_log", "calibrations")
    for profile_id, profile in builtin_profiles().items():
        # every tecLine and Reiss variant has the five-entry history and guided calibrations
        want = expected.get(profile_id, ["calibration_log", "calibrations"])
        assert operations_for(profile) == want, profile_id
    assert operations_for(get_profile("reiss-m3c")) == ["calibration_log", "calibrations"]


# --- set_clock ------------------------------------------------------------------------------


@pytest.mark.line
async def test_s10_clock_block_is_written_with_function_16_and_offsets_reported(
    tmp_path: Path, ledger: FlashLedger
) -> None:
    # The gateway's clock is 90 minutes ahead of the simulated sensor's.
    now = datetime.now(UTC) + timedelta(minutes=90)
    async with link_rig(tmp_path, PLANT, targets()) as rig:
        result = await run_operation("set_clock", writer(rig, "s10", ledger), {}, now=now)
        json.dumps(result)  # JSON-ready as the MQTT result needs it
        written = datetime.fromisoformat(str(result["written"]))
        [record] = rig.writes(1)
        assert (record.function, record.address) == (16, 0x2840)  # S10 manual 6.9
        assert record.values == (
            written.year,
            written.month,
            written.day,
            written.hour,
            written.minute,
            written.second,
            0,  # time zone: offset to UTC in minutes
        )
        assert written.microsecond == 0
        assert written.utcoffset() == timedelta(0)
        assert result["registers"] == list(record.values)
        before, after = result["offset_before_s"], result["offset_after_s"]
        assert isinstance(before, float)
        assert isinstance(after, float)
        assert -5402 < before < -5398
        assert abs(after) < 1.5  # the sensor keeps whole seconds
        assert result["running"] is True
        sensor = rig.device(1).get("clock")
        assert isinstance(sensor, datetime)
        assert abs((sensor - datetime.now(UTC) - timedelta(minutes=90)).total_seconds()) < 2
        assert rig.violations() == []
    # The S10 clock is flash-backed: an explicit write needs no allow-list but is counted.
    assert ledger.count_today("s10", "clock", DAY) == 1


@pytest.mark.line
async def test_set_clock_writes_utc_or_with_local_the_hosts_zone(
    tmp_path: Path, ledger: FlashLedger
) -> None:
    now = datetime.now(timezone(timedelta(hours=2)))
    async with link_rig(tmp_path, PLANT, targets()) as rig:
        s10 = writer(rig, "s10", ledger)
        utc = await set_clock(s10, now=now)
        assert utc.written.utcoffset() == timedelta(0)
        assert timedelta(0) < utc.written - now <= timedelta(seconds=2)  # the next whole second
        local = await set_clock(s10, now=datetime.now(UTC), local=True)
        offset = datetime.now().astimezone().utcoffset()
        assert offset is not None
        assert local.written.utcoffset() == offset
        first, second = rig.writes(1)
        assert first.values[6] == 0
        assert second.values[6] == int(offset.total_seconds() // 60) & 0xFFFF
        assert second.values[3] == local.written.hour


@pytest.mark.line
async def test_h10_calibration_date_is_set_keeps_the_250_ms_wait_and_stamps_the_logbook(
    tmp_path: Path, ledger: FlashLedger
) -> None:
    async with link_rig(tmp_path, PLANT, targets()) as rig:
        h10 = writer(rig, "h10", ledger)
        result = await set_clock(h10, now=datetime.now(UTC))
        assert result.point == "calibration_date"
        assert not result.running
        assert result.before is None  # never set: all seven registers 0
        assert result.offset_before_s is None
        assert result.after == result.written
        [record] = rig.writes(2)
        assert (record.function, record.address) == (16, 0x300A)  # manual 6.2.4
        w = result.written
        assert record.values == (w.year, w.month, w.day, w.hour, w.minute, w.second, 0)
        frames = [f for f in rig.rig.frames() if f.device == 2]
        at = next(i for i, f in enumerate(frames) if f.function == 16)
        assert frames[at].answer_at is not None
        assert frames[at + 1].start - frames[at].answer_at >= H10_POST_WRITE_WAIT_S
        # The sensor copies the date into the next logbook entry (manual 6.2.4).
        await h10.set(h10.point("zero_point_calibration_trigger"), 1.0, explicit=True)
        log = await calibration_log(rig.links["h10"])
        assert not log.entries[0].empty
        assert log.entries[0].values["date"] == result.written
        assert rig.violations() == []
    assert ledger.totals() == {("h10", "zero_point_calibration_trigger"): 1}  # the date is free


@pytest.mark.line
async def test_set_clock_keeps_the_daily_flash_budget(tmp_path: Path, ledger: FlashLedger) -> None:
    policy = FlashPolicy(allowed=frozenset(), daily_budget=1)
    async with link_rig(tmp_path, PLANT, targets()) as rig:
        s10 = writer(rig, "s10", ledger, policy)
        await set_clock(s10, now=datetime.now(UTC))
        with pytest.raises(CommandRejectedError, match="budget of 1 writes per day"):
            await set_clock(s10, now=datetime.now(UTC))
        assert len(rig.writes(1)) == 1
    assert ledger.count_today("s10", "clock", DAY) == 1


@pytest.mark.line
async def test_set_clock_refuses_a_clock_without_zone_before_the_bus(
    tmp_path: Path, ledger: FlashLedger
) -> None:
    async with link_rig(tmp_path, PLANT, targets()) as rig:
        with pytest.raises(CommandRejectedError, match="time zone"):
            await set_clock(writer(rig, "s10", ledger), now=datetime(2026, 1, 1, 12))
        assert rig.rig.frames() == []


# --- measure --------------------------------------------------------------------------------


@pytest.mark.line
async def test_measure_triggers_with_bit_2_waits_for_the_end_and_returns_fresh_values(
    tmp_path: Path, ledger: FlashLedger
) -> None:
    # No continuous measurement (interval 0): only the triggered one can change the value.
    async with link_rig(tmp_path, plant_with(2, measurement_interval=0.0), targets()) as rig:
        device = rig.device(2)
        device.put("oxygen", 55.5)
        counter = device.get("measurement_counter")
        assert isinstance(counter, int)
        result = await run_operation("measure", writer(rig, "h10", ledger), {}, now=DAY_NOW)
        json.dumps(result)
        assert result["oxygen"] == device.get("oxygen") != 55.5
        assert result["oxygen_unit"] == "mg/l"  # the H10 simulator measures in ppm
        assert result["temperature"] == device.get("temperature")
        assert result["temperature_unit"] == "°C"
        assert device.get("measurement_counter") == counter + 1  # exactly one measurement
        assert result["saw_running"] is True
        assert result["status"] == ["new_values"]
        duration = result["duration_s"]
        assert isinstance(duration, float)
        # Timed from the write's answer, a few ms after the simulator started its 0.3 s.
        assert duration >= SINGLE_MEASUREMENT_S - 0.05
        # 0x3001, uint32 high word first: bit 2 set, bit 0 (continuous) kept as read.
        [record] = rig.writes(2)
        assert (record.function, record.address, record.values) == (16, 0x3001, (0x0000, 0x0005))
        frames = [f for f in rig.rig.frames() if f.device == 2]
        at = next(i for i, f in enumerate(frames) if f.function == 16)
        write = frames[at]
        assert write.answer_at is not None
        assert frames[at + 1].start - write.answer_at >= H10_POST_WRITE_WAIT_S
        oxygen_read = next(f for f in frames[at:] if f.function in {3, 4} and f.address == 0x2001)
        assert oxygen_read.start - write.start >= SINGLE_MEASUREMENT_S  # read after the end
        assert rig.violations() == []
    # 0x3001 is classed flash-backed by the profile: the trigger counts against the budget.
    assert ledger.count_today("h10", "measurement_status", DAY) == 1


@pytest.mark.parametrize(
    ("continuous", "word"), [(True, (0x0000, 0x0005)), (False, (0x0000, 0x0004))]
)
@pytest.mark.line
async def test_measure_writes_back_the_status_word_it_read(
    tmp_path: Path, ledger: FlashLedger, *, continuous: bool, word: tuple[int, int]
) -> None:
    plant = plant_with(3, measurement_status={"continuous_measurement": continuous})
    async with link_rig(tmp_path, plant, targets()) as rig:
        await measure(writer(rig, "h20", ledger))
        assert [(r.function, r.address, r.values) for r in rig.writes(3)] == [(16, 0x3001, word)]
        assert rig.violations() == []


@pytest.mark.line
async def test_measure_while_the_worker_polls(tmp_path: Path, ledger: FlashLedger) -> None:
    polled = [
        target("s10", "jumo-digiline-odo-s10", 1, interval=0.2),
        target("h10", "jumo-digiline-odo-h10", 2, interval=0.2),
        link_target("cl2", "jumo-tecline-cl2", 20),
    ]
    async with link_rig(tmp_path, PLANT, polled, poll=True) as rig:
        # The simulator's 0.3 s measurement is over 50 ms after the H10's post-write wait:
        # a poll of the two devices in between on a loaded machine and the status read
        # finds it done (seen in CI). Bit 1 is the point here, so the measurement runs 1 s.
        behaviour = rig.device(2).behaviour
        assert isinstance(behaviour, H10Behaviour)
        behaviour.single_measurement_s = 1.0
        result = await measure(writer(rig, "h10", ledger))
        assert result.values["oxygen"] == rig.device(2).get("oxygen")
        assert result.saw_running
        assert isinstance(result.duration_s, float)
        assert result.duration_s >= 1.0 - 0.05
        [record] = rig.writes(2)
        assert (record.address, record.values[1] & 0b100) == (0x3001, 0b100)
        s10_reads = [f for f in rig.rig.frames() if f.device == 1]
        assert len(s10_reads) > 2  # polling went on meanwhile
        assert rig.violations() == []


@pytest.mark.line
async def test_measure_that_never_reports_new_values_times_out(
    tmp_path: Path, ledger: FlashLedger
) -> None:
    async with link_rig(tmp_path, PLANT, targets()) as rig:
        rig.device(2).set_flags("status", new_values=False)  # held: never set again
        with pytest.raises(OperationTimeoutError, match=r"did not finish within 0\.8 s"):
            await measure(writer(rig, "h10", ledger), timeout_s=0.8)
        assert len(rig.writes(2)) == 1  # the trigger was sent; the error says so by its type


@pytest.mark.line
async def test_measure_does_not_trigger_while_a_measurement_runs(
    tmp_path: Path, ledger: FlashLedger
) -> None:
    async with link_rig(tmp_path, PLANT, targets()) as rig:
        rig.device(2).set_flags("measurement_status", measuring=True)
        with pytest.raises(OperationTimeoutError, match="still running"):
            await measure(writer(rig, "h10", ledger), timeout_s=0.5)
        assert rig.writes(2) == []
    assert ledger.totals() == {}


# --- calibration_log ------------------------------------------------------------------------

LOGBOOK_FIELDS = (
    "entry_type",
    "manual_change",
    "rating",
    "operating_seconds",
    "date",
    "sensor_replacement_counter",
    "phase",
    "temperature",
    "calibration_mode",
    "oxygen",
    "pressure",
    "value_6",
    "phase_unit",
    "temperature_unit",
    "calibration_mode_unit",
    "oxygen_unit",
    "pressure_unit",
    "value_6_unit",
)


def fill_logbook(device: SimulatedDevice, index: int, *, entry_type: int, when: datetime) -> None:
    prefix = f"logbook_{index}_"
    device.put(prefix + "entry_type", entry_type)
    device.put(prefix + "manual_change", "calibration")
    device.put(prefix + "rating", "ok")
    device.put(prefix + "operating_seconds", 3_600_000 + index)
    device.put(prefix + "date", when)
    device.put(prefix + "sensor_replacement_counter", 2)
    device.put(prefix + "phase", 35.25 + index)
    device.put(prefix + "phase_unit", "°")
    device.put(prefix + "temperature", 21.5)
    device.put(prefix + "temperature_unit", "°C")
    device.put(prefix + "calibration_mode", 1.0)
    if entry_type == 21:
        device.put(prefix + "oxygen", 8.25)
        device.put(prefix + "oxygen_unit", "mg/l")
        device.put(prefix + "pressure", 1013.0)
        device.put(prefix + "pressure_unit", "mbar")


@pytest.mark.line
async def test_logbook_shows_the_entries_the_sensor_holds_and_empty_ones_as_empty(
    tmp_path: Path,
) -> None:
    cest = timezone(timedelta(hours=2))
    async with link_rig(tmp_path, PLANT, targets()) as rig:
        device = rig.device(2)
        fill_logbook(device, 1, entry_type=21, when=datetime(2026, 5, 4, 10, 30, 5, tzinfo=cest))
        fill_logbook(device, 2, entry_type=20, when=datetime(2026, 5, 4, 10, 0, tzinfo=cest))
        # Entry 3 says "kein Eintrag" but holds leftovers; entry 10 is erased flash (0xFFFF),
        # whose date and unit texts do not even decode.
        device.put("logbook_3_phase", 42.0)
        device.put("logbook_3_phase_unit", "zz")
        entry_10 = device.profile.point("logbook_10_entry_type").address
        for address in range(entry_10, entry_10 + 0x31):
            device.registers[address] = 0xFFFF
        log = await calibration_log(rig.links["h10"])
        assert log.kind == "logbook"
        assert log.fields == LOGBOOK_FIELDS
        assert [e.index for e in log.entries] == list(range(1, 11))
        assert [e.empty for e in log.entries] == [False, False] + [True] * 8
        for entry in log.entries[:2]:
            assert entry.values == {
                name: device.get(f"logbook_{entry.index}_{name}") for name in LOGBOOK_FIELDS
            }
        first = log.entries[0]
        assert first.values["entry_type"] == codec.EnumValue(21, "end_value")
        assert first.values["date"] == datetime(2026, 5, 4, 10, 30, 5, tzinfo=cest)
        assert log.unit_of(first, "oxygen") == "mg/l"
        assert log.unit_of(first, "operating_seconds") == "s"
        assert all(e.values == {} for e in log.entries[2:])
        data = log.as_dict()
        json.dumps(data)
        entries = data["entries"]
        assert isinstance(entries, list)
        assert entries[2] == {"index": 3, "empty": True}
        assert entries[9] == {"index": 10, "empty": True}
        assert entries[0]["date"] == "2026-05-04T10:30:05+02:00"
        assert entries[0]["entry_type"] == "end_value"
        assert rig.violations() == []
    assert rig.writes(2) == []


@pytest.mark.parametrize(("device_name", "address"), [("cl2", 20), ("m0c", 10)])
@pytest.mark.line
async def test_history_shows_the_current_calibration_and_five_entries(
    tmp_path: Path, device_name: str, address: int
) -> None:
    stamps = [datetime(2026, 3, 1, 14, 30), datetime(2026, 2, 1, 9, 0), datetime(2026, 1, 5, 8, 0)]
    async with link_rig(tmp_path, PLANT, targets()) as rig:
        device = rig.device(address)
        for index, stamp in enumerate(stamps):
            device.put(f"history_{index}_x_zero", 0.5 * index)
            device.put(f"history_{index}_x_span", 21.75 - index)
            device.put(f"history_{index}_stamp", stamp)
        device.put("x_zero", 0.0)
        device.put("x_span", 21.75)
        device.put("calibration_stamp", stamps[0])
        device.put("history_3_x_zero", 7.0)  # leftovers of an entry with stamp 0
        device.put("history_3_x_span", 99.0)
        result = await run_operation(
            "calibration_log",
            writer(rig, device_name, FlashLedger(tmp_path / "f")),
            {},
            now=DAY_NOW,
        )
        json.dumps(result)
        assert result["kind"] == "history"
        assert result["current"] == {
            "x_zero": 0.0,
            "x_span": 21.75,
            "calibration_stamp": "2026-03-01T14:30:00",
        }
        assert result["entries"] == [
            {
                "index": index,
                "empty": False,
                "x_zero": device.get(f"history_{index}_x_zero"),
                "x_span": device.get(f"history_{index}_x_span"),
                "stamp": stamps[index].isoformat(),
            }
            for index in range(3)
        ] + [{"index": 3, "empty": True}, {"index": 4, "empty": True}]
        assert result["units"] == {"x_zero": "nA", "x_span": "nA/unit"}
        assert rig.violations() == []
    assert rig.writes(address) == []


# --- rejections: nothing reaches the bus ------------------------------------------------------


@pytest.mark.parametrize(
    ("device", "name", "arguments", "reason"),
    [
        ("h10", "reboot", {}, "unknown operation 'reboot'; operations: set_clock, measure"),
        ("s10", "measure", {}, "does not apply to profile jumo-digiline-odo-s10 .*: set_clock\\)"),
        ("cl2", "set_clock", {}, "operations for this device: calibration_log"),
        ("m0c", "measure", {}, "operations for this device: calibration_log"),
        ("h10", "measure", {"timeout": "soon"}, "'timeout' must be a number of seconds"),
        ("h10", "measure", {"timeout": 0}, "more than 0 and at most 50 seconds"),
        ("h10", "measure", {"timeout": 500}, "more than 0 and at most 50 seconds"),
        ("h10", "measure", {"timeout": True}, "must be a number of seconds"),
        (
            "h10",
            "measure",
            {"timout": 5},
            "unknown argument 'timout' for measure; it takes timeout",
        ),
        ("s10", "set_clock", {"local": "yes"}, "'local' must be true or false"),
        ("h10", "calibration_log", {"entries": 3}, "for calibration_log; it takes none"),
    ],
    ids=[
        "unknown-operation",
        "measure-on-s10",
        "clock-on-tecline",
        "measure-on-reiss",
        "timeout-text",
        "timeout-zero",
        "timeout-too-long",
        "timeout-bool",
        "unknown-argument",
        "flag-not-bool",
        "log-takes-nothing",
    ],
)
@pytest.mark.line
async def test_rejected_operations_send_nothing(
    tmp_path: Path,
    ledger: FlashLedger,
    *,
    device: str,
    name: str,
    arguments: dict[str, object],
    reason: str,
) -> None:
    async with link_rig(tmp_path, PLANT, targets()) as rig:
        with pytest.raises(CommandRejectedError, match=reason):
            await run_operation(name, writer(rig, device, ledger), arguments, now=DAY_NOW)
        assert rig.rig.frames() == []
    assert ledger.totals() == {}
