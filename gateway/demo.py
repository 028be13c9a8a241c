"""``gateway demo``: the whole product in one process, with nothing to install or wire.

A simulated line with one sensor of every family on a pseudo-terminal, the gateway polling
it, an MQTT broker (the one on localhost if it answers, else an embedded amqtt broker from
the ``demo`` extra), ``/metrics`` and ``/healthz``, and a live table in the terminal.
"""

from __future__ import annotations

import asyncio
import contextlib
import importlib.util
import socket
import tempfile
from pathlib import Path
from typing import TYPE_CHECKING, Any

from rich.console import Console, Group
from rich.live import Live
from rich.table import Table

from gateway.app import run
from gateway.config import parse_config
from gateway.samples import Quality
from gateway.simulator import SimulatorServer, build_bus, parse_settings
from gateway.sinks.console import format_sample
from gateway.state import GatewayState

if TYPE_CHECKING:
    from collections.abc import AsyncIterator

DEMO_SENSORS: list[dict[str, Any]] = [
    {"profile": "jumo-digiline-odo-s10", "address": 1},
    {"profile": "jumo-digiline-odo-h10", "address": 2},
    # One sensor in fault, to show a fault is published as a fault and never as 2e37.
    {
        "profile": "jumo-digiline-odo-h20",
        "address": 3,
        "values": {"oxygen": {"fault": "overrange"}},
    },
    {"profile": "jumo-tecline-cl2", "address": 20},
    {"profile": "reiss-m0c", "address": 10},
    {"profile": "reiss-m3c", "address": 30},
]
DEVICE_NAMES = {
    1: "aeration_oxygen",
    2: "digester_oxygen",
    3: "fermenter_oxygen",
    20: "pool_chlorine",
    10: "basin_chlorine",
    30: "outlet_chlorine",
}
BASE_TOPIC = "demo"
REFRESH_S = 0.5


def _listening(host: str, port: int) -> bool:
    with contextlib.suppress(OSError), socket.create_connection((host, port), timeout=0.3):
        return True
    return False


@contextlib.asynccontextmanager
async def _broker(port: int, console: Console) -> AsyncIterator[int | None]:
    """The MQTT broker to use: one on localhost, else an embedded one; None without both."""
    if _listening("127.0.0.1", port):
        console.print(f"MQTT: using the broker on 127.0.0.1:{port}")
        yield port
        return
    if importlib.util.find_spec("amqtt") is None:
        console.print(
            "MQTT: no broker on localhost and no embedded one: install the demo extra "
            "(pip install '.[demo]'); running without MQTT"
        )
        yield None
        return
    from amqtt.broker import Broker  # noqa: PLC0415 - an optional extra, loaded only here

    broker = Broker(
        {
            "listeners": {"default": {"type": "tcp", "bind": f"127.0.0.1:{port}"}},
            "plugins": {
                "amqtt.plugins.authentication.AnonymousAuthPlugin": {"allow_anonymous": True}
            },
        }
    )
    await broker.start()
    console.print(f"MQTT: embedded broker on 127.0.0.1:{port}")
    try:
        yield port
    finally:
        await broker.shutdown()


def _config(port: Path, mqtt_port: int | None, metrics_port: int, state_dir: Path) -> str:
    devices = "".join(
        f"  - {{name: {DEVICE_NAMES[d['address']]}, bus: demo, address: {d['address']}, "
        f"profile: {d['profile']}, poll_interval: 1.0}}\n"
        for d in DEMO_SENSORS
    )
    mqtt = (
        f"mqtt: {{host: 127.0.0.1, port: {mqtt_port}, base_topic: {BASE_TOPIC}}}\n"
        if mqtt_port is not None
        else "mqtt: {enabled: false}\n"
    )
    # The S10 takes its compensation temperature from the tecLine's, as a plant would.
    feeds = (
        "feeds:\n"
        "  - {device: aeration_oxygen, point: compensation_temperature, interval: 30,"
        " deadband: 0.1, source: {device: pool_chlorine, point: temperature}}\n"
    )
    return (
        f"buses:\n  - {{name: demo, port: {port}, baudrate: 19200, parity: E}}\n"
        f"devices:\n{devices}{mqtt}{feeds}"
        f"prometheus: {{host: 127.0.0.1, port: {metrics_port}}}\n"
        f"state_dir: {state_dir}\n"
    )


def _table(state: GatewayState) -> Group:
    snapshot = state.snapshot()
    values = Table(title="Values", expand=True)
    for column in ("device", "point", "value", "quality"):
        values.add_column(column, overflow="fold")
    for (_bus, device, point), sample in sorted(snapshot.latest.items()):
        if sample.group not in {"process", "status"}:
            continue
        shown = format_sample(sample).split("=", 1)[1]
        style = {Quality.GOOD: "", Quality.FAULT: "bold red"}.get(sample.quality, "yellow")
        values.add_row(
            device, point, shown, f"[{style}]{sample.quality.value}[/]" if style else "good"
        )
    health = Table(title="Bus and MQTT", expand=True)
    for column in (
        "bus",
        "requests",
        "responses",
        "errors",
        "utilisation",
        "devices online",
        "MQTT",
    ):
        health.add_column(column)
    online = sum(1 for d in snapshot.devices.values() if d.online)
    mqtt = snapshot.mqtt
    mqtt_text = (
        f"{'connected' if mqtt.connected else 'down'}, "
        f"{mqtt.published} sent, {mqtt.queue_depth} queued"
        if mqtt.enabled
        else "off"
    )
    for bus, stats in snapshot.lines.items():
        health.add_row(
            bus,
            str(sum(stats.requests.values())),
            str(sum(stats.responses.values())),
            str(sum(stats.errors.values())),
            f"{stats.utilisation():.0%}",
            f"{online}/{len(snapshot.devices)}",
            mqtt_text,
        )
    return Group(values, health)


async def run_demo(*, mqtt_port: int = 1883, metrics_port: int = 9108, live: bool = True) -> None:
    """Run the demo until SIGINT or SIGTERM."""
    console = Console(soft_wrap=True)  # commands to copy stay on one line
    with tempfile.TemporaryDirectory(prefix="gateway-demo-") as tmp:
        directory = Path(tmp)
        pty = directory / "ttyDEMO"
        line = {"baudrate": 19200, "parity": "E", "stopbits": 1}
        simulator = SimulatorServer(
            build_bus(
                parse_settings({"line": line, "pace": True, "seed": 1, "devices": DEMO_SENSORS})
            )
        )
        simulator.open_pty(pty)
        try:
            async with _broker(mqtt_port, console) as broker_port:
                config = parse_config(
                    _config(pty, broker_port, metrics_port, directory / "state"), environ={}
                )
                console.print(f"simulated line: {pty} (19200 8E1), {len(DEMO_SENSORS)} sensors")
                if broker_port is not None:
                    console.print(
                        f"watch MQTT:  mosquitto_sub -h 127.0.0.1 -p {broker_port} "
                        f"-t '{BASE_TOPIC}/#' -v"
                    )
                    console.print(
                        f"write:       mosquitto_pub -h 127.0.0.1 -p {broker_port} "
                        f"-t {BASE_TOPIC}/digester_oxygen/compensation_pressure/set -m 1003.5"
                    )
                console.print(f"metrics:     curl http://127.0.0.1:{metrics_port}/metrics")
                console.print(f"health:      curl http://127.0.0.1:{metrics_port}/healthz")
                console.print("Ctrl-C stops the demo.")
                state = GatewayState()
                gateway = asyncio.create_task(run(config, state=state), name="demo.gateway")
                if live and console.is_terminal:
                    with Live(_table(state), console=console, refresh_per_second=2) as screen:
                        while not gateway.done():
                            await asyncio.sleep(REFRESH_S)
                            screen.update(_table(state))
                await gateway
        finally:
            await simulator.close()
