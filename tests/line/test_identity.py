"""Pinned serial numbers: the config check, and the bus worker against the simulator.

A swapped USB adapter is simulated the way it looks on the wire: the sensor at the
configured address answers with another serial number. The worker runs against the real
simulator over a pseudo-terminal; what reached the sinks is asserted, value by value.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import logging
from typing import TYPE_CHECKING, Any

import pytest

from gateway.app import device_target
from gateway.config import ConfigProblems, parse_config
from gateway.config import checks as config_checks
from gateway.errors import CommandRejectedError
from gateway.line.samples import Quality
from gateway.profiles import builtin_profiles, get_profile
from gateway.profiles.serial_number import PinnedSerial, pinned_serial
from gateway.wire import codec
from tests.rigs import rig, target

if TYPE_CHECKING:
    from pathlib import Path

    from gateway.config.problems import Problem
    from gateway.line.engine.devices import DeviceTarget

S10 = "jumo-digiline-odo-s10"
H10 = "jumo-digiline-odo-h10"
CL2 = "jumo-tecline-cl2"
S10_SERIAL = "S100000001"  # what the simulated S10 at address 1 reports
OTHER_SERIAL = "S109999999"  # the sensor of the other line, behind the swapped adapter
SERIAL_READ = (0x0100, 10)  # digiLine serial number: address, registers


def config_text(device: str) -> str:
    """A config of one bus and the device entry given (YAML, indented as an item)."""
    return (
        "buses:\n"
        "  - name: line1\n"
        "    port: /dev/serial/by-id/usb-FTDI_FT232R_USB_UART_A10K1234-if00-port0\n"
        "devices:\n"
        "  - name: tank1_oxygen\n"
        "    bus: line1\n"
        "    address: 1\n"
        f"    profile: {S10}\n" + device + "mqtt: {enabled: false}\n"
    )


def problems(text: str) -> list[Problem]:
    with pytest.raises(ConfigProblems) as caught:
        parse_config(text, environ={})
    return caught.value.problems


# --- the config ----------------------------------------------------------------------------


def test_a_pinned_serial_number_loads_as_text_or_as_a_whole_number() -> None:
    config = parse_config(config_text(f'    serial_number: "{S10_SERIAL}"\n'), environ={})
    device = config.devices[0]
    assert device.serial_number == S10_SERIAL
    pinned = device_target(device, config.buses[0]).serial_number
    assert pinned is not None
    assert pinned.matches(S10_SERIAL)
    assert pinned.matches(f"  {S10_SERIAL}  ")  # padding is not part of a serial
    assert not pinned.matches(OTHER_SERIAL)
    assert not pinned.matches(S10_SERIAL.lower())

    numeric = parse_config(config_text("    serial_number: 12345678\n"), environ={})
    assert numeric.devices[0].serial_number == 12345678
    pinned = device_target(numeric.devices[0], numeric.buses[0]).serial_number
    assert pinned is not None
    assert pinned.matches("12345678")
    assert not pinned.matches("12345679")
    assert str(pinned) == "12345678"


def test_an_unquoted_serial_yaml_reads_as_octal_still_matches_its_digits() -> None:
    # The simulated tecLine serial at address 201: only the digits 0-7, after a 0.
    serial = "0104714601000000201"
    config = parse_config(config_text(f"    serial_number: {serial}\n"), environ={})
    configured = config.devices[0].serial_number
    assert configured == int(serial, 8)  # what YAML made of it
    pinned = pinned_serial(get_profile(CL2), configured)
    assert pinned is not None
    assert pinned.matches(serial)
    assert not pinned.matches("0104714601000000202")
    assert not pinned.matches(str(int(serial, 8)) + "x")


@pytest.mark.parametrize(
    ("value", "message"),
    [
        ("1.10", "YAML reads this as the number 1.1 (digits lost), not a serial number"),
        ("yes", "YAML reads this as the boolean true (as it does yes, no, on, off)"),
        ('""', "an empty serial number pins nothing: give the serial number, or leave"),
        ("[S1, S2]", "['S1', 'S2'] is a list, not a serial number: write it in quotes"),
        ("-5", "-5 is negative"),
    ],
)
def test_a_serial_number_of_the_wrong_type_is_refused_with_key_and_line(
    value: str, message: str
) -> None:
    found = problems(config_text(f"    serial_number: {value}\n"))
    assert [(p.key, p.line) for p in found] == [("devices[0].serial_number", 9)]
    assert message in found[0].message


def test_a_serial_number_point_switched_off_is_refused() -> None:
    found = problems(
        config_text(
            f"    serial_number: {S10_SERIAL}\n    points:\n      serial_number: {{enabled: false}}\n"
        )
    )
    assert [(p.key, p.line) for p in found] == [("devices[0].serial_number", 9)]
    assert "points.serial_number.enabled is false, so it is never read" in found[0].message


@pytest.fixture
def profile_without_serial(monkeypatch: pytest.MonkeyPatch) -> str:
    """The built-in profiles plus an S10 whose map reads no serial number."""
    s10 = get_profile(S10)
    bare = dataclasses.replace(
        s10,
        id="test-s10-without-serial",
        points=tuple(p for p in s10.points if p.name != "serial_number"),
    )
    profiles = {**builtin_profiles(), bare.id: bare}
    monkeypatch.setattr(config_checks, "builtin_profiles", lambda: profiles)
    return bare.id


def test_a_profile_without_a_serial_number_point_is_refused(profile_without_serial: str) -> None:
    text = config_text(f"    serial_number: {S10_SERIAL}\n").replace(S10, profile_without_serial)
    found = problems(text)
    assert [(p.key, p.line) for p in found] == [("devices[0].serial_number", 9)]
    assert found[0].message == (
        f"profile {profile_without_serial} has no serial_number point, so the serial number "
        "cannot be checked; remove serial_number from this device"
    )
    # Unpinned, the same profile is fine.
    parse_config(text.replace(f"    serial_number: {S10_SERIAL}\n", ""), environ={})


def test_text_pinned_to_a_number_point_is_refused() -> None:
    point = dataclasses.replace(get_profile(S10).point("hardware_address"), name="serial_number")
    assert point.format.dtype is codec.DataType.UINT32
    with pytest.raises(ValueError, match="'S1901' is not a whole number, and serial_number is a"):
        PinnedSerial.for_point(point, "S1901")
    pinned = PinnedSerial.for_point(point, "1903081310")
    assert pinned.matches(1903081310)  # compared as the decoded uint32 is: a number
    assert not pinned.matches(1903081311)


# --- the bus worker ------------------------------------------------------------------------


def pinned(name: str, profile_id: str, address: int, serial: str, **options: Any) -> DeviceTarget:
    profile = get_profile(profile_id)
    return target(
        name, profile_id, address, serial_number=pinned_serial(profile, serial), **options
    )


def identity_records(caplog: pytest.LogCaptureFixture) -> list[logging.LogRecord]:
    return [r for r in caplog.records if r.name == "gateway.line.engine.identity_guard"]


@pytest.mark.line
async def test_the_pinned_serial_answering_publishes_as_before(tmp_path: Path) -> None:
    devices = [{"profile": S10, "address": 1, "animate": False, "values": {"temperature": 20.25}}]
    targets = [pinned("s10", S10, 1, S10_SERIAL, interval=0.2)]
    async with rig(tmp_path, devices, targets) as r:
        await r.run_for(1.5)
        health = r.worker.health()
    assert [s.value for s in r.sink.good("s10", "serial_number")] == [S10_SERIAL]
    temperatures = r.sink.good("s10", "temperature")
    assert len(temperatures) >= 3
    assert {s.value for s in temperatures} == {20.25}
    assert [(e.online, e.reason) for e in r.sink.events] == [(True, "answered")]
    assert (health[0].identity, health[0].expected_serial, health[0].answered_serial) == (
        "confirmed",
        S10_SERIAL,
        S10_SERIAL,
    )


@pytest.mark.line
async def test_another_serial_publishes_nothing_until_the_pinned_one_answers(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.DEBUG, logger="gateway.line.engine.identity_guard")
    devices = [
        {
            "profile": S10,
            "address": 1,
            "animate": False,
            "values": {"serial_number": OTHER_SERIAL, "temperature": 20.25},
        },
        {"profile": CL2, "address": 20, "animate": False},
    ]
    targets = [
        pinned("s10", S10, 1, S10_SERIAL, interval=0.2, probe_max_s=0.5),
        target("cl2", CL2, 20, interval=0.2),  # unpinned: as today
    ]
    async with rig(tmp_path, devices, targets) as r:
        task = asyncio.create_task(r.worker.run())
        try:
            await asyncio.sleep(2.0)
            # Nothing of the S10 reached the sinks: no values, no "online"; one "offline"
            # that says why. The unpinned tecLine is published as always.
            assert [s for s in r.sink.samples if s.device == "s10"] == []
            s10_events = [(e.online, e.reason) for e in r.sink.events if e.device == "s10"]
            assert s10_events == [
                (
                    False,
                    (
                        f"not the configured sensor: serial number {OTHER_SERIAL} answered, "
                        f"{S10_SERIAL} is pinned"
                    ),
                )
            ]
            assert r.sink.good("cl2", "concentration")
            health = {h.device: h for h in r.worker.health()}
            assert (health["s10"].identity, health["s10"].online) == ("mismatch", False)
            assert health["s10"].answered_serial == OTHER_SERIAL
            assert health["cl2"].identity == "unpinned"

            # One ERROR for the streak, with both serials and the remedy; repeats at DEBUG.
            errors = [r for r in identity_records(caplog) if r.levelno == logging.ERROR]
            assert len(errors) == 1
            assert errors[0].getMessage() == (
                f"line1/s10 (address 1): serial number {OTHER_SERIAL} answered, but "
                f"serial_number pins {S10_SERIAL}: another sensor answers at this address, so "
                "nothing is published for it and nothing written to it. If the USB adapters "
                "swapped after a reboot, give each bus its /dev/serial/by-id/... name as port "
                "(ls -l /dev/serial/by-id); if the sensor was replaced, set serial_number: "
                f'"{OTHER_SERIAL}". Checking again on the probe backoff'
            )
            rechecks = [
                r
                for r in identity_records(caplog)
                if r.levelno == logging.DEBUG and OTHER_SERIAL in r.getMessage()
            ]
            assert rechecks  # checked again, quietly

            # Held: the only requests to the S10 read its serial number.
            held_since = r.server.bus.frame_log[-1].start
            await asyncio.sleep(1.0)
            to_s10 = [
                (f.address, f.quantity)
                for f in r.frames()
                if f.device == 1 and f.start > held_since
            ]
            assert to_s10
            assert set(to_s10) == {SERIAL_READ}

            # Nor is it written to or read by commands: refused before the bus.
            refused = (
                f"s10 is not the configured sensor: serial number {OTHER_SERIAL} answers, "
                f"{S10_SERIAL} is pinned; nothing is read from it or written to it"
            )
            profile = r.worker.device_profile("s10")
            with pytest.raises(CommandRejectedError) as caught:
                await r.worker.write_registers("s10", profile.point("tag_number"), (0x4142, 0))
            assert str(caught.value) == refused
            with pytest.raises(CommandRejectedError):
                await r.worker.read_points("s10", [profile.point("temperature")])
            assert list(r.server.bus.devices[1].write_log) == []

            # The adapter swapped back: the pinned sensor answers again.
            caplog.clear()
            r.server.bus.devices[1].hold("serial_number", S10_SERIAL)
            await asyncio.sleep(2.0)
        finally:
            r.worker.request_stop()
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task
    infos = [r.getMessage() for r in identity_records(caplog) if r.levelno == logging.INFO]
    assert infos == [
        (
            f"line1/s10 (address 1): serial number {S10_SERIAL} answers again: it is the "
            "configured sensor; polling and publishing it again"
        )
    ]
    assert not [r for r in identity_records(caplog) if r.levelno >= logging.WARNING]
    s10_events = [(e.online, e.reason) for e in r.sink.events if e.device == "s10"]
    assert s10_events[-1] == (True, f"serial number {S10_SERIAL} confirmed")
    assert {s.value for s in r.sink.good("s10", "temperature")} == {20.25}
    assert [s.value for s in r.sink.good("s10", "serial_number")] == [S10_SERIAL]
    assert r.worker.health()[0].identity == "confirmed"


@pytest.mark.line
async def test_an_unread_identity_publishes_nothing_until_it_is_confirmed(tmp_path: Path) -> None:
    # Both sensors silent for the first second and a half: no identity can be read. (A
    # timeout of 0.1 s: without one, the first read of a digiLine waits the longest
    # minimum response time it may have, 500 ms, and fewer retries fit in the silence.)
    silent = {"animate": False, "faults": {"silences": [(0.0, 1.5)]}}
    devices = [
        {"profile": S10, "address": 1, **silent},
        {"profile": H10, "address": 2, **silent},
    ]
    targets = [
        pinned("s10", S10, 1, S10_SERIAL, interval=0.2, probe_max_s=0.5, timeout_s=0.1),
        target("h10", H10, 2, interval=0.2, probe_max_s=0.5, timeout_s=0.1),  # unpinned
    ]
    async with rig(tmp_path, devices, targets, late_answer_window_s=0.1) as r:
        await r.run_for(5.0)
    s10 = [s for s in r.sink.samples if s.device == "s10"]
    h10 = [s for s in r.sink.samples if s.device == "h10"]
    # Unpinned: its comms errors are published, as always. Pinned: nothing before its
    # serial number is read, and the first cycle published is the one that read it.
    assert any(s.quality is Quality.COMMS_ERROR for s in h10)
    assert s10
    assert all(s.quality is not Quality.COMMS_ERROR for s in s10)
    first_serial = next(i for i, s in enumerate(s10) if s.point == "serial_number")
    assert s10[first_serial].value == S10_SERIAL
    # Its own read's block, and the sensor's minimum response time read first of all.
    before = s10[:first_serial]
    assert {s.point for s in before if s.group != "identity"} <= {"min_response_time"}
    s10_events = [e.online for e in r.sink.events if e.device == "s10"]
    assert s10_events[-1] is True
    assert r.worker.health()[0].identity == "confirmed"


@pytest.mark.line
async def test_adapters_swapped_at_a_replug_are_caught_at_the_reconnection(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    devices = [{"profile": S10, "address": 1, "animate": False, "values": {"temperature": 20.25}}]
    targets = [pinned("s10", S10, 1, S10_SERIAL, interval=0.2, probe_max_s=0.5)]
    async with rig(tmp_path, devices, targets) as r:
        task = asyncio.create_task(r.worker.run())
        try:
            await asyncio.sleep(1.0)
            assert r.sink.good("s10", "temperature")
            # Unplugged; what comes back at the same path is the other line's adapter, whose
            # S10 has the same address and format.
            r.server.unplug_pty()
            await asyncio.sleep(1.0)
            r.server.bus.devices[1].hold("serial_number", OTHER_SERIAL)
            r.server.bus.devices[1].hold("temperature", 11.5)
            back = asyncio.get_running_loop().time()
            r.server.replug_pty()
            await asyncio.sleep(2.5)
        finally:
            r.worker.request_stop()
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task
    assert r.line.stats.port_failures >= 1
    # The other sensor's temperature never reached a sink under this device's name.
    assert {s.value for s in r.sink.good("s10", "temperature")} == {20.25}
    assert not [s for s in r.sink.samples if s.device == "s10" and s.monotonic > back]
    events = [(e.online, e.reason) for e in r.sink.events if e.device == "s10"]
    assert events[0] == (True, "answered")
    assert events[-1] == (
        False,
        f"not the configured sensor: serial number {OTHER_SERIAL} answered, {S10_SERIAL} is pinned",
    )
    assert [e for e in events[1:] if e[0]] == []  # never "online" again
    errors = [r.getMessage() for r in identity_records(caplog) if r.levelno == logging.ERROR]
    assert len(errors) == 1
    assert (
        f"serial number {OTHER_SERIAL} answered, but serial_number pins {S10_SERIAL}" in (errors[0])
    )
    assert r.worker.health()[0].identity == "mismatch"


@pytest.mark.line
async def test_a_serial_number_the_sensor_refuses_holds_the_device(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    # This unit answers everything but its serial number (exception 02 at 0x0100).
    devices = [{"profile": S10, "address": 1, "animate": False, "unmapped": [0x0100]}]
    targets = [pinned("s10", S10, 1, S10_SERIAL, interval=0.2, probe_max_s=0.5)]
    async with rig(tmp_path, devices, targets) as r:

        def serial_reads() -> list[Any]:
            return [
                f for f in r.frames() if f.device == 1 and (f.address, f.quantity) == SERIAL_READ
            ]

        # Until the serial was asked three times: a fixed two seconds of running was not
        # enough on a loaded machine, where the first read came 1.5 s after the start.
        await r.run_until(lambda: len(serial_reads()) >= 3, within_s=15)
        health = r.worker.health()[0]
    assert [s for s in r.sink.samples if s.device == "s10"] == []
    assert [(e.online, e.reason) for e in r.sink.events] == [
        (
            False,
            "identity not confirmed: its serial number could not be read (exception_02)",
        )
    ]
    assert (health.identity, health.online, health.answered_serial) == (
        "unread",
        False,
        "exception_02",
    )
    errors = [r.getMessage() for r in identity_records(caplog) if r.levelno == logging.ERROR]
    assert errors == [
        (
            "line1/s10 (address 1): its serial number could not be read (exception_02), so "
            "it cannot be told from another sensor: nothing is published for it until "
            f"serial number {S10_SERIAL} is read; check the profile and the device. "
            "Checking again on the probe backoff"
        )
    ]
    # Still checked on the backoff (0.2 s, then 0.4 s, then at most 0.5 s, each jittered by
    # 20 %): the serial alone, three times within two seconds of the first.
    first, _, third = serial_reads()[:3]
    assert third.start - first.start <= 2.0
