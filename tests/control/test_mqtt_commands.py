"""Commands and feeds end to end: a real mosquitto, the gateway, the simulator on a pty.

A test publishes ``…/set`` and ``…/command/NAME`` as a plant system would, reads the
result topics, and checks against the simulator's write log and registers what reached
the sensors, and what did not.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import struct
from typing import TYPE_CHECKING, Any

import aiomqtt
import pytest

from gateway.publish.message import Message
from gateway.publish.prometheus import GatewayCollector
from gateway.publish.store import MessageStore
from tests.mqtt_broker import recording
from tests.publish.test_mqtt import gateway, simulated

if TYPE_CHECKING:
    from collections.abc import AsyncIterator, Callable
    from pathlib import Path

    from gateway.simulator import SimulatorServer
    from tests.mqtt_broker import Broker, Recorder

pytestmark = [pytest.mark.line, pytest.mark.broker]

SENSORS: list[dict[str, Any]] = [
    {"profile": "jumo-digiline-odo-s10", "address": 1, "animate": False},
    # Single measurements only (interval 0, H10 manual 0x201B): a measurement of its own
    # cycle would count beside the one a command triggers.
    {
        "profile": "jumo-digiline-odo-h10",
        "address": 2,
        "animate": False,
        "values": {"measurement_interval": 0},
    },
    {"profile": "reiss-m0c", "address": 10, "animate": False, "values": {"temperature": 17.5}},
]


def config(tmp_path: Path, port: int, *, feeds: str = "", commands: str = "") -> str:
    return (
        f"buses:\n  - {{name: line1, port: {tmp_path / 'ttySIM'}}}\n"
        "devices:\n"
        "  - {name: aeration, bus: line1, address: 1, profile: jumo-digiline-odo-s10,"
        " poll_interval: 0.5}\n"
        "  - {name: hygienic, bus: line1, address: 2, profile: jumo-digiline-odo-h10,"
        " poll_interval: 0.5}\n"
        "  - {name: basin, bus: line1, address: 10, profile: reiss-m0c, poll_interval: 0.5,"
        " flash_writes: [x_span], flash_write_budget: 1}\n"
        f"mqtt: {{host: 127.0.0.1, port: {port}, base_topic: gw, reconnect_max_s: 1}}\n"
        f"{commands}"
        f"{feeds}"
        "prometheus: {enabled: false}\n"
        f"state_dir: {tmp_path / 'state'}\n"
    )


def cdab(value: float) -> tuple[int, int]:
    high, low = struct.unpack(">HH", struct.pack(">f", value))
    return low, high


@contextlib.asynccontextmanager
async def publisher(port: int) -> AsyncIterator[aiomqtt.Client]:
    async with aiomqtt.Client("127.0.0.1", port, identifier="plant-system") as client:
        yield client


async def command(
    client: aiomqtt.Client,
    seen: Recorder,
    topic: str,
    payload: str,
) -> dict[str, Any]:
    """Publish a command and return its result document."""
    result = f"{topic}/result"
    before = len(seen.on(result))
    await client.publish(topic, payload, qos=1)
    await seen.wait_for(result, skip=before, within_s=15)
    document: dict[str, Any] = json.loads(seen.on(result)[before])
    return document


def writes(server: SimulatorServer, address: int) -> list[tuple[int, int, tuple[int, ...]]]:
    return [(w.function, w.address, w.values) for w in server.bus.devices[address].write_log]


async def test_set_commands_and_every_rejection(tmp_path: Path, broker: Broker) -> None:
    async with (
        simulated(tmp_path, SENSORS) as server,
        recording(broker.port, "gw/#") as seen,
        gateway(config(tmp_path, broker.port)) as state,
        publisher(broker.port) as client,
    ):
        await seen.wait_for("gw/basin/availability", "online")

        ok = await command(client, seen, "gw/aeration/compensation_temperature/set", "21.5")
        assert ok["status"] == "ok"
        assert ok["value"] == 21.5
        assert ok["written"] is True
        assert ok["id"] is None
        assert (ok["device"], ok["point"]) == ("aeration", "compensation_temperature")

        with_id = await command(
            client, seen, "gw/hygienic/compensation_pressure/set", '{"value": 1000, "id": "p-7"}'
        )
        assert (with_id["status"], with_id["id"], with_id["value"]) == ("ok", "p-7", 1000.0)

        flash = await command(client, seen, "gw/basin/x_span/set", '{"value": 55.5, "id": 1}')
        assert (flash["status"], flash["id"], flash["value"]) == ("ok", "1", 55.5)
        same = await command(client, seen, "gw/basin/x_span/set", "55.5")
        assert same["status"] == "ok"
        assert same["written"] is False
        assert same["note"] == "unchanged, not written"

        written_so_far = {a: writes(server, a) for a in (1, 2, 10)}
        rejections = {
            "gw/aeration/no_such_point/set": ("1", "no point 'no_such_point'"),
            "gw/aeration/oxygen/set": ("8.0", "read-only"),
            "gw/hygienic/compensation_temperature/set": ("120", "allowed range 0 to 99.99"),
            "gw/aeration/compensation_salinity/set": ("salty", "float32 needs a number"),
            "gw/aeration/description/set": ("x" * 200, "exceed the 192 bytes"),
            "gw/basin/x_zero/set": ("1.0", "flash-backed point not allowed for device basin"),
            "gw/aeration/oxygen_unit/set": ('{"value": "ppm", "id": 5', "malformed JSON"),
            "gw/nowhere/compensation_temperature/set": ("20", "no device 'nowhere'"),
        }
        for topic, (payload, reason) in rejections.items():
            refused = await command(client, seen, topic, payload)
            assert refused["status"] == "error", topic
            assert reason in refused["reason"], (topic, refused["reason"])
        budget = await command(client, seen, "gw/basin/x_span/set", '{"value": 60, "id": "b"}')
        assert budget["status"] == "error", budget
        assert budget["id"] == "b"
        assert "budget of 1 writes per day for basin/x_span is spent" in budget["reason"]
        assert {a: writes(server, a) for a in (1, 2, 10)} == written_so_far  # nothing more
        assert written_so_far == {
            1: [(16, 0x25B0, cdab(21.5))],
            2: [(16, 0x2017, cdab(1000.0))],
            10: [(16, 0x0208, cdab(55.5))],
        }
        outcomes = state.writes.outcomes
        assert outcomes["aeration", "set", "ok"] == 1
        assert outcomes["basin", "set", "unchanged"] == 1
        assert outcomes["basin", "set", "rejected"] == 2
        assert outcomes["unknown", "set", "rejected"] == 1
        assert server.bus.stats()["timing_violations"] == 0
        metrics = {m.name: m for m in GatewayCollector(state).collect()}
        flash_total = metrics["gateway_flash_writes"].samples
        assert [(s.labels, s.value) for s in flash_total if s.name.endswith("_total")] == [
            ({"device": "basin", "point": "x_span"}, 1.0)
        ]
        assert [(s.labels, s.value) for s in metrics["gateway_flash_write_budget"].samples] == [
            ({"device": "basin", "point": "x_span"}, 1.0)
        ]


async def test_flash_budget_and_counter_survive_a_restart(tmp_path: Path, broker: Broker) -> None:
    async with (
        simulated(tmp_path, SENSORS) as server,
        recording(broker.port, "gw/#") as seen,
        publisher(broker.port) as client,
    ):
        async with gateway(config(tmp_path, broker.port)):
            await seen.wait_for("gw/basin/availability", "online")
            first = await command(client, seen, "gw/basin/x_span/set", "55.5")
            assert first["written"] is True
        # Left retained while the gateway is away: the broker hands it over again at the
        # next subscription, flagged retained, and the gateway refuses it.
        await client.publish("gw/aeration/compensation_temperature/set", "30", retain=True)
        async with gateway(config(tmp_path, broker.port)) as state:
            result = "gw/aeration/compensation_temperature/set/result"
            await seen.wait_for(result)
            retained = json.loads(seen.on(result)[0])
            assert retained["status"] == "error"
            assert "retained command" in retained["reason"]
            await client.publish("gw/aeration/compensation_temperature/set", b"", retain=True)
            await seen.wait_for("gw/basin/availability", "online", skip=1)
            again = await command(client, seen, "gw/basin/x_span/set", "58")
            assert again["status"] == "error"
            assert "budget of 1 writes per day" in again["reason"]
            metrics = {m.name: m for m in GatewayCollector(state).collect()}
            today = metrics["gateway_flash_writes_today"].samples
            assert [(s.labels, s.value) for s in today] == [
                ({"device": "basin", "point": "x_span"}, 1.0)
            ]
        assert writes(server, 10) == [(16, 0x0208, cdab(55.5))]
        assert writes(server, 1) == []


async def test_commands_can_be_switched_off(tmp_path: Path, broker: Broker) -> None:
    off = "commands: {enabled: false}\n"
    async with (
        simulated(tmp_path, SENSORS) as server,
        recording(broker.port, "gw/#") as seen,
        gateway(config(tmp_path, broker.port, commands=off)),
        publisher(broker.port) as client,
    ):
        await seen.wait_for("gw/aeration/availability", "online")
        await client.publish("gw/aeration/compensation_temperature/set", "21.5", qos=1)
        await asyncio.sleep(1.0)
        assert seen.on("gw/aeration/compensation_temperature/set/result") == []
        assert writes(server, 1) == []


async def test_a_command_sent_at_online_is_run_while_the_backlog_drains(
    tmp_path: Path, broker: Broker, caplog: pytest.LogCaptureFixture
) -> None:
    """``online`` means commands are heard: the gateway subscribes before it says so.

    A broker restart leaves a backlog on disk; a plant system that sends a command the
    moment it sees ``online`` must not lose it to a subscription made only after the
    backlog is sent (a clean session drops what arrives before).
    """
    backlog = MessageStore(tmp_path / "state" / "mqtt-queue.sqlite", max_messages=100_000)
    backlog.append([Message.text("gw/backlog", str(i)) for i in range(5_000)])
    backlog.close()
    async with (
        simulated(tmp_path, SENSORS) as server,
        recording(broker.port, "gw/+/+/set/result") as seen,
        publisher(broker.port) as client,
    ):
        await client.subscribe("gw/status", qos=1)
        async with gateway(config(tmp_path, broker.port)) as state:
            async with asyncio.timeout(15):
                async for message in client.messages:
                    if message.payload == b"online":
                        break
            backlog_left = state.mqtt.queue_depth
            topic = "gw/aeration/compensation_temperature/set"
            result = await command(client, seen, topic, '{"value": 22.5, "id": "at-once"}')
        assert backlog_left > 0, "the command went out while the backlog drained"
        assert (result["status"], result["id"], result["value"]) == ("ok", "at-once", 22.5)
        assert writes(server, 1) == [(16, 0x25B0, cdab(22.5))]
    # The drain keeps 16 publishes in flight by design: no warning about it per message.
    assert not [r for r in caplog.records if "pending publish calls" in r.getMessage()]


async def test_feeds_keep_compensation_values_current(tmp_path: Path, broker: Broker) -> None:
    feeds = (
        "feeds:\n"
        "  - {device: aeration, point: compensation_temperature, interval: 60, deadband: 0.2,"
        " source: {device: basin, point: temperature}}\n"
        "  - {device: hygienic, point: compensation_pressure, interval: 60,"
        " source: {topic: plant/air/pressure}}\n"
    )
    async with (
        simulated(tmp_path, SENSORS) as server,
        recording(broker.port, "gw/#") as seen,
        gateway(config(tmp_path, broker.port, feeds=feeds)) as state,
        publisher(broker.port) as client,
    ):
        await seen.wait_for("gw/basin/temperature", "17.5")
        s10 = server.bus.devices[1]
        await _until(lambda: len(writes(server, 1)) >= 2)
        # The value first, then the control byte's RAM bit: the sensor never computes
        # with a stale RAM value.
        assert writes(server, 1) == [(16, 0x25B0, cdab(17.5)), (6, 0x25AF, (0b001,))]
        server.bus.devices[10].hold("temperature", 17.6)  # within the deadband: no write
        await asyncio.sleep(1.5)
        assert len(writes(server, 1)) == 2
        server.bus.devices[10].hold("temperature", 18.0)  # beyond it: written at once
        await _until(lambda: s10.get("compensation_temperature") == 18.0)
        assert writes(server, 1)[2:] == [(16, 0x25B0, cdab(18.0))]  # the bit is set already

        await client.publish("plant/air/pressure", '{"value": 987.5}', qos=1)
        h10 = server.bus.devices[2]
        await _until(lambda: h10.get("compensation_pressure") == 987.5)
        assert writes(server, 2) == [(16, 0x2017, cdab(987.5))]
        await client.publish("plant/air/pressure", "not a number", qos=1)
        await _until(lambda: state.writes.feeds["hygienic/compensation_pressure"].errors == 1)
        assert state.writes.feeds["aeration/compensation_temperature"].writes == 2
        assert server.bus.stats()["timing_violations"] == 0


async def _until(condition: Callable[[], bool], within_s: float = 10.0) -> None:
    deadline = asyncio.get_running_loop().time() + within_s
    while not condition():
        if asyncio.get_running_loop().time() > deadline:
            raise AssertionError("the condition did not come true in time")
        await asyncio.sleep(0.05)


@pytest.mark.timing
async def test_a_stale_feed_hands_the_sensor_back_its_own_source(
    tmp_path: Path, broker: Broker
) -> None:
    feeds = (
        "feeds:\n"
        "  - {device: aeration, point: compensation_temperature, interval: 60, max_age: 1.5,"
        " source: {topic: plant/basin/temperature}}\n"
        "  - {device: hygienic, point: compensation_temperature, interval: 60, max_age: 1.5,"
        " source: {topic: plant/basin/temperature, key: celsius}}\n"
    )
    async with (
        simulated(tmp_path, SENSORS) as server,
        recording(broker.port, "gw/#") as seen,
        gateway(config(tmp_path, broker.port, feeds=feeds)) as state,
        publisher(broker.port) as client,
    ):
        await seen.wait_for("gw/aeration/availability", "online")
        await client.publish("plant/basin/temperature", '{"value": 16.0, "celsius": 16.5}')
        await _until(lambda: len(writes(server, 1)) == 2 and len(writes(server, 2)) == 1)
        # No newer value: after max_age the S10's RAM bit is cleared (control byte read,
        # bit 0 cleared, the rest kept) and the H10 gets 0x201F, its own temperature.
        await _until(lambda: len(writes(server, 1)) == 3 and len(writes(server, 2)) == 2)
        assert writes(server, 1) == [
            (16, 0x25B0, cdab(16.0)),
            (6, 0x25AF, (0b001,)),
            (6, 0x25AF, (0b000,)),
        ]
        assert writes(server, 2) == [(16, 0x2013, cdab(16.5)), (16, 0x201F, (0, 1))]
        # The simulator logs a write before the gateway has its echo and has waited
        # the post-write time: the feed's own state follows a little later.
        feed = state.writes.feeds["aeration/compensation_temperature"]
        await _until(
            lambda: feed.fallback and state.writes.outcomes["hygienic", "feed", "fallback"] > 0
        )
        assert (feed.stale, feed.fallback) == (True, True)
        assert state.writes.outcomes["hygienic", "feed", "fallback"] == 1
        # A fresh value: the feed writes again and selects RAM again.
        await client.publish("plant/basin/temperature", '{"value": 16.2, "celsius": 16.7}')
        await _until(lambda: len(writes(server, 1)) == 5)
        assert writes(server, 1)[3:] == [(16, 0x25B0, cdab(16.2)), (6, 0x25AF, (0b001,))]
        await _until(lambda: not feed.fallback)
        assert (feed.stale, feed.fallback) == (False, False)
        assert server.bus.stats()["timing_violations"] == 0


async def test_operations_as_mqtt_commands(tmp_path: Path, broker: Broker) -> None:
    async with (
        simulated(tmp_path, SENSORS) as server,
        recording(broker.port, "gw/#") as seen,
        gateway(config(tmp_path, broker.port)) as state,
        publisher(broker.port) as client,
    ):
        await seen.wait_for("gw/hygienic/availability", "online")
        h10 = server.bus.devices[2]
        counter = h10.get("measurement_counter")
        measured = await command(client, seen, "gw/hygienic/command/measure", '{"id": "m1"}')
        assert (measured["status"], measured["id"], measured["command"]) == ("ok", "m1", "measure")
        assert measured["result"]["oxygen"] == h10.get("oxygen")
        assert h10.get("measurement_counter") == counter + 1  # type: ignore[operator]
        assert (16, 0x3001, (0, 5)) in writes(server, 2)  # bit 2 set, bit 0 kept

        log = await command(client, seen, "gw/basin/command/calibration_log", "")
        assert log["status"] == "ok"
        assert log["result"]["kind"] == "history"

        clock = await command(client, seen, "gw/aeration/command/set_clock", "{}")
        assert clock["status"] == "ok"
        assert abs(clock["result"]["offset_after_s"]) < 2.0
        [clock_write] = [w for w in writes(server, 1) if w[1] == 0x2840]
        assert clock_write[0] == 16

        before = {a: writes(server, a) for a in (1, 2, 10)}
        refusals = {
            "gw/basin/command/measure": "does not apply to profile reiss-m0c",
            "gw/hygienic/command/self_destruct": "self_destruct",
            "gw/hygienic/command/measure": "malformed JSON",
        }
        for topic, reason in refusals.items():
            payload = "{oops" if topic.endswith("measure") and "hygienic" in topic else ""
            refused = await command(client, seen, topic, payload)
            assert refused["status"] == "error", topic
            assert reason in refused["reason"], (topic, refused["reason"])
        assert {a: writes(server, a) for a in (1, 2, 10)} == before
        assert state.writes.outcomes["hygienic", "command", "ok"] == 1
        assert state.writes.outcomes["hygienic", "command", "rejected"] == 2
        assert server.bus.stats()["timing_violations"] == 0
