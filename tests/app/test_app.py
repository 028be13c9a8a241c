"""The running gateway: several buses in parallel, each in its own task, stopped cleanly."""

from __future__ import annotations

import asyncio
import json
import socket
import urllib.request
from typing import TYPE_CHECKING

import pytest
from prometheus_client.parser import text_string_to_metric_families

from gateway.app import run
from gateway.app.tasks import TaskEndedError
from gateway.config import parse_config
from gateway.errors import ConfigError
from gateway.simulator import SimulatorServer, build_bus, parse_settings
from tests.mqtt_broker import Broker, free_port, recording
from tests.rigs import ListSink
from tests.waiting import eventually

if TYPE_CHECKING:
    from pathlib import Path

pytestmark = [pytest.mark.line]


async def test_two_buses_poll_in_parallel_one_over_tcp(tmp_path: Path) -> None:
    serial_line = SimulatorServer(
        build_bus(
            parse_settings(
                {
                    "devices": [
                        {
                            "profile": "reiss-m0c",
                            "address": 10,
                            "animate": False,
                            "values": {"concentration": 0.168},
                        }
                    ]
                }
            )
        )
    )
    tcp_line = SimulatorServer(
        build_bus(
            parse_settings(
                {
                    "line": {"baudrate": 19200},
                    "devices": [
                        {
                            "profile": "jumo-digiline-odo-s10",
                            "address": 1,
                            "animate": False,
                            "values": {"temperature": 20.25},
                        }
                    ],
                }
            )
        )
    )
    port = tmp_path / "ttyA"
    serial_line.open_pty(port)
    tcp_port = await tcp_line.open_tcp("127.0.0.1", 0)
    config = parse_config(
        f"buses:\n"
        f"  - {{name: basin, port: {port}}}\n"
        f"  - {{name: aeration, port: 'socket://127.0.0.1:{tcp_port}', baudrate: 19200}}\n"
        "devices:\n"
        "  - {name: basin_chlorine, bus: basin, address: 10, profile: reiss-m0c, poll_interval: 0.3}\n"
        "  - {name: aeration_oxygen, bus: aeration, address: 1, profile: jumo-digiline-odo-s10, poll_interval: 0.3}\n"
        "mqtt: {enabled: false}\n"
        "prometheus: {enabled: false}\n",
        environ={},
    )
    sink = ListSink()
    stop = asyncio.Event()
    task = asyncio.create_task(run(config, [sink], stop=stop))
    await eventually(
        lambda: (
            sink.good("basin_chlorine", "concentration")
            and sink.good("aeration_oxygen", "temperature")
        ),
        within_s=15,
    )
    names = {t.get_name() for t in asyncio.all_tasks()}
    stop.set()
    await asyncio.wait_for(task, timeout=6)
    await serial_line.close()
    await tcp_line.close()
    assert {"bus[basin]", "bus[aeration]"} <= names
    assert [s.value for s in sink.good("basin_chlorine", "concentration")][:1] == [0.168]
    assert [s.value for s in sink.good("aeration_oxygen", "temperature")][:1] == [20.25]
    assert {s.bus for s in sink.samples} == {"basin", "aeration"}


async def test_a_start_that_fails_half_way_stops_what_it_started(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    # The web page's port is taken: the start fails after the buses are polling. Their
    # workers stop before the ports close: no "not open; retrying" ahead of the real error,
    # and no task left behind to poll on.
    line = SimulatorServer(
        build_bus(parse_settings({"devices": [{"profile": "reiss-m0c", "address": 10}]}))
    )
    port = tmp_path / "ttyA"
    line.open_pty(port)
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        config = parse_config(
            f"buses: [{{name: basin, port: {port}}}]\n"
            "devices: [{name: basin_chlorine, bus: basin, address: 10, profile: reiss-m0c}]\n"
            "mqtt: {enabled: false}\n"
            "prometheus: {enabled: false}\n"
            f"web: {{enabled: true, port: {taken.getsockname()[1]}}}\n",
            environ={},
        )
        before = asyncio.all_tasks()
        try:
            with pytest.raises(ConfigError, match="web: cannot listen on") as info:
                await asyncio.wait_for(run(config, stop=asyncio.Event()), timeout=10)
            assert info.value.key == "web.port"
            left = {t.get_name() for t in asyncio.all_tasks() - before if not t.done()}
            assert left == set()
            assert [r.getMessage() for r in caplog.records if "retrying" in r.getMessage()] == []
        finally:
            await line.close()


# An S10 clock block (6.9: year, month ... second, time-zone offset) dated month 13.
MONTH_13 = (2025, 13, 1, 12, 0, 0, 0)
MONTH_13_HEX = ["0x07E9", "0x000D", "0x0001", "0x000C", "0x0000", "0x0000", "0x0000"]


@pytest.mark.broker
async def test_an_undecodable_value_is_a_fault_of_the_value_not_of_the_line(
    tmp_path: Path, broker: Broker
) -> None:
    """The S10 answers, but its clock says month 13: MQTT and /metrics show a fault of that
    value (``undecodable``, with its registers in the state document), never a number, and
    the device and line stay healthy."""
    sensor = {
        "profile": "jumo-digiline-odo-s10",
        "address": 1,
        "animate": False,
        "values": {"temperature": 20.25},
        "registers": {0x2840 + offset: word for offset, word in enumerate(MONTH_13)},
    }
    server = SimulatorServer(build_bus(parse_settings({"devices": [sensor]})))
    port = tmp_path / "ttySIM"
    server.open_pty(port)
    metrics_port = free_port()
    config = parse_config(
        f"buses:\n  - {{name: line1, port: {port}}}\n"
        "devices:\n"
        "  - {name: aeration, bus: line1, address: 1, profile: jumo-digiline-odo-s10,"
        " poll_interval: 0.3, points: {clock: {interval: 0.3}}}\n"
        f"mqtt: {{host: 127.0.0.1, port: {broker.port}, base_topic: gw}}\n"
        # The clock is a setting: Prometheus gets it when the group is asked for.
        f"prometheus: {{host: 127.0.0.1, port: {metrics_port}, groups: [process, configuration]}}\n"
        f"state_dir: {tmp_path / 'state'}\n",
        environ={},
    )
    stop = asyncio.Event()
    try:
        async with recording(broker.port, "gw/#") as seen:
            task = asyncio.create_task(run(config, [], stop=stop))
            await seen.wait_for("gw/aeration/temperature", "20.25")
            for _ in range(50):  # settings are first read a little after the process values
                if any("undecodable" in p for p in seen.on("gw/aeration/state")):
                    break
                await asyncio.sleep(0.1)
            metrics = await asyncio.to_thread(scrape, metrics_port)
            stop.set()
            await asyncio.wait_for(task, timeout=15)
    finally:
        await server.close()
    state = json.loads(seen.on("gw/aeration/state")[-1])
    assert state["faults"]["clock"] == "undecodable"
    assert state["quality"]["clock"] == "fault"
    assert state["raw"] == {"clock": MONTH_13_HEX}
    assert "clock" not in state["values"]
    assert state["quality"]["temperature"] == "good"
    assert set(seen.on("gw/aeration/clock")) == {""}  # cleared, never a made-up date
    assert seen.on("gw/aeration/availability")[-1] == "online"
    device = {"bus": "line1", "device": "aeration", "profile": "jumo-digiline-odo-s10"}
    faults = metrics["gateway_value_fault"]
    assert faults == [({**device, "point": "clock", "fault": "undecodable"}, 1.0)]
    assert metrics["gateway_device_online"] == [(device, 1.0)]
    assert not any(
        labels.get("point") == "clock" for labels, _ in metrics["gateway_value_age_seconds"]
    )


def scrape(port: int) -> dict[str, list[tuple[dict[str, str], float]]]:
    """``/metrics`` parsed: each sample's labels and value, by sample name."""
    with urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=5) as reply:
        text = reply.read().decode()
    samples: dict[str, list[tuple[dict[str, str], float]]] = {}
    for family in text_string_to_metric_families(text):
        for sample in family.samples:
            samples.setdefault(sample.name, []).append((dict(sample.labels), float(sample.value)))
    return samples


async def test_a_part_cancelled_from_outside_stops_the_gateway_with_its_name(
    tmp_path: Path,
) -> None:
    """A part that should run until the stop ends otherwise: the gateway stops and says
    which. (Cancelled: run() raised CancelledError out of the task's ``exception()``;
    returned: run() waited again at once on the finished task, round and round.)"""
    line = SimulatorServer(
        build_bus(parse_settings({"devices": [{"profile": "reiss-m0c", "address": 10}]}))
    )
    port = tmp_path / "ttyA"
    line.open_pty(port)
    config = parse_config(
        f"buses: [{{name: basin, port: {port}}}]\n"
        "devices: [{name: basin_chlorine, bus: basin, address: 10, profile: reiss-m0c}]\n"
        "mqtt: {enabled: false}\n"
        "prometheus: {enabled: false}\n"
        f"web: {{enabled: true, port: {free_port()}}}\n"
        f"state_dir: {tmp_path / 'state'}\n",
        environ={},
    )
    try:
        gateway = asyncio.create_task(run(config, stop=asyncio.Event()))
        page = await eventually(
            lambda: next((t for t in asyncio.all_tasks() if t.get_name() == "web"), None),
            within_s=10,
        )
        page.cancel()
        with pytest.raises(TaskEndedError, match="web was cancelled while the gateway ran"):
            await asyncio.wait_for(gateway, timeout=10)
    finally:
        await line.close()
