"""``gateway demo`` as a newcomer runs it: values on MQTT and /metrics within seconds, Ctrl-C."""

from __future__ import annotations

import asyncio
import contextlib
import ipaddress
import json
import re
import signal
import socket
import subprocess
import sys
import urllib.error
import urllib.request
from pathlib import Path
from typing import TYPE_CHECKING

import aiomqtt
import pytest

from gateway.cli.demo import Listen, WebPage
from gateway.config import parse_config
from gateway.web.auth import host_allowed
from tests.mqtt_broker import free_port

if TYPE_CHECKING:
    from collections.abc import AsyncIterator

# On the loopback interface (127.0.0.0/8) but not the address the demo listens on by
# default: reaching the demo here shows it listens beyond 127.0.0.1, as a container's
# published port needs, on any machine (no other interface required).
OTHER_ADDRESS = "127.0.0.2"
LISTEN = "0A"  # TCP_LISTEN in /proc/net/tcp
# The demo as a user without the ``demo`` extra runs it: amqtt cannot be imported.
WITHOUT_AMQTT = (
    "import runpy, sys; sys.modules['amqtt'] = None; "
    "runpy.run_module('gateway', run_name='__main__', alter_sys=True)"
)


async def read_banner(process: asyncio.subprocess.Process, *, within_s: float) -> str:
    """What the demo prints before it runs: up to the line that says how to stop it."""
    assert process.stdout is not None
    banner = ""
    while "Ctrl-C" not in banner:
        line = await asyncio.wait_for(process.stdout.readline(), timeout=within_s)
        assert line, f"the demo ended before its banner: {banner}"
        banner += line.decode()
    return banner


@contextlib.asynccontextmanager
async def demo(
    *args: str,
    mqtt_port: int,
    metrics_port: int,
    web_port: int | None = None,
    modbus_port: int | None = None,
    without_amqtt: bool = False,
) -> AsyncIterator[tuple[str, asyncio.StreamReader]]:
    """Run ``gateway demo --no-live ARGS``; yield its banner and the rest of its output;
    Ctrl-C must end it cleanly.

    Yields once ``/metrics`` answers: the gateway is running then, and Ctrl-C stops it
    (before, it interrupts the start-up, exit status 130).
    """
    entry = ("-c", WITHOUT_AMQTT) if without_amqtt else ("-m", "gateway")
    process = await asyncio.create_subprocess_exec(
        sys.executable,
        *entry,
        "demo",
        "--mqtt-port",
        str(mqtt_port),
        "--metrics-port",
        str(metrics_port),
        "--web-port",
        str(web_port or free_port()),
        "--modbus-port",
        str(modbus_port or free_port()),
        *args,
        "--no-live",
        stdout=asyncio.subprocess.PIPE,
        stderr=asyncio.subprocess.PIPE,
    )
    try:
        banner = await read_banner(process, within_s=30)
        assert process.stdout is not None
        await get_when_up(f"http://127.0.0.1:{metrics_port}/healthz", process=process)
        yield banner, process.stdout
    except BaseException as exc:
        # What the demo said of it, next to the test's own failure.
        exc.add_note(f"the demo's stderr:\n{(await _stopped(process)).decode()}")
        raise
    err = await _stopped(process)
    assert process.returncode == 0, err.decode()


async def _stopped(process: asyncio.subprocess.Process) -> bytes:
    """Ctrl-C the demo if it still runs; its stderr once it has ended."""
    if process.returncode is None:
        process.send_signal(signal.SIGINT)
    _, err = await asyncio.wait_for(process.communicate(), timeout=15)
    return err


def listening_addresses(port: int) -> set[str]:
    """The addresses sockets listen on at ``port``, from the kernel's own tables."""
    found = set()
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        with contextlib.suppress(FileNotFoundError):
            for row in Path(table).read_text(encoding="ascii").splitlines()[1:]:
                local, state = row.split()[1], row.split()[3]
                host, port_hex = local.split(":")
                if state == LISTEN and int(port_hex, 16) == port:
                    raw = bytes.fromhex(host)  # 32-bit words, each in host (little-endian) order
                    words = b"".join(raw[i : i + 4][::-1] for i in range(0, len(raw), 4))
                    found.add(str(ipaddress.ip_address(words)))
    return found


def refused(host: str, port: int) -> bool:
    try:
        socket.create_connection((host, port), timeout=2).close()
    except ConnectionRefusedError:
        return True
    return False


def get(url: str) -> str:
    """The body of a GET; errors (a 503 health while MQTT connects) are answers too."""
    try:
        with urllib.request.urlopen(url, timeout=5) as response:  # noqa: S310 - a local http URL
            return str(response.read().decode())
    except urllib.error.HTTPError as exc:
        with exc:
            return str(exc.read().decode())


async def get_when_up(
    url: str, *, timeout_s: float = 15, process: asyncio.subprocess.Process | None = None
) -> str:
    """GET ``url`` once the gateway serves it (it starts after the banner).

    A ``process`` that ends meanwhile fails the wait at once with its own words: a demo
    that could not start (a port taken, a failed import) is not a slow one.
    """
    async with asyncio.timeout(timeout_s):
        while True:
            try:
                return await asyncio.to_thread(get, url)
            except OSError:
                if process is not None and process.returncode is not None:
                    _, err = await process.communicate()
                    pytest.fail(
                        f"the demo ended (exit status {process.returncode}) before it "
                        f"served {url}:\n{err.decode()}"
                    )
                await asyncio.sleep(0.2)


@pytest.mark.line
@pytest.mark.broker
async def test_demo_publishes_to_mqtt_and_metrics_then_stops_on_ctrl_c() -> None:
    mqtt_port, metrics_port = free_port(), free_port()
    async with demo(mqtt_port=mqtt_port, metrics_port=metrics_port) as (banner, _):
        assert f"embedded broker on 127.0.0.1:{mqtt_port}" in banner
        assert f"mosquitto_sub -h 127.0.0.1 -p {mqtt_port} -t 'demo/#' -v" in banner
        # The line the banner names is the one the simulated sensors say they are set to.
        assert "(19200 8E1), 6 sensors" in banner
        received: dict[str, str] = {}
        async with aiomqtt.Client("127.0.0.1", mqtt_port) as client:
            await client.subscribe("demo/#", qos=1)

            async def collect() -> None:
                async for message in client.messages:
                    payload = message.payload
                    received[str(message.topic)] = (
                        payload.decode() if isinstance(payload, bytes) else str(payload)
                    )
                    if {
                        "demo/aeration_oxygen/temperature",
                        "demo/basin_chlorine/concentration",
                    } <= set(received):
                        return

            await asyncio.wait_for(collect(), timeout=15)
            # The write the banner shows goes through, and its result comes back.
            topic = "demo/digester_oxygen/compensation_pressure/set"
            assert f"-t {topic} -m 1003.5" in banner
            await client.subscribe(f"{topic}/result", qos=1)
            await client.publish(topic, "1003.5", qos=1)

            async def result() -> dict[str, object]:
                async for message in client.messages:
                    if str(message.topic) == f"{topic}/result":
                        return json.loads(message.payload)  # type: ignore[no-any-return]
                raise AssertionError("no result")

            outcome = await asyncio.wait_for(result(), timeout=15)
            assert (outcome["status"], outcome["value"]) == ("ok", 1003.5)
        assert float(received["demo/aeration_oxygen/temperature"]) > 0
        metrics = await get_when_up(f"http://127.0.0.1:{metrics_port}/metrics")
        assert 'gateway_temperature_celsius{bus="demo",device="aeration_oxygen"' in metrics
        assert 'gateway_value_fault{bus="demo",device="fermenter_oxygen"' in metrics
        # The demo's feed keeps the S10's compensation temperature from the tecLine's.
        feed = 'gateway_feed_writes_total{feed="aeration_oxygen/compensation_temperature"'
        assert feed in metrics
        assert (
            'gateway_writes_total{device="digester_oxygen",kind="set",outcome="ok"} 1.0' in metrics
        )
        # By default nothing of the demo is reachable from another machine.
        assert listening_addresses(metrics_port) == {"127.0.0.1"}
        assert listening_addresses(mqtt_port) == {"127.0.0.1"}
        assert refused(OTHER_ADDRESS, metrics_port)
        assert refused(OTHER_ADDRESS, mqtt_port)


@pytest.mark.line
@pytest.mark.broker
async def test_other_masters_read_the_demo_sensors_through_the_gateway() -> None:
    modbus_port = free_port()
    async with demo(mqtt_port=free_port(), metrics_port=free_port(), modbus_port=modbus_port) as (
        banner,
        _,
    ):
        command = f"mbpoll -m tcp -p {modbus_port} -a 20 -r 1 -c 6 -t 4:hex -1 127.0.0.1"
        assert command in banner
        result = await asyncio.to_thread(
            subprocess.run, command.split(), capture_output=True, text=True, timeout=20
        )
        assert listening_addresses(modbus_port) == {"127.0.0.1"}
    assert result.returncode == 0, result.stderr
    # The tecLine's six measuring registers, as the simulated sensor answered them.
    shown = [line.split(":")[1].strip() for line in result.stdout.splitlines() if line[:1] == "["]
    assert len(shown) == 6
    assert all(value.startswith("0x") for value in shown)


@pytest.mark.line
@pytest.mark.broker
async def test_the_demo_serves_its_web_page_on_loopback_and_prints_its_url() -> None:
    web_port = free_port()
    async with demo(mqtt_port=free_port(), metrics_port=free_port(), web_port=web_port) as (
        banner,
        _,
    ):
        assert f"web page:    http://127.0.0.1:{web_port}/ (sign in with the password" in banner
        page = await get_when_up(f"http://127.0.0.1:{web_port}/")
        assert '<script src="/static/app.js" defer></script>' in page
        state = json.loads(await get_when_up(f"http://127.0.0.1:{web_port}/api/state"))
        assert {"pool_chlorine", "fermenter_oxygen"} <= {d["name"] for d in state["devices"]}
        assert listening_addresses(web_port) == {"127.0.0.1"}


@pytest.mark.line
@pytest.mark.broker
async def test_bind_serves_metrics_and_mqtt_to_other_machines() -> None:
    # A container's ``-p 9108:9108 -p 1883:1883`` reaches only what listens beyond loopback.
    mqtt_port, metrics_port, web_port = free_port(), free_port(), free_port()
    bind = "0.0.0.0"  # noqa: S104 - every interface: the point of the test
    async with demo(
        "--bind", bind, mqtt_port=mqtt_port, metrics_port=metrics_port, web_port=web_port
    ) as (banner, _):
        assert f"embedded broker on 0.0.0.0:{mqtt_port}" in banner
        assert "listening on 0.0.0.0 (every interface)" in banner
        # The commands shown still work on this machine.
        assert f"curl http://127.0.0.1:{metrics_port}/metrics" in banner
        assert f"mosquitto_sub -h 127.0.0.1 -p {mqtt_port}" in banner
        metrics = await get_when_up(f"http://{OTHER_ADDRESS}:{metrics_port}/metrics")
        assert "gateway_up 1.0" in metrics
        # The gateway's own client reaches the broker, and so does one from elsewhere.
        async with aiomqtt.Client(OTHER_ADDRESS, mqtt_port) as client:
            await client.subscribe("demo/aeration_oxygen/availability", qos=1)
            message = await asyncio.wait_for(anext(aiter(client.messages)), timeout=15)
            # The embedded broker (amqtt) also hands a new subscriber retained messages of
            # topics it did not subscribe to (the owner marker, {base}/owner): the first
            # message of the subscribed topic is the one that counts.
            while not message.topic.matches("demo/aeration_oxygen/availability"):
                message = await asyncio.wait_for(anext(aiter(client.messages)), timeout=15)
            assert message.payload == b"online"
        assert listening_addresses(metrics_port) == {"0.0.0.0"}  # noqa: S104
        assert listening_addresses(mqtt_port) == {"0.0.0.0"}  # noqa: S104
        # The page too, by the names the demo lets it answer to; others are refused.
        await get_when_up(f"http://{OTHER_ADDRESS}:{web_port}/")
        request = urllib.request.Request(
            f"http://{OTHER_ADDRESS}:{web_port}/api/state",
            headers={"Host": f"localhost:{web_port}"},
        )
        with await asyncio.to_thread(urllib.request.urlopen, request, timeout=5) as answer:
            assert answer.status == 200
        refused = urllib.request.Request(
            f"http://{OTHER_ADDRESS}:{web_port}/api/state", headers={"Host": "evil.example"}
        )
        with pytest.raises(urllib.error.HTTPError) as caught:
            await asyncio.to_thread(urllib.request.urlopen, refused, timeout=5)
        caught.value.close()
        assert caught.value.code == 421  # still no rebinding


async def test_without_the_demo_extra_the_hint_shows_the_extra() -> None:
    # rich markup took ``[demo]`` for a tag: the hint read ``pip install '.'``.
    async with demo(mqtt_port=free_port(), metrics_port=free_port(), without_amqtt=True) as (
        banner,
        _,
    ):
        assert "install the demo extra (pip install '.[demo]'); running without MQTT" in banner
        assert "mosquitto_sub" not in banner  # no broker: no MQTT commands to copy


@pytest.mark.line
@pytest.mark.broker
async def test_without_a_live_table_the_demo_prints_its_values() -> None:
    # In a container's log or a pipe there is no live table: each poll cycle is a line.
    async with demo(mqtt_port=free_port(), metrics_port=free_port()) as (_, output):
        seen = ""
        cycle = re.compile(r"demo/basin_chlorine concentration=[0-9.]+ ppm")
        while not cycle.search(seen) or "demo/aeration_oxygen oxygen=" not in seen:
            line = await asyncio.wait_for(output.readline(), timeout=15)
            assert line, f"the demo's output ended: {seen}"
            seen += line.decode()


def test_bound_beyond_loopback_the_demos_page_answers_to_localhost_from_a_containers_host() -> None:
    # A browser on the host of a container asks for localhost:8080; the connection comes
    # in from the container network's gateway, not from loopback.
    page = WebPage(port=8080, password="demo-password")  # noqa: S106 - a test's
    everywhere = Listen.parse("0.0.0.0")  # noqa: S104 - the container's --bind
    config = parse_config(
        "buses: [{name: line1, port: /dev/null}]\n" + page.config(everywhere), environ={}
    )
    allowed = frozenset(config.web.allowed_hosts)
    assert "localhost" in allowed

    def answers(host: str) -> bool:
        return host_allowed(
            host, allowed=allowed, listen=everywhere.host, local="10.88.0.5", remote="10.88.0.1"
        )

    assert answers("localhost:8080")
    assert not answers("evil.example")
    # On loopback only (the default), no name is added: localhost is this machine's anyway.
    assert "allowed_hosts" not in page.config(Listen.parse("127.0.0.1"))
