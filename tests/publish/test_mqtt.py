"""MQTT with a real mosquitto broker and the simulator: the topic contract, availability,
the last will, store-and-forward across an outage and a restart, and bad settings.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import signal
import subprocess
import sys
from typing import TYPE_CHECKING, Any, Self

import paho.mqtt.client as paho
import pytest

from gateway.app import run
from gateway.config import MqttConfig, parse_config
from gateway.errors import GatewayError, PublishError
from gateway.publish.mqtt import MqttSink
from gateway.shared.state import DeviceInfo, GatewayState, StateSink
from gateway.simulator import SimulatorServer, build_bus, parse_settings
from tests.mqtt_broker import Broker, TlsFiles, recording
from tests.publish.prometheus.test_prometheus import sample
from tests.rigs import ListSink
from tests.sparkplug_decoder import encode_varint
from tests.waiting import eventually

if TYPE_CHECKING:
    from collections.abc import AsyncIterator, Sequence
    from pathlib import Path

    from gateway.line.samples import Sample

SENSORS = [
    {
        "profile": "jumo-digiline-odo-s10",
        "address": 1,
        "animate": False,
        "values": {
            "temperature": 20.25,
            "oxygen": {"fault": "overrange"},
            "status": {"cap_missing": True},
        },
    },
    {"profile": "reiss-m0c", "address": 10, "animate": False, "values": {"concentration": 0.168}},
]


@contextlib.asynccontextmanager
async def simulated(
    tmp_path: Path, devices: list[dict[str, Any]] = SENSORS, **faults: Any
) -> AsyncIterator[SimulatorServer]:
    server = SimulatorServer(build_bus(parse_settings({"devices": devices, **faults})))
    server.open_pty(tmp_path / "ttySIM")
    try:
        yield server
    finally:
        await server.close()


def gateway_yaml(
    tmp_path: Path, broker_port: int, *, mqtt: str = "", extra_device: str = ""
) -> str:
    return (
        f"buses:\n  - {{name: line1, port: {tmp_path / 'ttySIM'}}}\n"
        "devices:\n"
        "  - {name: aeration, bus: line1, address: 1, profile: jumo-digiline-odo-s10, poll_interval: 0.3,"
        " offline_after: 2}\n"
        "  - {name: basin, bus: line1, address: 10, profile: reiss-m0c, poll_interval: 0.3}\n"
        f"{extra_device}"
        f"mqtt: {{host: 127.0.0.1, port: {broker_port}, base_topic: gw, reconnect_max_s: 1{mqtt}}}\n"
        "prometheus: {enabled: false}\n"
        f"state_dir: {tmp_path / 'state'}\n"
    )


@contextlib.asynccontextmanager
async def gateway(config_text: str, sinks: list[Any] | None = None) -> AsyncIterator[GatewayState]:
    config = parse_config(config_text, environ={})
    state = GatewayState()
    stop = asyncio.Event()
    task = asyncio.create_task(run(config, sinks or [], stop=stop, state=state))
    try:
        yield state
    finally:
        stop.set()
        await asyncio.wait_for(task, timeout=15)


@pytest.mark.line
@pytest.mark.broker
async def test_every_topic_of_the_contract(tmp_path: Path, broker: Broker) -> None:
    async with simulated(tmp_path), recording(broker.port, "gw/#") as seen:
        async with gateway(gateway_yaml(tmp_path, broker.port)):
            await seen.wait_for("gw/aeration/state")
            await seen.wait_for("gw/basin/concentration", "0.168")
            await seen.wait_for("gw/aeration/temperature", "20.25")
            await seen.wait_for("gw/aeration/status/cap_missing", "true")
            await seen.wait_for("gw/aeration/availability", "online")
            await seen.wait_for("gw/status", "online")
        await seen.wait_for(
            "gw/status", "offline", skip=len(seen.on("gw/status")) - 1
        )  # a clean stop
    # A fault float is a fault: its value topic is cleared, never a number.
    assert set(seen.on("gw/aeration/oxygen")) == {""}
    documents = [json.loads(p) for p in seen.on("gw/aeration/state")]
    assert [d["seq"] for d in documents] == list(range(1, len(documents) + 1))  # none lost
    state = documents[-1]
    assert state["faults"]["oxygen"] == "overrange"
    assert state["quality"]["oxygen"] == "fault"
    assert "oxygen" not in state["values"]
    assert state["values"]["temperature"] == 20.25
    assert state["units"]["temperature"] == "°C"
    assert state["quality"]["temperature"] == "good"
    for message in seen.messages:
        assert "e+37" not in message.payload.lower()
    # What a subscriber arriving now gets: the retained topics, and no state document.
    async with recording(broker.port, "gw/#", name="late-subscriber") as late:
        await late.wait_for("gw/aeration/temperature", "20.25")
        await asyncio.sleep(0.3)
    retained = {m.topic for m in late.messages if m.retain}
    assert {"gw/status", "gw/aeration/availability", "gw/aeration/status/cap_missing"} <= retained
    assert "gw/basin/concentration" in retained
    assert not any(topic.endswith("/state") for topic in retained)
    assert "gw/aeration/oxygen" not in retained  # cleared: no stale number for newcomers


@pytest.mark.line
@pytest.mark.broker
async def test_status_bits_flip_and_availability_follows_the_sensor(
    tmp_path: Path, broker: Broker
) -> None:
    async with (
        simulated(tmp_path) as server,
        recording(broker.port, "gw/#") as seen,
        gateway(gateway_yaml(tmp_path, broker.port)),
    ):
        await seen.wait_for("gw/aeration/status/cap_missing", "true")
        server.bus.devices[1].set_flags("status", cap_missing=False)
        await seen.wait_for("gw/aeration/status/cap_missing", "false")
        server.bus.silence(1, 4.0, asyncio.get_running_loop().time())
        before = len(seen.on("gw/aeration/availability"))
        await seen.wait_for("gw/aeration/availability", "offline", within_s=8, skip=before)
        after = len(seen.on("gw/aeration/availability"))
        await seen.wait_for("gw/aeration/availability", "online", within_s=12, skip=after)
    assert seen.on("gw/aeration/availability")[-2:] == ["offline", "online"]
    assert seen.on("gw/basin/availability") == ["online"]


@pytest.mark.line
@pytest.mark.broker
async def test_the_last_will_fires_when_the_gateway_is_killed(
    tmp_path: Path, broker: Broker
) -> None:
    config = tmp_path / "gateway.yaml"
    config.write_text(gateway_yaml(tmp_path, broker.port), encoding="utf-8")
    async with simulated(tmp_path), recording(broker.port, "gw/status") as seen:
        process = await asyncio.create_subprocess_exec(
            sys.executable,
            "-m",
            "gateway",
            "run",
            "--config",
            str(config),
            stdout=asyncio.subprocess.DEVNULL,
            stderr=asyncio.subprocess.DEVNULL,
        )
        await seen.wait_for("gw/status", "online", within_s=15)
        process.send_signal(signal.SIGKILL)
        await process.wait()
        await seen.wait_for(
            "gw/status", "offline", within_s=15
        )  # keepalive 60 s: the broker sees the socket close


class CycleSink(ListSink):
    """Also remembers each poll cycle of the device ``basin``: the state documents to expect."""

    def __init__(self) -> None:
        super().__init__()
        self.cycles: list[str] = []

    async def publish(self, samples: Sequence[Sample]) -> None:
        await super().publish(samples)
        if samples and samples[0].device == "basin":
            self.cycles.append(samples[0].time.isoformat())


@pytest.mark.line
@pytest.mark.broker
async def test_outage_and_restart_lose_nothing_and_repeat_nothing(
    tmp_path: Path, broker: Broker
) -> None:
    cycles = CycleSink()
    async with simulated(tmp_path), recording(broker.port, "gw/basin/state") as seen:
        async with gateway(gateway_yaml(tmp_path, broker.port), [cycles]):
            await seen.wait_for("gw/basin/state")
            broker.stop()
            outage_starts = len(cycles.cycles)
            await asyncio.sleep(2.0)
        # The gateway is restarted during the outage: the queue is on disk.
        async with gateway(gateway_yaml(tmp_path, broker.port), [cycles]) as state:
            await eventually(lambda: state.mqtt.queue_depth > 10, within_s=15)
            assert state.mqtt.connected is False
            outage_ends = len(cycles.cycles)
            broker.start()
            deadline = asyncio.get_running_loop().time() + 20
            while state.mqtt.queue_depth and asyncio.get_running_loop().time() < deadline:  # noqa: ASYNC110 - another task drains it
                await asyncio.sleep(0.1)
            assert state.mqtt.queue_depth == 0
            assert state.mqtt.connected
            live_from = len(cycles.cycles)
            await asyncio.sleep(1.0)
    received = [json.loads(p)["time"] for p in seen.on("gw/basin/state")]
    during = cycles.cycles[outage_starts:outage_ends]
    assert len(during) > 5, "cycles were produced during the outage"
    for cycle in during:
        assert received.count(cycle) == 1, cycle  # every one arrived, exactly once
    positions = [received.index(cycle) for cycle in during]
    assert positions == sorted(positions)  # in order
    # And live data after the backlog: a cycle made once it had drained arrived after it.
    # (Not necessarily the very last one: a cycle made as the gateway stops stays queued.)
    live = [received.index(c) for c in cycles.cycles[live_from:] if c in received]
    assert live, "no cycle made after the backlog drained arrived"
    assert min(live) > max(positions)


@pytest.mark.broker
async def test_a_lost_broker_is_seen_at_once_with_nothing_to_send(
    tmp_path: Path, broker: Broker
) -> None:
    """A session with nothing in flight and no command topics still ends when the broker goes.

    Polling once a minute, the gateway must not show ``connected`` (``/healthz``, the
    metrics) until its next publish fails, nor wait for a PUBACK timeout to notice.
    """
    state = GatewayState()
    sink = MqttSink(
        MqttConfig(host="127.0.0.1", port=broker.port, base_topic="gw"),
        state,
        state_dir=tmp_path / "state",
    )
    task = asyncio.create_task(sink.run())
    try:
        async with asyncio.timeout(10):
            while not state.mqtt.connected:  # noqa: ASYNC110 - the sink's task sets it
                await asyncio.sleep(0.01)
        await asyncio.sleep(0.2)  # the status message acknowledged: nothing in flight
        broker.stop()
        stopped = asyncio.get_running_loop().time()
        async with asyncio.timeout(10):
            while state.mqtt.connected:  # noqa: ASYNC110 - the sink's task clears it
                await asyncio.sleep(0.01)
        seen_after = asyncio.get_running_loop().time() - stopped
    finally:
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task
    assert seen_after < 1.0  # the PUBACK timeout, the only other way to notice, is 4 s
    assert state.mqtt.last_error is not None


async def _remaining_length(reader: asyncio.StreamReader) -> int:
    """MQTT's variable-length integer (MQTT 3.1.1, 2.2.3)."""
    value, shift = 0, 0
    while True:
        byte = (await reader.readexactly(1))[0]
        value |= (byte & 0x7F) << shift
        if not byte & 0x80:
            return value
        shift += 7


def _swallowing_answer(kind: int, body: bytes) -> bytes:
    """A half-open broker's answer to one packet: only what a connection begins with."""
    if kind >> 4 == 1:  # CONNECT: CONNACK, session not present, accepted
        return b"\x20\x02\x00\x00"
    if kind >> 4 == 8:  # SUBSCRIBE (the owner marker, the status): SUBACK, QoS 1 granted
        return b"\x90\x03" + body[:2] + b"\x01"
    if kind >> 4 != 3 or not (kind >> 1) & 3:  # not a PUBLISH at QoS 1
        return b""
    topic_length = int.from_bytes(body[:2], "big")
    topic = body[2 : 2 + topic_length]
    if not topic.endswith((b"/status", b"/owner")):
        return b""  # swallowed
    packet_id = body[2 + topic_length : 4 + topic_length]
    answer = b"\x40\x02" + packet_id  # PUBACK: ``online`` and the claim
    if topic.endswith(b"/owner"):  # and the claim to its subscriber
        answer += bytes([kind]) + encode_varint(len(body)) + body
    return answer


async def test_a_broker_that_stops_acknowledging_ends_the_session_and_keeps_the_messages(
    tmp_path: Path,
) -> None:
    """A half-open broker: it takes the connection and acknowledges ``online`` (and the
    owner marker's subscription and claim, which it hands back), then swallows every publish without a PUBACK. The session ends at the oldest publish's 4 s
    timeout, and what was handed over stays queued on disk, none lost."""

    sessions: list[asyncio.StreamWriter] = []

    async def swallowing_broker(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        sessions.append(writer)
        with contextlib.suppress(asyncio.IncompleteReadError, ConnectionError):
            while True:
                kind = (await reader.readexactly(1))[0]
                body = await reader.readexactly(await _remaining_length(reader))
                writer.write(_swallowing_answer(kind, body))
                await writer.drain()

    server = await asyncio.start_server(swallowing_broker, "127.0.0.1", 0)
    port = server.sockets[0].getsockname()[1]
    state = GatewayState()
    state.add_device(
        DeviceInfo(bus="line1", name="basin", profile="reiss-m0c", address=10, intervals={})
    )
    sink = MqttSink(
        MqttConfig(host="127.0.0.1", port=port, base_topic="gw"), state, state_dir=tmp_path
    )
    task = asyncio.create_task(sink.run())
    try:
        async with asyncio.timeout(10):
            while not state.mqtt.connected:  # noqa: ASYNC110 - the sink's task sets it
                await asyncio.sleep(0.01)
        cycle = [sample("basin", "reiss-m0c", "concentration", 0.25, unit="mg/l")]
        await StateSink(state).publish(cycle)  # the state the document shows, as in the app
        await sink.publish(cycle)  # a value and a state document, never acknowledged
        handed_over = asyncio.get_running_loop().time()
        async with asyncio.timeout(10):
            while state.mqtt.connected:  # noqa: ASYNC110 - the sink's task clears it
                await asyncio.sleep(0.01)
        ended_after = asyncio.get_running_loop().time() - handed_over
        assert state.mqtt.queue_depth == 2  # both on disk, to be sent again
        assert state.mqtt.published == 0
    finally:
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task
        for writer in sessions:
            writer.close()
        server.close()
        await server.wait_closed()
    assert 3.5 < ended_after < 6.0  # the oldest publish's CLIENT_TIMEOUT_S (4 s)
    assert state.mqtt.last_error is not None
    assert "timed out" in state.mqtt.last_error


@pytest.mark.line
@pytest.mark.broker
async def test_refused_credentials_are_reported_and_polling_goes_on(tmp_path: Path) -> None:
    directory = tmp_path / "broker"
    directory.mkdir()
    secured = Broker(directory, users={"plant": "right"})
    secured.start()
    try:
        async with simulated(tmp_path):
            text = gateway_yaml(tmp_path, secured.port, mqtt=", username: plant, password: wrong")
            cycles = ListSink()
            async with gateway(text, [cycles]) as state:
                error = await eventually(lambda: state.mqtt.last_error, within_s=15)
                assert state.mqtt.connected is False
                assert "refused the credentials of plant" in error
        assert any(s.good for s in cycles.samples)
    finally:
        secured.stop()


async def test_missing_tls_file_is_an_error_at_start(tmp_path: Path) -> None:
    text = gateway_yaml(tmp_path, 1883, mqtt=f", tls: {{ca: {tmp_path / 'missing-ca.pem'}}}")
    with pytest.raises(PublishError, match=r"mqtt\.tls\.ca: .*missing-ca\.pem does not exist"):
        await run(parse_config(text, environ={}), stop=asyncio.Event())


async def test_unwritable_state_directory_is_an_error_at_start(tmp_path: Path) -> None:
    blocker = tmp_path / "state"
    blocker.write_text("a file, not a directory", encoding="utf-8")
    with pytest.raises(GatewayError, match="cannot be written"):
        await run(parse_config(gateway_yaml(tmp_path, 1883), environ={}), stop=asyncio.Event())


def test_cli_reports_start_errors_clearly(tmp_path: Path) -> None:
    config = tmp_path / "gateway.yaml"
    config.write_text(
        gateway_yaml(tmp_path, 1883, mqtt=f", tls: {{cert: {tmp_path / 'no.pem'}}}"),
        encoding="utf-8",
    )
    result = subprocess.run(
        [sys.executable, "-m", "gateway", "run", "--config", str(config)],
        capture_output=True,
        text=True,
        check=False,
        timeout=30,
        env={**os.environ, "COLUMNS": "200"},
    )
    assert result.returncode == 2
    assert "mqtt.tls.cert" in result.stderr


@pytest.mark.line
@pytest.mark.broker
async def test_publish_modes_on_change_and_deadband_with_heartbeat(
    tmp_path: Path, broker: Broker
) -> None:
    moving = [
        {"profile": "jumo-digiline-odo-s10", "address": 1},  # values move a little every read
        {
            "profile": "reiss-m0c",
            "address": 10,
            "animate": False,
            "values": {"concentration": 0.168},
        },
    ]
    text = (
        gateway_yaml(tmp_path, broker.port)
        .replace(
            "poll_interval: 0.3, offline_after: 2}",
            "poll_interval: 0.3, offline_after: 2, publish: {mode: deadband, deadband: 100, heartbeat_s: 1.5}}",
        )
        .replace(
            "profile: reiss-m0c, poll_interval: 0.3}",
            "profile: reiss-m0c, poll_interval: 0.3, publish: {mode: on_change, heartbeat_s: 1.0},"
            " points: {temperature: {publish: {mode: every_poll}}}}",
        )
    )
    async with (
        simulated(tmp_path, moving),
        recording(broker.port, "gw/#") as seen,
        gateway(text),
    ):
        await asyncio.sleep(3.2)
    states = len(seen.on("gw/basin/state"))
    assert states >= 8  # the state document goes out every poll cycle
    assert 2 <= len(seen.on("gw/basin/concentration")) <= 4  # first value, then heartbeats
    assert len(seen.on("gw/basin/temperature")) >= states - 1  # its own mode: every poll
    oxygen = seen.on("gw/aeration/oxygen")
    assert 1 <= len(oxygen) <= 3  # it moves, but never by 100: heartbeats only


@pytest.mark.line
@pytest.mark.broker
async def test_tls_with_a_client_certificate(tmp_path: Path) -> None:
    directory = tmp_path / "broker"
    directory.mkdir()
    tls = TlsFiles.make(directory)
    secured = Broker(directory, tls=tls)
    secured.start()
    try:
        settings = f", tls: {{ca: {tls.ca}, cert: {tls.client_cert}, key: {tls.client_key}}}"
        async with (
            simulated(tmp_path),
            recording(secured.port, "gw/#", tls) as seen,
            gateway(gateway_yaml(tmp_path, secured.port, mqtt=settings)) as state,
        ):
            await seen.wait_for("gw/aeration/temperature", "20.25")
            # Connected once the backlog of the claim's wait (publish/mqtt/identity) is sent.
            await eventually(lambda: state.mqtt.connected, within_s=10)
    finally:
        secured.stop()


@pytest.mark.line
@pytest.mark.broker
async def test_home_assistant_discovery(tmp_path: Path, broker: Broker) -> None:
    settings = ", client_id: plant-gw, discovery: {enabled: true, prefix: ha}"
    async with (
        simulated(tmp_path),
        recording(broker.port, "ha/#") as seen,
        gateway(gateway_yaml(tmp_path, broker.port, mqtt=settings)),
    ):
        topic = "ha/sensor/plant-gw_aeration/temperature/config"
        await seen.wait_for(topic)
        await seen.wait_for("ha/binary_sensor/plant-gw_aeration/status_cap_missing/config")
    config = json.loads(seen.on(topic)[-1])
    assert config["state_topic"] == "gw/aeration/temperature"
    assert config["unit_of_measurement"] == "°C"
    assert config["device_class"] == "temperature"
    assert config["device"]["model"] == "JUMO digiLine O-DO S10"
    assert {a["topic"] for a in config["availability"]} == {"gw/status", "gw/aeration/availability"}


class TurnCounter:
    """Counts the event loop's turns: a callback that puts itself back on every turn.

    While it runs the loop never sleeps, so a timer of any length would take thousands of
    turns to fire: a message sent within a few turns was sent at once, not by a timer.
    """

    def __init__(self) -> None:
        self.turns = 0
        self._handle: asyncio.Handle | None = None

    def __enter__(self) -> Self:
        self._handle = asyncio.get_running_loop().call_soon(self._tick)
        return self

    def __exit__(self, *_: object) -> None:
        if self._handle is not None:
            self._handle.cancel()

    def _tick(self) -> None:
        self.turns += 1
        self._handle = asyncio.get_running_loop().call_soon(self._tick)


@pytest.mark.broker
async def test_a_handed_over_cycle_is_published_at_once_not_by_a_timer(
    tmp_path: Path, broker: Broker, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Values are published as soon as a cycle is decoded: no batching that waits a timer.

    Each cycle's messages must reach the client within a few turns of the loop after the
    bus task hands it over, the second cycle too while the first waits for its PUBACKs.
    """
    state = GatewayState()
    state.add_device(
        DeviceInfo(
            bus="line1",
            name="basin",
            profile="reiss-m0c",
            address=10,
            intervals={"concentration": 1.0},
        )
    )
    sink = MqttSink(
        MqttConfig(host="127.0.0.1", port=broker.port, base_topic="gw"),
        state,
        state_dir=tmp_path / "state",
    )
    recorder = StateSink(state)
    counter = TurnCounter()
    sent: list[tuple[str, bytes, int]] = []  # topic, payload, the turn it reached the client
    client_publish = paho.Client.publish  # where every publish reaches the client

    def spy(client: paho.Client, topic: str, payload: Any, *args: Any, **kwargs: Any) -> Any:
        sent.append((topic, payload, counter.turns))
        return client_publish(client, topic, payload, *args, **kwargs)

    monkeypatch.setattr(paho.Client, "publish", spy)
    task = asyncio.create_task(sink.run())
    try:
        async with asyncio.timeout(10):
            while not state.mqtt.connected:  # noqa: ASYNC110 - the sink's task sets it
                await asyncio.sleep(0.01)
        handed_over = {}
        with counter:
            for value in (0.25, 0.5):
                cycle = [sample("basin", "reiss-m0c", "concentration", value, unit="mg/l")]
                await recorder.publish(cycle)  # the state the document shows, as in the app
                handed_over[value] = counter.turns
                await sink.publish(cycle)
                await asyncio.sleep(0)  # one turn: the first cycle then waits for PUBACKs
            async with asyncio.timeout(10):
                while state.mqtt.published < 4:  # noqa: ASYNC110 - the sink's task counts
                    await asyncio.sleep(0)
    finally:
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task
    assert state.mqtt.published == 4  # two cycles of a value and a state document each
    for value, at in handed_over.items():
        out = [(topic, turn) for topic, payload, turn in sent if carries(topic, payload, value)]
        assert {topic for topic, _ in out} == {"gw/basin/concentration", "gw/basin/state"}
        assert all(turn - at <= 3 for _, turn in out), (value, at, out)


def carries(topic: str, payload: bytes, value: float) -> bool:
    """Whether a message of the sink is the value's own or its cycle's state document."""
    if topic == "gw/basin/concentration":
        return float(payload) == value
    if topic == "gw/basin/state":
        return bool(json.loads(payload)["values"]["concentration"] == value)
    return False
