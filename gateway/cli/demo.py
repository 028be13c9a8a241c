"""``gateway demo``: the whole product in one process, with nothing to install or wire.

A simulated line with one sensor of every family on a pseudo-terminal, the gateway polling
it, an MQTT broker (the one on localhost if it answers, else an embedded amqtt broker from
the ``demo`` extra), ``/metrics`` and ``/healthz``, the web page (its password printed),
and a live table in the terminal.

What the demo serves listens on 127.0.0.1 unless ``bind`` says otherwise: in a container,
``-p 9108:9108`` reaches only what listens on the container's own interface.

Everything printed goes through rich, whose markup would take ``[demo]`` in
``pip install '.[demo]'`` for a style tag and print nothing: text and values are printed
without markup, and only the table's own styles are markup.
"""

from __future__ import annotations

import asyncio
import contextlib
import importlib.util
import ipaddress
import json
import os
import re
import secrets
import socket
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from rich.console import Console, Group
from rich.markup import escape
from rich.table import Table

from gateway.app import run
from gateway.config import parse_config
from gateway.errors import ConfigError
from gateway.line.samples import Quality
from gateway.publish.console import ConsoleSink, format_sample
from gateway.shared.state import GatewayState
from gateway.wire.timing import LineFormat

if TYPE_CHECKING:
    from collections.abc import AsyncIterator

# Every sensor has a past (the simulator's ``aging``, as in config/simulator-plant.yaml):
# eight weeks in service, calibrated two days ago. One of each kind needs care: the S10
# recommends a new cap, the H10 has used 90 % of its cap's measurements, the tecLine cell
# is overdue for calibration with its slope at 44 % of nominal and falling.
_HEALTHY_OXYGEN: dict[str, Any] = {
    "weeks_in_service": 8,
    "last_calibration_days": 2,
    "measurements_per_week": 20000,
}
_HEALTHY_CELL: dict[str, Any] = {
    "weeks_in_service": 8,
    "last_calibration_days": 2,
    "slope_decay_per_week": 0.01,
}
DEMO_SENSORS: list[dict[str, Any]] = [
    {
        "profile": "jumo-digiline-odo-s10",
        "address": 1,
        "aging": {**_HEALTHY_OXYGEN, "cap_replacement_recommended": True},
    },
    {
        "profile": "jumo-digiline-odo-h10",
        "address": 2,
        "aging": {**_HEALTHY_OXYGEN, "measurements_per_week": 112500},
    },
    # One sensor in fault, to show a fault is published as a fault and never as 2e37.
    {
        "profile": "jumo-digiline-odo-h20",
        "address": 3,
        "values": {"oxygen": {"fault": "overrange"}},
        "aging": _HEALTHY_OXYGEN,
    },
    {
        "profile": "jumo-tecline-cl2",
        "address": 20,
        "aging": {
            "weeks_in_service": 8,
            "calibration_interval_days": 7,
            "last_calibration_days": 9,
            "slope_start": 0.8,
            "slope_decay_per_week": 0.06,
        },
    },
    {"profile": "reiss-m0c", "address": 10, "aging": _HEALTHY_CELL},
    {"profile": "reiss-m3c", "address": 30, "aging": _HEALTHY_CELL},
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
DEMO_LINE = LineFormat(baudrate=19200, parity="E", stopbits=1)
LOCAL_BIND = "127.0.0.1"  # the default: nothing of the demo is reachable from elsewhere
INSTALL_HINT = (
    "MQTT: no broker on localhost and no embedded one: install the demo extra "
    "(pip install '.[demo]'); running without MQTT"
)


@dataclass(frozen=True, slots=True)
class Listen:
    """Where the demo's metrics and embedded broker listen, and where local clients find them.

    Example::

        Listen.parse("0.0.0.0")  # every interface; the gateway and hints use 127.0.0.1
    """

    bind: ipaddress.IPv4Address | ipaddress.IPv6Address

    @classmethod
    def parse(cls, text: str) -> Listen:
        """An IP address of this machine, or ``0.0.0.0``/``::`` for every interface."""
        try:
            return cls(ipaddress.ip_address(text))
        except ValueError as exc:
            raise ConfigError(
                f"--bind {text!r}: expected an IP address, e.g. 0.0.0.0 for every interface"
            ) from exc

    @property
    def host(self) -> str:
        """The address to listen on, as a socket takes it."""
        return str(self.bind)

    @property
    def client_host(self) -> str:
        """Where a client on this machine connects: loopback for every interface."""
        if self.bind.is_unspecified:
            return "::1" if isinstance(self.bind, ipaddress.IPv6Address) else "127.0.0.1"
        return str(self.bind)

    @staticmethod
    def in_url(host: str) -> str:
        """A host as URLs write it (IPv6 in brackets)."""
        return f"[{host}]" if ":" in host else host


def _say(console: Console, text: str) -> None:
    """Print plain text: paths, addresses and commands are never rich markup."""
    console.print(text, markup=False, highlight=False)


def _listening(host: str, port: int) -> bool:
    with contextlib.suppress(OSError), socket.create_connection((host, port), timeout=0.3):
        return True
    return False


@contextlib.asynccontextmanager
async def _broker(port: int, listen: Listen, console: Console) -> AsyncIterator[int | None]:
    """The MQTT broker to use: one on localhost, else an embedded one; None without both."""
    local = listen.client_host
    if _listening(local, port):
        _say(console, f"MQTT: using the broker on {Listen.in_url(local)}:{port}")
        yield port
        return
    if importlib.util.find_spec("amqtt") is None:
        _say(console, INSTALL_HINT)
        yield None
        return
    # An optional extra, loaded only here.
    from amqtt.broker import Broker  # noqa: PLC0415
    from amqtt.errors import BrokerError  # noqa: PLC0415

    broker = Broker(
        {
            # HOST:PORT without brackets for IPv6: amqtt splits at the last colon, and keeps
            # the brackets of ``[::]:1883`` in the address it resolves (amqtt 0.12).
            "listeners": {"default": {"type": "tcp", "bind": f"{listen.host}:{port}"}},
            "plugins": {
                "amqtt.plugins.authentication.AnonymousAuthPlugin": {"allow_anonymous": True}
            },
        }
    )
    where = f"{Listen.in_url(listen.host)}:{port}"
    try:
        await broker.start()
    except BrokerError as exc:
        raise ConfigError(
            f"cannot start the embedded MQTT broker on {where} (--bind, --mqtt-port): {exc}"
        ) from exc
    _say(console, f"MQTT: embedded broker on {where}")
    try:
        yield port
    finally:
        await broker.shutdown()


@dataclass(frozen=True, slots=True)
class WebPage:
    """The demo's web page: its port and the password that signs in to calibrate."""

    port: int
    password: str

    @classmethod
    def make(cls, port: int) -> WebPage:
        """``GATEWAY_WEB__PASSWORD`` if set, else a new password for this run."""
        return cls(port, os.environ.get("GATEWAY_WEB__PASSWORD") or secrets.token_urlsafe(9))

    def config(self, listen: Listen) -> str:
        """The ``web:`` section.

        Reachable from other machines (``--bind 0.0.0.0``, a container with its ports
        published), the page answers to ``localhost`` and this machine's name too: a
        browser on the host of a container comes from the container's gateway address,
        not from loopback, and would otherwise be refused as a rebinding attempt.
        """
        names = "" if listen.bind.is_loopback else f", allowed_hosts: {_host_names()}"
        return (
            f"web: {{enabled: true, host: {json.dumps(listen.host)}, port: {self.port}, "
            f"password: {json.dumps(self.password)}{names}}}\n"
        )


def _host_names() -> str:
    """``localhost`` and this machine's name, as a YAML flow list."""
    names = ["localhost", socket.gethostname().lower()]
    # A name the config would refuse (an underscore, say) is left out, not the demo.
    return json.dumps([n for n in dict.fromkeys(names) if re.fullmatch(r"[a-z0-9.-]+", n)])


def _config(
    port: Path, mqtt_port: int | None, metrics_port: int, listen: Listen, state_dir: Path
) -> str:
    # Paths and addresses as JSON strings, which YAML reads as they are (an IPv6 address
    # or a path with a colon or brackets in it would not survive as a plain scalar).
    devices = "".join(
        f"  - {{name: {DEVICE_NAMES[d['address']]}, bus: demo, address: {d['address']}, "
        f"profile: {d['profile']}, poll_interval: 1.0}}\n"
        for d in DEMO_SENSORS
    )
    mqtt = (
        f"mqtt: {{host: {json.dumps(listen.client_host)}, port: {mqtt_port}, "
        f"base_topic: {BASE_TOPIC}}}\n"
        if mqtt_port is not None
        else "mqtt: {enabled: false}\n"
    )
    # The S10 takes its compensation temperature from the tecLine's, as a plant would.
    feeds = (
        "feeds:\n"
        "  - {device: aeration_oxygen, point: compensation_temperature, interval: 30,"
        " deadband: 0.1, source: {device: pool_chlorine, point: temperature}}\n"
    )
    line = DEMO_LINE
    return (
        f"buses:\n  - {{name: demo, port: {json.dumps(str(port))}, baudrate: {line.baudrate}, "
        f"parity: {line.parity}, stopbits: {line.stopbits}}}\n"
        f"devices:\n{devices}{mqtt}{feeds}"
        f"prometheus: {{host: {json.dumps(listen.host)}, port: {metrics_port}}}\n"
        f"state_dir: {json.dumps(str(state_dir))}\n"
    )


def _shared_bus(port: int, listen: Listen) -> str:
    """The ``shared_bus:`` section: Modbus TCP for other masters, read only (0: off)."""
    if not port:
        return ""
    return f"shared_bus: {{listen: [{{host: {json.dumps(listen.host)}, port: {port}}}]}}\n"


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
        # Names and values are text (a device's string may hold brackets); the style is ours.
        quality = escape(sample.quality.value)
        values.add_row(
            escape(device),
            escape(point),
            escape(shown),
            f"[{style}]{quality}[/]" if style else quality,
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
            escape(bus),
            str(sum(stats.requests.values())),
            str(sum(stats.responses.values())),
            str(sum(stats.errors.values())),
            f"{stats.utilisation():.0%}",
            f"{online}/{len(snapshot.devices)}",
            mqtt_text,
        )
    return Group(values, health)


def _banner(
    console: Console,
    *,
    pty: Path,
    listen: Listen,
    broker_port: int | None,
    metrics_port: int,
    page: WebPage | None = None,
    modbus_port: int = 0,
) -> None:
    """What runs where, and the commands to try it, ready to copy."""
    local = listen.client_host
    _say(console, f"simulated line: {pty} ({DEMO_LINE}), {len(DEMO_SENSORS)} sensors")
    if broker_port is not None:
        _say(
            console,
            f"watch MQTT:  mosquitto_sub -h {local} -p {broker_port} -t '{BASE_TOPIC}/#' -v",
        )
        _say(
            console,
            f"write:       mosquitto_pub -h {local} -p {broker_port} "
            f"-t {BASE_TOPIC}/digester_oxygen/compensation_pressure/set -m 1003.5",
        )
    if modbus_port:
        _say(
            console,
            f"Modbus TCP:  mbpoll -m tcp -p {modbus_port} -a 20 -r 1 -c 6 -t 4:hex -1 {local}"
            "  (other masters through the gateway: point the vendor's software here)",
        )
    url = f"http://{Listen.in_url(local)}:{metrics_port}"
    _say(console, f"metrics:     curl {url}/metrics")
    _say(console, f"health:      curl {url}/healthz")
    if page is not None:
        _say(
            console,
            f"web page:    http://{Listen.in_url(local)}:{page.port}/ "
            f"(sign in with the password {page.password} to write and calibrate)",
        )
    if listen.bind.is_loopback:
        _say(console, f"listening on {listen.host} only: --bind 0.0.0.0 to serve other machines")
    else:
        everywhere = " (every interface)" if listen.bind.is_unspecified else ""
        _say(console, f"listening on {listen.host}{everywhere}: reachable from other machines")
    _say(console, "Ctrl-C stops the demo.")


async def run_demo(
    *,
    mqtt_port: int = 1883,
    metrics_port: int = 9108,
    web_port: int = 8080,
    modbus_port: int = 1502,
    bind: str = LOCAL_BIND,
    live: bool = True,
) -> None:
    """Run the demo until SIGINT or SIGTERM.

    ``bind`` is where ``/metrics`` and the embedded broker listen: ``0.0.0.0`` for a
    container whose ports are published, loopback by default.
    """
    # Here, not at the top: the tests import this module for its parts, without a
    # simulator or a live display.
    from rich.live import Live  # noqa: PLC0415

    from gateway.simulator import SimulatorServer, build_bus, parse_settings  # noqa: PLC0415

    listen = Listen.parse(bind)
    console = Console(soft_wrap=True)  # commands to copy stay on one line
    with tempfile.TemporaryDirectory(prefix="gateway-demo-") as tmp:
        directory = Path(tmp)
        pty = directory / "ttyDEMO"
        line = {
            "baudrate": DEMO_LINE.baudrate,
            "parity": DEMO_LINE.parity,
            "stopbits": DEMO_LINE.stopbits,
        }
        simulator = SimulatorServer(
            build_bus(
                parse_settings({"line": line, "pace": True, "seed": 1, "devices": DEMO_SENSORS})
            )
        )
        simulator.open_pty(pty)
        try:
            async with _broker(mqtt_port, listen, console) as broker_port:
                page = WebPage.make(web_port)
                config = parse_config(
                    _config(pty, broker_port, metrics_port, listen, directory / "state")
                    + page.config(listen)
                    + _shared_bus(modbus_port, listen),
                    environ={},
                )
                _banner(
                    console,
                    pty=pty,
                    listen=listen,
                    broker_port=broker_port,
                    metrics_port=metrics_port,
                    page=page,
                    modbus_port=modbus_port,
                )
                state = GatewayState()
                table = live and console.is_terminal
                # Without the live table (--no-live, a pipe, a container's log) each poll
                # cycle is printed as a line, as `gateway run --print` does.
                sinks = [] if table else [ConsoleSink()]
                gateway = asyncio.create_task(run(config, sinks, state=state), name="demo.gateway")
                if table:
                    with Live(_table(state), console=console, refresh_per_second=2) as screen:
                        while not gateway.done():
                            await asyncio.sleep(REFRESH_S)
                            screen.update(_table(state))
                await gateway
        finally:
            await simulator.close()
