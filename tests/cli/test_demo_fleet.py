"""``gateway demo --fleet N``: N gateways of their own into one broker, all stopped by Ctrl-C."""

from __future__ import annotations

import asyncio
import json
import re
import signal
import socket
import sys
from pathlib import Path

import aiomqtt
import pytest

from gateway.cli.demo import Listen
from gateway.cli.demo_fleet import Cabinet, cabinet_config, plan
from gateway.config import parse_config
from gateway.errors import ConfigError
from tests.cli.test_demo import get_when_up, read_banner
from tests.mqtt_broker import free_port

FLEET = 3
# A row of the fleet's table: cabinet, pid, metrics URL, base topic (then the page's URL).
ROW = re.compile(r"^(cabinet-\d+)\s+(\d+)\s+(http://\S+/metrics)\s+(\S+)", re.MULTILINE)


def free_ports(count: int) -> int:
    """The first of ``count`` consecutive ports on 127.0.0.1, each free a moment ago."""
    while True:
        first = free_port()
        try:
            for port in range(first + 1, first + count):
                with socket.socket() as probe:
                    probe.bind(("127.0.0.1", port))
        except OSError:
            continue
        return first


def start_time(pid: int) -> str | None:
    """A process's start time (clock ticks after boot) while it runs; None once it is gone.

    With the pid, it names one process: a pid the kernel hands out again has another.
    """
    try:
        stat = Path(f"/proc/{pid}/stat").read_text(encoding="ascii")
    except FileNotFoundError:
        return None
    fields = stat.rsplit(")", 1)[1].split()
    return None if fields[0] == "Z" else fields[19]  # state, starttime (fields 3 and 22)


def parent(pid: int) -> int:
    return int(Path(f"/proc/{pid}/stat").read_text(encoding="ascii").rsplit(")", 1)[1].split()[1])


@pytest.mark.line
@pytest.mark.broker
async def test_a_fleet_of_three_publishes_under_three_topics_and_stops_on_ctrl_c() -> None:
    mqtt_port, metrics_port, web_port = free_port(), free_ports(FLEET), free_ports(FLEET)
    process = await asyncio.create_subprocess_exec(
        sys.executable,
        "-m",
        "gateway",
        "demo",
        "--fleet",
        str(FLEET),
        "--mqtt-port",
        str(mqtt_port),
        "--metrics-port",
        str(metrics_port),
        "--web-port",
        str(web_port),
        "--modbus-port",
        "0",
        "--no-live",
        stdout=asyncio.subprocess.PIPE,
        stderr=asyncio.subprocess.PIPE,
    )
    children: dict[int, str | None] = {}
    try:
        banner = await read_banner(process, within_s=60)
        rows = ROW.findall(banner)
        assert [name for name, *_ in rows] == ["cabinet-01", "cabinet-02", "cabinet-03"]
        assert f"mosquitto_sub -h 127.0.0.1 -p {mqtt_port} -t 'demo/+/+/state' -v" in banner
        # Each gateway a process of its own, a child of the demo.
        children = {int(pid): start_time(int(pid)) for _, pid, _, _ in rows}
        assert len(children) == FLEET
        assert all(parent(pid) == process.pid for pid in children)
        urls = [url for _, _, url, _ in rows]
        topics = [topic for *_, topic in rows]
        assert urls == [f"http://127.0.0.1:{metrics_port + i}/metrics" for i in range(FLEET)]
        assert topics == [f"demo/cabinet-0{i}" for i in range(1, FLEET + 1)]

        # Every cabinet's value documents, under its own base topic, on the one broker.
        seen: dict[str, dict[str, object]] = {}
        async with aiomqtt.Client("127.0.0.1", mqtt_port) as client:
            await client.subscribe("demo/+/+/state", qos=1)

            async def collect() -> None:
                async for message in client.messages:
                    base = str(message.topic).rsplit("/", 2)[0]
                    assert isinstance(message.payload, bytes)
                    seen[base] = json.loads(message.payload)
                    if set(seen) == set(topics):
                        return

            await asyncio.wait_for(collect(), timeout=60)
        assert all("time" in document for document in seen.values())

        # Every cabinet's /metrics answers, each its own gateway's, and each its page.
        for i, url in enumerate(urls):
            metrics = await get_when_up(url, timeout_s=30, process=process)
            assert 'gateway_temperature_celsius{bus="demo",device="aeration_oxygen"' in metrics
            page = await get_when_up(f"http://127.0.0.1:{web_port + i}/", process=process)
            assert '<script src="/static/app.js" defer></script>' in page
    finally:
        if process.returncode is None:
            process.send_signal(signal.SIGINT)
        _, err = await asyncio.wait_for(process.communicate(), timeout=60)
    assert process.returncode == 0, err.decode()
    # Not one gateway left behind: each ended (and was reaped) with the demo.
    assert children
    assert all(start_time(pid) != started for pid, started in children.items())


def test_each_cabinet_has_its_own_identity_and_ports(tmp_path: Path) -> None:
    cabinets = plan(3, metrics_port=9108, web_port=8080, modbus_port=0)
    assert [c.metrics_port for c in cabinets] == [9108, 9109, 9110]
    assert [c.web_port for c in cabinets] == [8080, 8081, 8082]
    assert [c.modbus_port for c in cabinets] == [0, 0, 0]
    config = parse_config(
        cabinet_config(
            cabinets[1],
            pty=tmp_path / "ttyDEMO",
            broker_port=1883,
            listen=Listen.parse("127.0.0.1"),
            state_dir=tmp_path / "state",
            password="secret-for-the-test",  # noqa: S106 - a test's page, never served
        ),
        environ={},
    )
    assert (config.mqtt.base_topic, config.mqtt.client_id) == (
        "demo/cabinet-02",
        "gateway-demo-cabinet-02",
    )
    assert (config.prometheus.port, config.web.port) == (9109, 8081)


@pytest.mark.parametrize(
    ("size", "ports", "problem"),
    [
        (0, (9108, 8080, 1502), "from 1 to 50"),
        (3, (9108, 9109, 0), "overlap"),
        (2, (65535, 8080, 0), "beyond 65535"),
    ],
)
def test_a_fleet_that_cannot_be_is_refused_before_it_starts(
    size: int, ports: tuple[int, int, int], problem: str
) -> None:
    metrics, web, modbus = ports
    with pytest.raises(ConfigError, match=problem):
        plan(size, metrics_port=metrics, web_port=web, modbus_port=modbus)


def test_a_cabinet_without_a_page_or_shared_bus_listens_on_metrics_only() -> None:
    cabinet = Cabinet.number(2, metrics_port=9108, web_port=0, modbus_port=0)
    assert cabinet.ports() == [9109]
