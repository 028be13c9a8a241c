"""Several brokers, one at a time, and one identity per gateway: with real mosquittos.

``mqtt.servers`` lists three brokers; the first is down at the start, the second is stopped
while the gateway publishes, the first comes back: the gateway moves down the list and back,
and every state document of the run reaches one broker or another, in order (each device's
``seq`` has no gap). Two gateways started from a copied config: the second stands down
within seconds, the first publishes on (publish/mqtt/identity).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import time
from typing import TYPE_CHECKING

import aiomqtt
import paho.mqtt.client as paho
import pytest
from paho.mqtt.enums import CallbackAPIVersion

from tests.mqtt_broker import Broker, Recorder, recording
from tests.nats_cluster import retained_on
from tests.publish.test_mqtt import gateway, simulated
from tests.waiting import eventually

if TYPE_CHECKING:
    from collections.abc import AsyncIterator
    from pathlib import Path

    from gateway.shared.state import GatewayState

STATE = "gw/basin/state"


def config(tmp_path: Path, servers: list[Broker], *, extra: str = "", state: str = "state") -> str:
    """A gateway of the two simulated sensors on the given brokers, in order."""
    listed = ", ".join(f"{{host: 127.0.0.1, port: {b.port}}}" for b in servers)
    return (
        f"buses:\n  - {{name: line1, port: {tmp_path / 'ttySIM'}}}\n"
        "devices:\n"
        "  - {name: basin, bus: line1, address: 10, profile: reiss-m0c, poll_interval: 0.3}\n"
        f"mqtt: {{servers: [{listed}], base_topic: gw, reconnect_max_s: 1{extra}}}\n"
        "prometheus: {enabled: false}\n"
        f"state_dir: {tmp_path / state}\n"
    )


def brokers(tmp_path: Path, *names: str) -> list[Broker]:
    made = []
    for name in names:
        directory = tmp_path / f"broker-{name}"
        directory.mkdir()
        made.append(Broker(directory))
    return made


def vanish_leaving_a_will(port: int, topic: str, payload: str) -> None:
    """A client that connects with a retained will and closes its socket without a
    DISCONNECT: the broker publishes the will."""
    client = paho.Client(CallbackAPIVersion.VERSION2, client_id="vanishing")
    client.will_set(topic, payload, qos=1, retain=True)
    client.connect("127.0.0.1", port, keepalive=60)
    deadline = time.monotonic() + 5
    while not client.is_connected():
        assert time.monotonic() < deadline, "no CONNACK"
        client.loop(timeout=0.1)
    sock = client.socket()
    assert sock is not None
    sock.close()


def seqs(*recorders: Recorder) -> list[int]:
    """Every ``seq`` of the state documents the recorders got, each once, in order."""
    return sorted({json.loads(p)["seq"] for r in recorders for p in r.on(STATE)})


def gaps(numbers: list[int]) -> list[int]:
    return [n for n in range(numbers[0], numbers[-1]) if n not in set(numbers)] if numbers else []


@pytest.mark.line
@pytest.mark.broker
async def test_the_next_server_takes_over_and_the_first_comes_back_losing_nothing(
    tmp_path: Path,
) -> None:
    a, b, c = brokers(tmp_path, "a", "b", "c")
    address = {x.port: f"127.0.0.1:{x.port}" for x in (a, b, c)}
    text = config(tmp_path, [a, b, c], extra=", return_to_first_s: 10")
    try:
        b.start()
        c.start()
        async with (
            simulated(tmp_path),
            recording(b.port, "gw/#", name="on-b") as on_b,
            recording(c.port, "gw/#", name="on-c") as on_c,
            gateway(text) as state,
        ):
            mqtt = state.mqtt
            # The first refuses: the second at once (no backoff within a round).
            await eventually(lambda: mqtt.connected and mqtt.server == address[b.port], within_s=10)
            assert mqtt.servers == tuple(address[x.port] for x in (a, b, c))
            assert mqtt.switches == 1
            await eventually(lambda: len(on_b.on(STATE)) >= 3, within_s=10)
            b.stop()
            await eventually(lambda: mqtt.connected and mqtt.server == address[c.port], within_s=10)
            await eventually(lambda: len(on_c.on(STATE)) >= 3, within_s=10)
            a.start()
            async with recording(a.port, "gw/#", name="on-a") as on_a:
                # Ten seconds on the third, then home to the first.
                await eventually(
                    lambda: mqtt.connected and mqtt.server == address[a.port], within_s=25
                )
                assert mqtt.switches == 3
                await eventually(lambda: len(on_a.on(STATE)) >= 3, within_s=10)
                # The third was told the gateway left it; the first has it online.
                assert on_c.on("gw/status")[-1] == "offline"
                assert on_a.on("gw/status")[-1] == "online"
                assert json.loads(on_a.on("gw/owner")[-1])["client_id"]
                # What the second took before it stopped reaches its recorder once it is
                # back (its persistence kept the recorder's session).
                b.start()
                await eventually(lambda: not gaps(seqs(on_a, on_b, on_c)), within_s=15)
            numbers = seqs(on_a, on_b, on_c)
            assert numbers[0] == 1, numbers[:5]
            assert len(numbers) >= 9
            # In order on each broker (a repeat allowed, QoS 1: one in flight at a switch).
            for recorder in (on_a, on_b, on_c):
                got = [json.loads(p)["seq"] for p in recorder.on(STATE)]
                assert got == sorted(got), got
    finally:
        for x in (a, b, c):
            x.stop()


@pytest.mark.line
@pytest.mark.broker
@pytest.mark.parametrize("client_ids", ["same", "own"])
async def test_a_copied_config_stands_down_and_the_first_gateway_publishes_on(
    tmp_path: Path, broker: Broker, client_ids: str
) -> None:
    """A copied config: one base topic, the same client id (sessions taken over) or not."""
    first_dir, second_dir = tmp_path / "first", tmp_path / "second"
    first_dir.mkdir()
    second_dir.mkdir()
    first_text = config(first_dir, [broker], extra=", client_id: cab-1")
    second_id = "cab-1" if client_ids == "same" else "cab-2"
    second_text = config(second_dir, [broker], extra=f", client_id: {second_id}")
    async with (
        simulated(first_dir),
        simulated(second_dir),
        recording(broker.port, "gw/#", name="watcher") as seen,
        gateway(first_text) as first,
    ):
        await eventually(lambda: first.mqtt.connected, within_s=10)
        await seen.wait_for("gw/owner")
        holder = json.loads(seen.on("gw/owner")[-1])["start_id"]
        loop = asyncio.get_running_loop()
        async with gateway(second_text) as second:
            started = loop.time()
            await eventually(lambda: second.mqtt.identity_conflict is not None, within_s=60)
            stood_down_s = loop.time() - started
            conflict = second.mqtt.identity_conflict or ""
            assert "cab-1" in conflict  # it names the holder
            assert "mqtt.base_topic" in conflict  # and what to change
            assert second.mqtt.healthy is False
            # The first is connected and publishing, and holds the marker.
            await eventually(lambda: first.mqtt.connected, within_s=10)
            count = len(seen.on(STATE))
            await eventually(lambda: len(seen.on(STATE)) >= count + 3, within_s=10)
            assert first.mqtt.identity_conflict is None
            assert first.mqtt.healthy is True
            assert second.mqtt.connected is False
            await eventually(
                lambda: json.loads(seen.on("gw/owner")[-1])["start_id"] == holder, within_s=10
            )
            # What the second may have written over before it stood down (its will's
            # offline too, if its connection closed uncleanly) is the first's again.
            head_of = first.writes.records_head  # the first's head of the moment
            assert head_of is not None
            wanted = {"gw/status", "gw/records/head", "gw/basin/availability"}
            # The watcher gets every message in the broker's order: the last of a topic is
            # what is retained.
            await eventually(
                lambda: (
                    seen.on("gw/status")[-1] == "online"
                    and json.loads(seen.on("gw/records/head")[-1])["hash"] == head_of().hash
                ),
                within_s=10,
            )
            node = ("127.0.0.1", broker.port)
            retained = await retained_on(node, ["gw/#"], wanted, within_s=5)
            assert retained["gw/status"] == b"online"
            assert json.loads(retained["gw/records/head"])["hash"] == head_of().hash
            assert retained["gw/basin/availability"] == b"online"
    print(f"stood down after {stood_down_s:.2f} s ({client_ids} client id)")  # noqa: T201
    assert stood_down_s < 60


@contextlib.asynccontextmanager
async def connected_gateway(
    tmp_path: Path, broker: Broker, topic_filter: str
) -> AsyncIterator[tuple[Recorder, GatewayState]]:
    """One gateway (client id ``cab-1``) on ``broker``, connected, watched on ``topic_filter``."""
    (tmp_path / "cab").mkdir()
    text = config(tmp_path / "cab", [broker], extra=", client_id: cab-1")
    async with (
        simulated(tmp_path / "cab"),
        recording(broker.port, topic_filter, name="watcher") as seen,
        gateway(text) as state,
    ):
        await eventually(lambda: state.mqtt.connected, within_s=10)
        yield seen, state


@pytest.mark.line
@pytest.mark.broker
async def test_an_offline_said_for_a_connected_gateway_is_answered_online(
    tmp_path: Path, broker: Broker
) -> None:
    """Another client's last will on ``{base}/status`` (a copied config's gateway whose
    connection closed uncleanly after it stood down) would leave Home Assistant showing a
    running gateway's entities unavailable: the gateway says ``online`` again."""
    async with connected_gateway(tmp_path, broker, "gw/status") as (seen, _):
        await seen.wait_for("gw/status", "online")
        said = len(seen.on("gw/status"))
        await asyncio.to_thread(vanish_leaving_a_will, broker.port, "gw/status", "offline")
        await seen.wait_for("gw/status", "offline", skip=said)
        await seen.wait_for("gw/status", "online", within_s=5, skip=said + 1)
        node = ("127.0.0.1", broker.port)
        assert (await retained_on(node, ["gw/status"], {"gw/status"}, within_s=5)) == {
            "gw/status": b"online"
        }
        assert seen.on("gw/status")[said:] == ["offline", "online"]  # answered once


@pytest.mark.line
@pytest.mark.broker
async def test_a_flood_of_claims_and_offlines_is_answered_without_amplifying_it(
    tmp_path: Path, broker: Broker
) -> None:
    """A careless or hostile client publishing claims on ``{base}/owner`` and ``offline``
    on ``{base}/status`` live: each claim is defended, the retained state goes again once
    (not once per claim), the status ends ``online`` and the gateway publishes on."""
    async with connected_gateway(tmp_path, broker, "gw/#") as (seen, state):
        await seen.wait_for("gw/basin/availability", "online")
        availability = len(seen.on("gw/basin/availability"))
        claims = 50
        async with aiomqtt.Client("127.0.0.1", broker.port, identifier="flooder") as flooder:
            for n in range(claims):
                claim = {"start_id": f"fake{n:03d}", "client_id": "x", "host": "h", "pid": n}
                await flooder.publish("gw/owner", json.dumps(claim), qos=1)
                await flooder.publish("gw/status", "offline", qos=1, retain=True)

        def defences() -> list[str]:
            return [
                p for p in seen.on("gw/owner") if "fake" in json.loads(p).get("contested_by", "")
            ]

        await eventually(lambda: len(defences()) == claims, within_s=20)
        await eventually(lambda: seen.on("gw/status")[-1] == "online", within_s=10)
        documents = len(seen.on(STATE))
        await eventually(lambda: len(seen.on(STATE)) >= documents + 3, within_s=10)
        assert len(seen.on("gw/basin/availability")) <= availability + 1  # sent again once
        assert state.mqtt.connected


@pytest.mark.line
@pytest.mark.broker
async def test_the_next_server_gets_the_retained_discovery_availability_and_values(
    tmp_path: Path,
) -> None:
    """Separate servers share no retained messages: after a switch the gateway sends its
    discovery configs, availability and records head again at once, and every value at the
    next cycle, even one published on change only (the simulator's values do not change)."""
    a, b = brokers(tmp_path, "a", "b")
    listed = ", ".join(f"{{host: 127.0.0.1, port: {x.port}}}" for x in (a, b))
    text = (
        f"buses:\n  - {{name: line1, port: {tmp_path / 'ttySIM'}}}\n"
        "devices:\n"
        "  - {name: basin, bus: line1, address: 10, profile: reiss-m0c, poll_interval: 0.3,"
        " publish: {mode: on_change}}\n"
        f"mqtt: {{servers: [{listed}], base_topic: gw, reconnect_max_s: 1,"
        " return_to_first_s: null, discovery: {enabled: true}}\n"
        "prometheus: {enabled: false}\n"
        f"state_dir: {tmp_path / 'state'}\n"
    )
    try:
        a.start()
        b.start()
        async with (
            simulated(tmp_path),
            recording(a.port, "#", name="on-a") as seen_a,
            recording(b.port, "#", name="on-b") as seen_b,
            gateway(text) as state,
        ):
            mqtt = state.mqtt
            await eventually(
                lambda: mqtt.connected and mqtt.server.endswith(f":{a.port}"), within_s=10
            )
            values = {"gw/basin/availability", "gw/basin/concentration", "gw/records/head"}
            await eventually(lambda: all(seen_a.on(t) for t in values), within_s=10)
            await eventually(lambda: seen_a.on("gw/basin/care"), within_s=10)  # care's configs too
            configs = {m.topic for m in seen_a.messages if m.topic.startswith("homeassistant/")}
            assert len(configs) >= 3, configs  # the device's entities and its care's
            on_a = await retained_on(("127.0.0.1", a.port), ["#"], configs | values, within_s=10)
            a.stop()
            await eventually(
                lambda: mqtt.connected and mqtt.server.endswith(f":{b.port}"), within_s=10
            )
            wanted = configs | values
            await eventually(lambda: all(seen_b.on(t) for t in wanted), within_s=10)
            on_b = await retained_on(("127.0.0.1", b.port), ["#"], wanted, within_s=10)
            assert sorted(wanted - on_b.keys()) == []
            assert on_b["gw/basin/availability"] == b"online"
            assert on_b["gw/basin/concentration"] == on_a["gw/basin/concentration"]
            assert all(on_b[t] == on_a[t] for t in configs)  # the same configs, byte for byte
            head_a, head_b = (json.loads(x["gw/records/head"]) for x in (on_a, on_b))
            assert (head_b["seq"], head_b["hash"]) == (head_a["seq"], head_a["hash"])
    finally:
        for x in (a, b):
            x.stop()
