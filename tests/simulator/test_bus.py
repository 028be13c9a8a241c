"""The simulated bus without I/O: manual behaviour and the timing referee, on a test clock."""

from __future__ import annotations

from datetime import datetime, timedelta, timezone

import pytest

from gateway.errors import ConfigError, DeviceExceptionError
from gateway.profiles import get_profile
from gateway.simulator import SimulatedDevice
from gateway.simulator.bus import Reply
from gateway.wire import codec, encoding, frames
from gateway.wire.codec import Fault, WordOrder
from tests.simulator.helpers import ClockedMaster, make_bus

S10 = {"profile": "jumo-digiline-odo-s10", "address": 1, "animate": False}
H10 = {"profile": "jumo-digiline-odo-h10", "address": 2, "animate": False}
TECLINE = {"profile": "jumo-tecline-cl2", "address": 20, "animate": False}
REISS = {"profile": "reiss-m0c", "address": 10, "animate": False}


def decode(
    profile_id: str, name: str, registers: tuple[int, ...], order: WordOrder = WordOrder.CDAB
) -> object:
    point = get_profile(profile_id).point(name)
    return codec.decode(point.format, registers, float_order=order)


def read_point(
    master: ClockedMaster, address: int, profile_id: str, name: str, gap_s: float | None = None
) -> object:
    point = get_profile(profile_id).point(name)
    response = master.ask(frames.read_request(address, point.address, point.count), gap_s=gap_s)
    return codec.decode(point.format, response.registers)


def write_point(
    master: ClockedMaster, address: int, profile_id: str, name: str, value: object
) -> frames.Response:
    profile = get_profile(profile_id)
    point = profile.point(name)
    registers = encoding.encode(point.format, value)
    return master.ask(
        frames.write_request(address, point.address, registers), exceptions=profile.exceptions
    )


# --- reads and exceptions ----------------------------------------------------------------


def test_every_family_answers_with_its_configured_values() -> None:
    bus = make_bus(
        {**S10, "values": {"temperature": 20.25}},
        {**TECLINE, "values": {"temperature": 24.091}},
        H10,
        REISS,
    )
    master = ClockedMaster(bus)
    response = master.ask(frames.read_request(1, 0x2620, 2))
    assert response.registers == (0x0000, 0x41A2)  # S10 manual 2.6.2, byte for byte
    assert read_point(master, 20, "jumo-tecline-cl2", "temperature") == pytest.approx(
        24.091, abs=1e-4
    )
    assert read_point(master, 1, "jumo-digiline-odo-s10", "device_name") == "ODO S10"
    assert read_point(master, 2, "jumo-digiline-odo-h10", "sensor_type") == codec.EnumValue(
        3, "digiline_odo_h10_h20"
    )
    assert read_point(master, 10, "reiss-m0c", "sensor_type") == "CP4.0N-M0"


@pytest.mark.parametrize(
    ("address", "count"),
    [(0x2345, 1), (0x2600, 3), (0x001A, 1), (0x0000, 126), (0x0000, 0)],
)
def test_unmapped_and_over_long_reads_get_exception_02(address: int, count: int) -> None:
    master = ClockedMaster(make_bus(S10))
    request = frames.Request(
        device=1, function=3, address=address, count=count, frame=_raw_read(1, address, count)
    )
    with pytest.raises(DeviceExceptionError) as caught:
        master.ask(request)
    assert caught.value.code == 2


def _raw_read(device: int, address: int, count: int) -> bytes:
    body = bytes([device, 3]) + address.to_bytes(2, "big") + count.to_bytes(2, "big")
    return body + frames.crc16(body)


def test_raw_registers_are_held_and_answered_outside_the_map() -> None:
    """``registers``: raw words no encoder writes (an S10 clock dated month 13), held
    against the clock's ticking, and words a unit answers beyond its manual (a tecLine
    that reads 0 at the digiLine sensor type 0x010A) while the rest stays unmapped."""
    bus = make_bus({**S10, "registers": {0x2841: 13}}, {**TECLINE, "registers": {0x010A: 0}})
    master = ClockedMaster(bus)
    master.now += 5.0  # the sensor's clock would have ticked on
    clock = master.ask(frames.read_request(1, 0x2840, 7)).registers
    assert clock[1] == 13
    assert master.ask(frames.read_request(20, 0x010A, 1)).registers == (0,)
    with pytest.raises(DeviceExceptionError) as beyond:
        master.ask(frames.read_request(20, 0x010A, 2))  # 0x010B: not given, not in its map
    assert beyond.value.code == 2


def test_write_to_read_only_is_08_on_digiline_and_02_on_tecline() -> None:
    master = ClockedMaster(make_bus(S10, TECLINE))
    with pytest.raises(DeviceExceptionError) as digiline:
        master.ask(frames.write_multiple_request(1, 0x2620, [0, 0x41A2]))
    assert digiline.value.code == 8
    with pytest.raises(DeviceExceptionError) as tecline:
        master.ask(frames.write_multiple_request(20, 0x0000, [0, 0x41A2]))
    assert tecline.value.code == 2
    with pytest.raises(DeviceExceptionError) as unmapped:
        master.ask(frames.write_single_request(1, 0x2345, 1))  # the manuals' example
    assert unmapped.value.code == 2


def test_out_of_range_values_get_exception_03_and_change_nothing() -> None:
    bus = make_bus(H10)
    master = ClockedMaster(bus)
    before = bus.devices[2].get("compensation_temperature")
    with pytest.raises(DeviceExceptionError) as caught:
        master.ask(
            frames.write_multiple_request(
                2, 0x2013, list(codec.float_to_registers(150.0, WordOrder.CDAB))
            )
        )
    assert caught.value.code == 3
    assert bus.devices[2].get("compensation_temperature") == before
    with pytest.raises(DeviceExceptionError) as enum:
        master.ask(frames.write_single_request(2, 0x3009, 7), gap_s=1.0)
    assert enum.value.code == 3
    log = bus.devices[2].write_log
    assert [w.exception for w in log] == [3, 3]


def test_unknown_function_gets_exception_01() -> None:
    master = ClockedMaster(make_bus(S10))
    body = bytes.fromhex("01 2B 0E 01 00")
    replies = master.send(body + frames.crc16(body))
    assert replies[0].data[:3] == bytes.fromhex("01 AB 01")


def test_silent_for_other_addresses_and_bad_crc() -> None:
    bus = make_bus(S10)
    master = ClockedMaster(bus)
    assert master.send(frames.read_request(5, 0x2620, 2)) == []
    corrupted = bytearray(frames.read_request(1, 0x2620, 2).frame)
    corrupted[-1] ^= 0xFF
    assert master.send(bytes(corrupted)) == []
    assert bus.counters["other_address"] == 1
    assert bus.counters["crc_errors"] == 1


# --- digiLine settings honoured ----------------------------------------------------------


@pytest.mark.parametrize(
    ("code", "order"), [(0, WordOrder.CDAB), (1, WordOrder.DCBA), (2, WordOrder.ABCD)]
)
def test_float_format_register_selects_the_word_order(code: int, order: WordOrder) -> None:
    bus = make_bus({**S10, "values": {"temperature": 20.25}})
    master = ClockedMaster(bus)
    master.ask(frames.write_single_request(1, 0x0307, code))
    registers = master.ask(frames.read_request(1, 0x2620, 2)).registers
    assert (
        codec.decode(
            get_profile("jumo-digiline-odo-s10").point("temperature").format,
            registers,
            float_order=order,
        )
        == 20.25
    )
    # Writes use the selected order too.
    master.ask(
        frames.write_multiple_request(1, 0x25B0, list(codec.float_to_registers(12.5, order)))
    )
    assert bus.devices[1].get("compensation_temperature") == 12.5


def test_processing_time_and_minimum_response_time() -> None:
    bus = make_bus(S10)
    master = ClockedMaster(bus)
    char = 10 / 9600  # 8N1
    wire = (8 + 9) * char  # the request heard in full, the answer on the line
    sent = master.now + 0.3
    reply = master.send(frames.read_request(1, 0x2620, 2))[0]
    assert reply.at == pytest.approx(sent + wire + 0.005)  # t1 typical 5 ms
    master.ask(frames.write_single_request(1, 0x0305, 120))  # minimum response time 120 ms
    sent = master.now + 0.3
    reply = master.send(frames.read_request(1, 0x2620, 2))[0]
    assert reply.at == pytest.approx(sent + wire + 0.005 + 0.120)


def test_an_answer_never_comes_sooner_than_both_frames_take_on_the_wire() -> None:
    # Unpaced, the master's frames arrive at once; the answer still cannot: a slave hears
    # the whole request first, and its answer takes its own time on the line.
    bus = make_bus(S10, line={"baudrate": 9600, "parity": "E", "stopbits": 1})
    master = ClockedMaster(bus)
    sent = master.now + 0.3
    reply = master.send(frames.write_single_request(1, 0x0305, 0))[0]
    char = 11 / 9600
    assert reply.at == pytest.approx(sent + 8 * char + 0.005 + 8 * char)


def test_pacing_takes_the_line_time_of_both_frames() -> None:
    bus = make_bus(S10, line={"baudrate": 9600, "parity": "E", "stopbits": 1}, pace=True)
    master = ClockedMaster(bus)
    sent = master.now + 0.3
    reply = master.send(frames.read_request(1, 0x2620, 2))[0]
    char = 11 / 9600
    assert reply.at == pytest.approx(sent + 8 * char + 0.005 + 9 * char)


# --- tecLine / Reiss calibration history ---------------------------------------------------


def _calibrate(
    master: ClockedMaster,
    address: int,
    profile_id: str,
    *,
    zero: float,
    span: float,
    stamp: datetime,
) -> None:
    write_point(master, address, profile_id, "x_zero", zero)
    write_point(master, address, profile_id, "x_span", span)
    write_point(master, address, profile_id, "calibration_stamp", stamp)


def _history(sensor: SimulatedDevice, index: int) -> tuple[object, ...]:
    return tuple(sensor.get(f"history_{index}_{part}") for part in ("x_zero", "x_span", "stamp"))


@pytest.mark.parametrize("device", [TECLINE, REISS], ids=["tecline", "reiss"])
def test_later_date_pushes_the_history_down_and_drops_the_oldest(device: dict[str, object]) -> None:
    address, profile_id = int(device["address"]), str(device["profile"])  # type: ignore[call-overload]
    bus = make_bus(device)
    master = ClockedMaster(bus)
    for n in range(6):
        stamp = datetime(2024, 1, 1 + n, 12, 0)
        _calibrate(master, address, profile_id, zero=float(n), span=10.0 + n, stamp=stamp)
    sensor = bus.devices[address]
    assert _history(sensor, 0) == (5.0, 15.0, datetime(2024, 1, 6, 12, 0))
    assert _history(sensor, 4) == (1.0, 11.0, datetime(2024, 1, 2, 12, 0))
    assert sensor.get("x_zero") == 5.0
    assert sensor.get("calibration_stamp") == datetime(2024, 1, 6, 12, 0)


@pytest.mark.parametrize(
    "stamp", [datetime(2024, 1, 3, 12, 0), datetime(2023, 12, 1, 8, 0)], ids=["equal", "earlier"]
)
def test_equal_or_earlier_date_overwrites_entry_0_only(stamp: datetime) -> None:
    bus = make_bus(TECLINE)
    master = ClockedMaster(bus)
    for n in range(3):
        when = datetime(2024, 1, 1 + n, 12, 0)
        _calibrate(master, 20, "jumo-tecline-cl2", zero=0.0, span=20.0 + n, stamp=when)
    sensor = bus.devices[20]
    before = [_history(sensor, i) for i in range(1, 5)]
    _calibrate(master, 20, "jumo-tecline-cl2", zero=0.5, span=30.0, stamp=stamp)
    assert _history(sensor, 0) == (0.5, 30.0, stamp)
    assert [_history(sensor, i) for i in range(1, 5)] == before
    assert sensor.get("x_span") == 30.0


def test_concentration_follows_cell_current_zero_and_span() -> None:
    bus = make_bus({**TECLINE, "values": {"cell_current": 11.0}})
    master = ClockedMaster(bus)
    write_point(master, 20, "jumo-tecline-cl2", "x_zero", 1.0)
    write_point(master, 20, "jumo-tecline-cl2", "x_span", 20.0)
    assert read_point(master, 20, "jumo-tecline-cl2", "concentration") == pytest.approx(0.5)


# --- H10/H20 -------------------------------------------------------------------------------


def test_zero_point_trigger_updates_registers_and_logs_an_entry() -> None:
    bus = make_bus({**H10, "values": {"phase_shift": 37.5, "temperature": 21.0}})
    master = ClockedMaster(bus, gap_s=0.65)
    sensor = bus.devices[2]
    stamp = datetime(2025, 2, 10, 9, 15, 0, tzinfo=timezone(timedelta(minutes=60)))
    write_point(master, 2, "jumo-digiline-odo-h10", "calibration_date", stamp)
    write_point(master, 2, "jumo-digiline-odo-h10", "calibration_mode", "wet")
    write_point(master, 2, "jumo-digiline-odo-h10", "zero_point_calibration_trigger", 1.0)
    assert sensor.get("zero_point_phase") == 37.5
    assert sensor.get("zero_point_temperature") == 21.0
    assert sensor.get("calibration_mode") == codec.EnumValue(0, "as_configured")
    assert sensor.get("logbook_1_entry_type") == codec.EnumValue(20, "zero_point")
    assert sensor.get("logbook_1_date") == stamp
    assert sensor.get("logbook_1_phase") == 37.5
    assert sensor.get("logbook_1_calibration_mode") == 1.0
    # An end-value calibration becomes entry 1 and the zero point moves to entry 2.
    write_point(master, 2, "jumo-digiline-odo-h10", "end_value_oxygen", 8.5)
    write_point(master, 2, "jumo-digiline-odo-h10", "end_value_calibration_trigger", 1.0)
    assert sensor.get("logbook_1_entry_type") == codec.EnumValue(21, "end_value")
    assert sensor.get("logbook_1_oxygen") == 8.5
    assert sensor.get("end_value_phase") == 37.5
    assert sensor.get("logbook_2_entry_type") == codec.EnumValue(20, "zero_point")


def test_single_measurement_trigger() -> None:
    bus = make_bus({**H10, "values": {"measurement_interval": 0.0}})
    master = ClockedMaster(bus)
    sensor = bus.devices[2]
    counter = sensor.get("measurement_counter")
    write_point(
        master,
        2,
        "jumo-digiline-odo-h10",
        "measurement_status",
        {"single_measurement_trigger": True},
    )
    status = read_point(master, 2, "jumo-digiline-odo-h10", "measurement_status", gap_s=0.26)
    assert isinstance(status, codec.BitfieldValue)
    assert "measuring" in status.active
    assert "continuous_measurement" not in status.active
    master.now += 0.5
    status = read_point(master, 2, "jumo-digiline-odo-h10", "measurement_status")
    assert isinstance(status, codec.BitfieldValue)
    assert "measuring" not in status.active
    assert sensor.get("measurement_counter") == counter + 1  # type: ignore[operator]
    flags = sensor.get("status")
    assert isinstance(flags, codec.BitfieldValue)
    assert "new_values" in flags.active


def test_volatile_pressure_is_not_changed_inside_a_multi_value_write() -> None:
    bus = make_bus(H10)
    master = ClockedMaster(bus)
    registers = [
        *codec.float_to_registers(25.0, WordOrder.CDAB),
        *codec.float_to_registers(5.0, WordOrder.CDAB),
        *codec.float_to_registers(900.0, WordOrder.CDAB),
    ]
    master.ask(frames.write_multiple_request(2, 0x2013, registers))
    sensor = bus.devices[2]
    assert sensor.get("compensation_temperature") == 25.0
    assert sensor.get("salinity") == 5.0
    assert sensor.get("compensation_pressure") == 1013.25  # H10/H20 6.2.2


# --- S10 compensation ----------------------------------------------------------------------


def test_control_byte_chooses_flash_or_ram_compensation() -> None:
    bus = make_bus(S10)
    master = ClockedMaster(bus)
    profile = "jumo-digiline-odo-s10"
    write_point(master, 1, profile, "oxygen_unit", "ppm")
    flash_value = read_point(master, 1, profile, "oxygen")
    write_point(master, 1, profile, "compensation_salinity", 50.0)  # RAM, not yet selected
    assert read_point(master, 1, profile, "oxygen") == flash_value
    write_point(master, 1, profile, "compensation_control", {"salinity_from_ram": True})
    ram_value = read_point(master, 1, profile, "oxygen")
    assert isinstance(ram_value, float)
    assert isinstance(flash_value, float)
    assert ram_value < flash_value * 0.9  # salt lowers the solubility
    write_point(master, 1, profile, "oxygen_unit", "percent_saturation")
    saturation = read_point(master, 1, profile, "oxygen")
    assert isinstance(saturation, float)
    write_point(master, 1, profile, "compensation_pressure", 900.0)
    write_point(
        master,
        1,
        profile,
        "compensation_control",
        {"salinity_from_ram": True, "pressure_from_ram": True},
    )
    expected = saturation * 1013.25 / 900.0
    assert read_point(master, 1, profile, "oxygen") == pytest.approx(expected, rel=1e-4)


def test_fault_floats_and_status_bits_can_be_set() -> None:
    bus = make_bus({**S10, "values": {"oxygen": {"fault": "overrange"}}})
    master = ClockedMaster(bus)
    fault = read_point(master, 1, "jumo-digiline-odo-s10", "oxygen")
    assert isinstance(fault, Fault)
    assert fault.name == "overrange"
    registers = master.ask(frames.read_request(1, 0x2600, 2)).registers
    assert registers == (0xBDC2, 0x7D70)  # S10 manual 2.8.2
    bus.devices[1].set_flags("status", cap_missing=True)
    status = read_point(master, 1, "jumo-digiline-odo-s10", "status")
    assert isinstance(status, codec.BitfieldValue)
    assert status.active == ("cap_missing",)


def test_broadcast_write_is_applied_without_an_answer() -> None:
    bus = make_bus(S10, {**H10, "address": 3})
    master = ClockedMaster(bus)
    assert master.send(frames.write_single_request(0, 0x0305, 40)) == []
    assert bus.devices[1].get("min_response_time") == 40
    assert bus.devices[3].get("min_response_time") == 40
    assert bus.counters["broadcasts"] == 1


# --- the timing referee ------------------------------------------------------------------


@pytest.mark.parametrize(
    ("line", "gap_s"),
    [
        ({"baudrate": 9600, "parity": "E", "stopbits": 1}, 3.5 * 11 / 9600),
        ({"baudrate": 19200, "parity": "N", "stopbits": 1}, 0.002),
    ],
    ids=["9600-8E1", "19200-8N1-digiline-2ms"],
)
def test_request_inside_the_gap_is_ignored_and_counted(
    line: dict[str, object], gap_s: float
) -> None:
    bus = make_bus(S10, line=line)
    master = ClockedMaster(bus)
    master.ask(frames.read_request(1, 0x2620, 2))
    assert master.send(frames.read_request(1, 0x2620, 2), gap_s=gap_s * 0.9) == []
    assert bus.violations[-1].rule == "inter_frame_gap"
    assert bus.violations[-1].required_s == pytest.approx(gap_s)
    assert len(master.send(frames.read_request(1, 0x2620, 2), gap_s=gap_s * 1.01)) == 1
    assert len(bus.violations) == 1


@pytest.mark.parametrize(
    ("address", "registers", "wait_s"),
    [(0x3009, [1], 0.25), (0x2031, [0, 0x3F80], 0.65), (0x0402, [3], 0.65)],
)
def test_post_write_wait_on_h10(address: int, registers: list[int], wait_s: float) -> None:
    bus = make_bus(H10)
    master = ClockedMaster(bus)
    master.ask(frames.write_request(2, address, registers))
    assert master.send(frames.read_request(2, 0x2001, 2), gap_s=wait_s - 0.01) == []
    violation = bus.violations[-1]
    assert (violation.rule, violation.required_s) == ("post_write_wait", wait_s)
    assert len(master.send(frames.read_request(2, 0x2001, 2), gap_s=wait_s + 0.001)) == 1


def test_post_write_wait_is_per_device() -> None:
    bus = make_bus(H10, S10)
    master = ClockedMaster(bus)
    master.ask(frames.write_single_request(2, 0x3009, 1))
    assert len(master.send(frames.read_request(1, 0x2620, 2), gap_s=0.01)) == 1
    assert bus.violations == []


def test_request_while_an_answer_is_pending_is_a_collision() -> None:
    bus = make_bus(S10)
    master = ClockedMaster(bus)
    master.ask(frames.write_single_request(1, 0x0305, 300))
    master.now += 0.3
    first = bus.on_frame(frames.read_request(1, 0x2620, 2).frame, master.now)
    wire = (8 + 9) * 10 / 9600  # the request heard, the answer on the line (8N1)
    assert first[0].at == pytest.approx(master.now + wire + 0.305)
    assert bus.on_frame(frames.read_request(1, 0x2620, 2).frame, master.now + 0.1) == []
    assert bus.violations[-1].rule == "answer_in_progress"


@pytest.mark.parametrize("first_judged", [True, False])
def test_a_frame_measured_against_an_unjudged_one_is_not_judged(
    first_judged: bool,  # noqa: FBT001
) -> None:
    """The soak's case: a request held up in the kernel, then the master's next one.

    The first request waited out a stall of the simulator, so its arrival (and the end
    and answer reckoned from it) is later than on the wire; the master gave up on its
    answer and sent the next request a gap after what it saw, 3.7 ms after the end the
    referee reckons. Judged, the same bytes are an inter-frame gap violation.
    """
    line = {"baudrate": 9600, "parity": "E", "stopbits": 1}
    bus = make_bus(S10, H10, line=line, pace=True)
    first = frames.read_request(1, 0x2600, 2).frame
    replies = bus.on_frame(first, 26.1181, judged=first_judged)
    assert len(replies) == 1
    request_end = 26.1181 + bus.line.wire_s(len(first))
    second = frames.read_request(2, 0x2001, 6).frame
    outcome = bus.on_frame(second, request_end + 0.003713)
    if first_judged:
        assert outcome == []
        assert bus.violations[-1].rule == "inter_frame_gap"
        assert bus.counters["unjudged"] == 0
    else:
        assert len(outcome) == 1  # answered, as a slave would once it heard the request
        assert bus.violations == []
        assert bus.counters["unjudged"] == 2
    # Once the answers reckoned from it are on the line, frames are judged again.
    for reply in (*replies, *outcome):
        bus.on_sent(reply, reply.at)
    last = max(reply.at for reply in (*replies, *outcome))
    violations = len(bus.violations)
    assert bus.on_frame(second, last + 0.001) == []
    assert len(bus.violations) == violations + 1
    assert bus.violations[-1].rule == "inter_frame_gap"


def test_a_late_answer_colliding_with_a_request_is_the_slaves_fault() -> None:
    """A late answer that starts as the master sends collides; the master kept its gap."""
    bus = make_bus(S10, TECLINE)
    master = ClockedMaster(bus)
    master.ask(frames.read_request(1, 0x2620, 2))
    late = Reply(at=master.now + 0.2, data=b"\x14\x03\x00", kind="late", device=20)
    bus.on_sent(late, late.at)  # the master could not hear it coming
    assert bus.on_frame(frames.read_request(1, 0x2620, 2).frame, late.at + 0.0005) == []
    assert bus.counters["collisions"] == 1
    assert bus.violations == []
    # A master that heard it and still did not wait the gap is in the wrong.
    noise = Reply(at=late.at + 0.5, data=b"\xff", kind="noise", device=20)
    bus.on_sent(noise, noise.at)
    assert bus.on_frame(frames.read_request(1, 0x2620, 2).frame, noise.at + 0.0015) == []
    assert bus.violations[-1].rule == "inter_frame_gap"


# --- fault injection (the bytes; the wire tests show them over a real line) ---------------


def test_injected_faults_change_the_answer() -> None:
    bus = make_bus({**S10, "faults": {"wrong_address": 1.0}})
    reply = ClockedMaster(bus).send(frames.read_request(1, 0x2620, 2))[0]
    assert reply.data[0] == 2
    assert frames.crc_ok(reply.data)
    bus = make_bus({**S10, "faults": {"crc": 1.0}})
    reply = ClockedMaster(bus).send(frames.read_request(1, 0x2620, 2))[0]
    assert not frames.crc_ok(reply.data)
    bus = make_bus({**S10, "faults": {"drop": 1.0}})
    assert ClockedMaster(bus).send(frames.read_request(1, 0x2620, 2)) == []
    bus = make_bus({**S10, "faults": {"late": 1.0, "late_s": 0.8}})
    master = ClockedMaster(bus)
    sent = master.now + 0.3
    reply = master.send(frames.read_request(1, 0x2620, 2))[0]
    assert reply.kind == "late"
    assert reply.at == pytest.approx(sent + (8 + 9) * 10 / 9600 + 0.805)
    bus = make_bus({**S10, "faults": {"noise": 1.0}})
    noise, answer = sorted(
        ClockedMaster(bus).send(frames.read_request(1, 0x2620, 2)), key=lambda r: r.at
    )
    assert noise.kind == "noise"
    assert answer.kind == "response"
    assert bus.injected == {"noise": 1}


def test_scheduled_silence_is_a_power_cycle() -> None:
    bus = make_bus({**S10, "faults": {"silences": [[2.0, 3.0]]}})
    master = ClockedMaster(bus)
    assert len(master.send(frames.read_request(1, 0x2620, 2))) == 1
    master.now = 2.5
    assert master.send(frames.read_request(1, 0x2620, 2)) == []
    master.now = 5.0
    assert len(master.send(frames.read_request(1, 0x2620, 2))) == 1
    assert bus.counters["silent"] == 1


def test_string_reads_with_the_two_byte_count() -> None:
    bus = make_bus({**S10, "faults": {"string_byte_count_16bit": True}})
    master = ClockedMaster(bus)
    reply = master.send(frames.read_request(1, 0x0000, 5))[0]
    assert reply.data[2:4] == b"\x00\x0a"
    response = frames.parse_response(
        frames.read_request(1, 0x0000, 5), reply.data, byte_count_16bit=True
    )
    assert response.tolerated == frames.QUIRK_STRING_BYTE_COUNT
    normal = master.send(frames.read_request(1, 0x2620, 2))[0]
    assert normal.data[2] == 4


# --- bad settings --------------------------------------------------------------------------


def test_bad_settings_are_named() -> None:
    with pytest.raises(ConfigError, match=r"address 1 is already used by devices\.0"):
        make_bus(S10, {**TECLINE, "address": 1})
    with pytest.raises(ConfigError, match="unknown profile 'jumo-odo'"):
        make_bus({"profile": "jumo-odo", "address": 1})
    with pytest.raises(ConfigError, match="has no point 'oxygenn'"):
        make_bus({**S10, "values": {"oxygenn": 1.0}})
    with pytest.raises(ConfigError, match=r"devices\.0\.faults\.crc"):
        make_bus({**S10, "faults": {"crc": 2.0}})
