"""A simulated sensor on a real line: what it reports about itself matches how it is served."""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING, Any

import pytest

from gateway.control.link import open_link
from gateway.line.engine.devices import DeviceTarget
from gateway.profiles import get_profile
from gateway.simulator import SimulatorServer, build_bus, parse_settings
from gateway.wire.codec import EnumValue
from gateway.wire.timing import LineFormat
from tests.simulator.helpers import make_bus

if TYPE_CHECKING:
    from pathlib import Path

    from gateway.wire.codec import Decoded

# Every family with line-setting registers, at addresses other than their factory ones
# (Reiss M0c 10, M3c 20: reiss-m0c-m3c 2.3), so the address register cannot pass by chance.
DEVICES: dict[int, str] = {
    1: "jumo-digiline-odo-s10",
    2: "jumo-digiline-odo-h10",
    3: "jumo-digiline-odo-h20",
    21: "jumo-tecline-cl2",
    11: "reiss-m0c",
    31: "reiss-m3c",
}
# The interface registers: digiLine 0x0300-0x0302 (S10 6.4, H10 6.1.4), tecLine and Reiss
# 0x0400-0x0402 ("Device data Modbus").
LINE_POINTS: dict[str, tuple[str, str, str]] = {
    "jumo-digiline": ("device_address", "baud_rate", "data_format"),
    "jumo-tecline": ("modbus_address", "baud_rate", "parity_stop_bits"),
    "reiss": ("modbus_address", "baud_rate", "parity_stop_bits"),
}


def line_points(profile_id: str) -> tuple[str, str, str]:
    (points,) = [p for prefix, p in LINE_POINTS.items() if profile_id.startswith(prefix)]
    return points


async def read_line_settings(port: str, line: LineFormat, address: int) -> dict[str, Decoded]:
    """The three points, read as ``gateway read`` reads them (its link and worker)."""
    profile = get_profile(DEVICES[address])
    target = DeviceTarget(
        name=f"address_{address}",
        address=address,
        profile=profile,
        intervals=dict.fromkeys(line_points(profile.id)),
    )
    async with open_link(port, line, target) as link:
        samples = await link.worker.read_once(target.name)
    assert all(s.good for s in samples), samples
    return {s.point: s.value for s in samples}


def labels(values: dict[str, Decoded], profile_id: str) -> tuple[object, str, str]:
    address, baud, framing = (values[name] for name in line_points(profile_id))
    assert isinstance(baud, EnumValue)
    assert isinstance(framing, EnumValue)
    return address, baud.label, framing.label


def simulator(line: dict[str, Any]) -> SimulatorServer:
    devices = [{"profile": p, "address": a, "animate": False} for a, p in DEVICES.items()]
    return SimulatorServer(build_bus(parse_settings({"line": line, "devices": devices})))


@pytest.mark.parametrize("address", sorted(DEVICES))
@pytest.mark.line
async def test_a_sensor_reports_the_line_it_is_served_on(tmp_path: Path, address: int) -> None:
    line = LineFormat(baudrate=19200, parity="E", stopbits=1)
    server = simulator({"baudrate": 19200, "parity": "E", "stopbits": 1})
    try:
        server.open_pty(tmp_path / "ttySIM")
        values = await read_line_settings(str(tmp_path / "ttySIM"), line, address)
    finally:
        await server.close()
    assert labels(values, DEVICES[address]) == (address, "baud_19200", "8e1")


@pytest.mark.line
async def test_over_tcp_a_sensor_reports_the_line_format_it_was_given() -> None:
    # RTU over TCP has no baud rate: the sensor stands behind a converter set to this line.
    address = 31  # Reiss M3c, whose factory line is 9600 8N2 (2.3.2)
    server = simulator({"baudrate": 38400, "parity": "N", "stopbits": 1})
    try:
        port = await server.open_tcp("127.0.0.1", 0)
        values = await read_line_settings(f"socket://127.0.0.1:{port}", LineFormat(), address)
    finally:
        await server.close()
    assert labels(values, DEVICES[address]) == (address, "baud_38400", "8n1")


def test_a_line_the_sensor_cannot_be_set_to_is_reported_not_invented(
    caplog: pytest.LogCaptureFixture,
) -> None:
    # digiLine 0x0301 knows 9600, 19200 and 38400 Bd only (S10 6.4): tests run faster lines.
    # Said as a warning once a profile, then quietly (another test may have made it first).
    caplog.set_level(logging.DEBUG, logger="gateway.simulator.line_settings")
    line = {"baudrate": 115200, "parity": "E", "stopbits": 1}
    bus = make_bus({"profile": "jumo-digiline-odo-s10", "address": 1}, line=line)
    baud, framing = bus.devices[1].get("baud_rate"), bus.devices[1].get("data_format")
    assert isinstance(baud, EnumValue)
    assert isinstance(framing, EnumValue)
    assert (baud.label, framing.label) == ("baud_9600", "8e1")  # the register as it was
    assert "baud_rate has no code for baud_115200" in caplog.text
