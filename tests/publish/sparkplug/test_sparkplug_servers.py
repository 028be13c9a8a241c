"""Sparkplug with several MQTT servers, and one identity per gateway: with real mosquittos.

Three mosquittos, each with a primary host's client on it that publishes the host's STATE
(retained, QoS 1, with its own timestamps, one series per server as a host keeps them) and
hears everything under ``spBv1.0/#``. Every payload it hears is read by Eclipse Tahu's
JavaScript ``sparkplug-payload`` (the decoder of ``test_sparkplug_tahu``), not by the
gateway's encoder; each broker also says how many clients it has (``$SYS``). The gateway
runs in the test's process as ``gateway run`` runs it (as the other Sparkplug tests drive
it), on simulated sensors, with the three in ``sparkplug.servers`` and a
``primary_host_id``. Test docstrings name the Sparkplug 3.0 statements they prove.

Then two gateways from one config on one mosquitto, Sparkplug on: the second stands down
on both of its connections, and the host never sees the first node die
(``gateway.publish.sparkplug.identity``). Last, without a broker: the identity gate, two
endings of a session at once, and the plain sender's stop while its backlog drains (which
the copied-config test found lost).
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import json
import logging
import time
from collections import deque
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import aiomqtt
import pytest

from gateway.config import parse_config
from gateway.publish.message import Message
from gateway.publish.mqtt.outbox import Outbox
from gateway.publish.prometheus import health_report
from gateway.publish.sparkplug import SparkplugSink
from gateway.publish.sparkplug.identity import GatewayIdentity, IdentityConflictError
from gateway.publish.sparkplug.session import HostOfflineError, SparkplugSession, _deciding
from gateway.publish.sparkplug.topics import SparkplugTopics
from gateway.publish.store import MessageStore
from gateway.shared.state import GatewayState, MqttStatus, SparkplugStatus
from tests.mqtt_broker import Broker
from tests.publish.sparkplug.test_sparkplug_tahu import HOST_JS, NODE_JS, tahu_encode
from tests.publish.test_mqtt import gateway, simulated
from tests.waiting import eventually

if TYPE_CHECKING:
    from collections.abc import AsyncIterator, Sequence
    from pathlib import Path

GROUP, EDGE, HOST = "plant", "gw1", "scada"
NODE = f"spBv1.0/{GROUP}"
STATE_TOPIC = f"spBv1.0/STATE/{HOST}"
CLIENTS_TOPIC = "$SYS/broker/clients/connected"
ANIMATED = [
    {"profile": "jumo-digiline-odo-s10", "address": 1, "animate": True},
    {"profile": "reiss-m0c", "address": 10, "animate": True},
]


# --- a host's view of three servers --------------------------------------------------------


@dataclass
class Heard:
    """One message a host's client heard on one server, and Tahu's reading of it."""

    server: str
    topic: str
    payload: bytes
    at: float = field(default_factory=time.monotonic)
    tahu: dict[str, Any] | None = None  # filled when the decoder has answered

    @property
    def kind(self) -> str:
        parts = self.topic.split("/")
        return "STATE" if parts[1] == "STATE" else parts[2]

    def read(self) -> dict[str, Any]:
        """The payload as Tahu's ``decodePayload`` reads it."""
        assert self.tahu is not None, f"Tahu has not read {self.topic} yet"
        assert "error" not in self.tahu, self.tahu
        payload: dict[str, Any] = self.tahu["payload"]
        return payload

    def metrics(self) -> dict[str, dict[str, Any]]:
        return {m["name"]: m for m in self.read().get("metrics", []) if "name" in m}

    @property
    def bd_seq(self) -> int:
        metric = self.metrics()["bdSeq"]
        assert metric["type"] == "Int64"
        return int(metric["value"])

    @property
    def seq(self) -> int | None:
        seq = self.read().get("seq")
        return None if seq is None else int(seq)

    def historical(self) -> bool:
        """Whether a data message carries stored values (``is_historical``)."""
        assert self.tahu is not None
        return any(m.get("isHistorical") for m in self.tahu["raw"].get("metrics", []))

    def state(self) -> dict[str, Any]:
        data: dict[str, Any] = json.loads(self.payload)
        return data


class TahuReader:
    """One node process with Tahu's decoder for every server's messages, answering in order."""

    def __init__(self, process: asyncio.subprocess.Process) -> None:
        self.process = process
        self.waiting: deque[Heard] = deque()
        assert process.stdout is not None
        self.task = asyncio.create_task(self._answers(process.stdout), name="tahu-reader")

    @classmethod
    async def start(cls) -> TahuReader:
        assert NODE_JS, "node is missing: scripts/setup test installs it (as root)"
        installed = HOST_JS.parent / "node_modules" / "sparkplug-payload"
        assert installed.is_dir(), "Tahu's sparkplug-payload is missing: run scripts/setup test"
        process = await asyncio.create_subprocess_exec(
            NODE_JS,
            str(HOST_JS),
            "decode",
            stdin=asyncio.subprocess.PIPE,
            stdout=asyncio.subprocess.PIPE,
        )
        return cls(process)

    def read(self, heard: Heard) -> None:
        assert self.process.stdin is not None
        self.waiting.append(heard)
        self.process.stdin.write(f"{heard.topic} {heard.payload.hex()}\n".encode())

    async def _answers(self, stdout: asyncio.StreamReader) -> None:
        async for line in stdout:
            self.waiting.popleft().tahu = json.loads(line)

    async def close(self) -> None:
        assert self.process.stdin is not None
        self.process.stdin.close()
        await asyncio.wait_for(self.process.wait(), timeout=10)  # its input ended
        await asyncio.wait_for(self.task, timeout=10)


@dataclass
class Server:
    """One mosquitto, and the primary host's client on it (publishes STATE, hears all)."""

    name: str
    broker: Broker
    reader: TahuReader
    heard: list[Heard] = field(default_factory=list)
    clients: list[int] = field(default_factory=list)  # the broker's $SYS count, as it said it
    host: aiomqtt.Client | None = None

    @property
    def address(self) -> str:
        return f"127.0.0.1:{self.broker.port}"

    def node(self, kind: str | None = None, *, since: int = 0) -> list[Heard]:
        """The edge node's messages (of ``kind``), from the ``since``-th message heard."""
        return [h for h in self.heard[since:] if h.kind != "STATE" and kind in {None, h.kind}]

    async def say(self, *, online: bool, timestamp: int, host: str = HOST) -> None:
        """The host's STATE on this server, as a host publishes it (retained, QoS 1)."""
        assert self.host is not None
        payload = json.dumps({"online": online, "timestamp": timestamp})
        await self.host.publish(f"spBv1.0/STATE/{host}", payload, qos=1, retain=True)

    @contextlib.asynccontextmanager
    async def listening(self) -> AsyncIterator[None]:
        async with aiomqtt.Client("127.0.0.1", self.broker.port, identifier=HOST) as client:
            await client.subscribe("spBv1.0/#", qos=1)
            await client.subscribe(CLIENTS_TOPIC, qos=1)
            self.host = client

            async def hear() -> None:
                async for message in client.messages:
                    payload = message.payload
                    assert isinstance(payload, bytes)
                    if message.topic.value == CLIENTS_TOPIC:
                        self.clients.append(int(payload))
                        continue
                    heard = Heard(self.name, message.topic.value, payload)
                    self.heard.append(heard)
                    self.reader.read(heard)

            task = asyncio.create_task(hear(), name=f"host-on-{self.name}")
            try:
                yield
            finally:
                task.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await task
                self.host = None


@contextlib.asynccontextmanager
async def servers(tmp_path: Path, names: str = "abc") -> AsyncIterator[list[Server]]:
    """A mosquitto per name, each with the host's client on it; stopped whatever happens."""
    brokers = []
    for name in names:
        directory = tmp_path / f"broker-{name}"
        directory.mkdir()
        # $SYS every second (its client count); its log of connections is kept beside it,
        # for a failure's post-mortem.
        connections = ["log_type error", "log_type warning", "log_type notice"]
        extra = ["sys_interval 1", f"log_dest file {directory}/mosquitto.log", *connections]
        brokers.append(Broker(directory, extra=extra))
    reader = await TahuReader.start()
    made = [Server(name, broker, reader) for name, broker in zip(names, brokers, strict=True)]
    try:
        async with contextlib.AsyncExitStack() as stack:
            for server in made:
                server.broker.start()
                await stack.enter_async_context(server.listening())
            yield made
    finally:
        for broker in brokers:
            broker.stop()
        await reader.close()


async def all_read(*on: Server) -> None:
    """Until Tahu has read everything the servers' host clients heard."""
    await eventually(lambda: all(h.tahu is not None for s in on for h in s.heard), within_s=15)


def host_clock_ms() -> int:
    """The host's own clock, as it stamps its STATE (UTC milliseconds)."""
    return int(time.time() * 1000)


def edge_yaml(
    tmp_path: Path,
    on: Sequence[Server],
    *,
    host_wait_s: float = 30.0,
    host: str | None = HOST,
    mqtt: str = "{enabled: false, reconnect_max_s: 1, return_to_first_s: null}",
) -> str:
    """The two animated sensors as edge node plant/gw1 on the servers, in order."""
    listed = ", ".join(f"{{host: 127.0.0.1, port: {s.broker.port}}}" for s in on)
    primary = f", primary_host_id: {host}, host_wait_s: {host_wait_s}" if host else ""
    return (
        f"buses:\n  - {{name: line1, port: {tmp_path / 'ttySIM'}}}\n"
        "devices:\n"
        "  - {name: aeration, bus: line1, address: 1, profile: jumo-digiline-odo-s10,"
        " poll_interval: 0.3, offline_after: 2}\n"
        "  - {name: basin, bus: line1, address: 10, profile: reiss-m0c, poll_interval: 0.3}\n"
        f"mqtt: {mqtt}\n"
        f"sparkplug: {{enabled: true, group_id: {GROUP}, edge_node_id: {EDGE}{primary},"
        f" servers: [{listed}]}}\n"
        "prometheus: {enabled: false}\n"
        f"state_dir: {tmp_path / 'state'}\n"
    )


# The host's clients stamp a message when this process reads it. Two servers' messages
# that waited in their sockets while the process was held (a loaded machine) are read in
# one pass of the loop, in either order: the node's last message on the server it left can
# be stamped just after its first on the next, though it was sent a connection earlier.
READ_SLACK_S = 0.5


def on_one_server_at_a_time(*on: Server) -> list[str]:
    """The servers the node stayed on, in order, each stay ended by an NDEATH.

    A server's own messages reach its client in the order the node sent them; each stay
    there runs up to and including an NDEATH. The stays of all servers are ordered by
    their first message, and a stay may begin only once the one before it has ended (the
    node left that server before it spoke on the next): no message of the earlier stay is
    read later than the next one's first, beyond the reading slack above. Every stay but
    the last ends with an NDEATH.
    """
    stays: list[list[Heard]] = []
    for server in on:
        for message in server.node():
            if not stays or stays[-1][0].server != server.name or stays[-1][-1].kind == "NDEATH":
                stays.append([])
            stays[-1].append(message)
    stays.sort(key=lambda stay: stay[0].at)
    for before, after in itertools.pairwise(stays):
        assert before[-1].kind == "NDEATH", (before[0].server, before[-1].kind, after[0].server)
        overlap = before[-1].at - after[0].at
        assert overlap < READ_SLACK_S, (before[0].server, after[0].server, overlap)
    servers: list[str] = []
    for stay in stays:
        if not servers or servers[-1] != stay[0].server:
            servers.append(stay[0].server)
    return servers


def births_follow_online(server: Server) -> None:
    """On ``server``, each session's NBIRTH follows the host's STATE online there."""
    latest: dict[str, Any] | None = None
    born = False
    for heard in server.heard:
        if heard.kind == "STATE" and heard.topic == STATE_TOPIC:
            latest = heard.state()
        elif heard.kind == "NDEATH":
            born = False
        elif heard.kind == "NBIRTH" and not born:
            assert latest is not None, f"an NBIRTH on {server.name} before any STATE"
            assert latest["online"] is True, f"an NBIRTH on {server.name} after {latest}"
            born = True


# --- several servers -----------------------------------------------------------------------


@pytest.mark.line
@pytest.mark.broker
async def test_births_wait_for_the_hosts_online_state_on_the_one_server_in_use(
    tmp_path: Path,
) -> None:
    """tck-id-operational-behavior-edge-node-birth-sequence-wait, …-primary-application-…

    …state-with-multiple-servers-single-server and -state-subs; tck-id-message-flow-edge-
    node-birth-publish-phid-wait, -phid-wait-id, -phid-wait-online, -nbirth-payload-bdSeq.
    Connected to the first server, with no STATE of its host there (only another host's),
    the edge node publishes nothing and stores its data; the host's online STATE brings
    NBIRTH, the DBIRTHs, the stored history, then live data, on that server only. The
    brokers' own client counts show one connection of the node, on the first.
    """
    async with simulated(tmp_path, ANIMATED), servers(tmp_path) as (a, b, c):
        await a.say(online=True, timestamp=host_clock_ms(), host="other-host")
        async with gateway(edge_yaml(tmp_path, [a, b, c], host_wait_s=120)) as state:
            spb = state.sparkplug
            await eventually(lambda: spb.connected and spb.server == a.address, within_s=15)
            # Connected and polling: several cycles stored, nothing born, on any server.
            await eventually(lambda: spb.queue_depth >= 4, within_s=15)
            assert a.node() == []
            assert b.node() == []
            assert c.node() == []
            assert (spb.births, spb.host_online) == (0, False)
            await a.say(online=True, timestamp=host_clock_ms())
            # The births, then the history (until the queue is empty), then live data.
            await eventually(lambda: spb.births == 1 and not spb.queue_depth, within_s=20)
            live_from = len(a.heard)
            await eventually(lambda: len(a.node("DDATA", since=live_from)) >= 3, within_s=10)
            # One client on b and c (the host's), two on a (the host's and the node's).
            await eventually(lambda: (a.clients[-1:], b.clients[-1:]) == ([2], [1]), within_s=10)
            await eventually(lambda: c.clients[-1:] == [1], within_s=10)
            bd_seq = spb.bd_seq
        await eventually(lambda: a.node("NDEATH"), within_s=10)  # the clean stop's
        await all_read(a, b, c)
    assert b.node() == []
    assert c.node() == []
    assert on_one_server_at_a_time(a, b, c) == ["a"]
    births_follow_online(a)
    kinds = [h.kind for h in a.node()]
    assert kinds[:3] == ["NBIRTH", "DBIRTH", "DBIRTH"]
    assert kinds.count("NBIRTH") == 1
    nbirth = a.node("NBIRTH")[0]
    assert nbirth.seq == 0
    assert nbirth.bd_seq == bd_seq
    assert nbirth.metrics()["Node Control/Rebirth"]["value"] is False
    # The first data after the births is what was stored while the host was not there.
    assert a.node("DDATA")[0].historical()
    assert [h.bd_seq for h in a.node("NDEATH")] == [bd_seq]


@pytest.mark.line
@pytest.mark.broker
async def test_a_newer_offline_state_ends_the_session_and_the_edge_walks_on(
    tmp_path: Path,
) -> None:
    """tck-id-message-flow-edge-node-birth-publish-phid-offline, tck-id-operational-behavior-…

    …edge-node-termination-host-offline and -host-offline-reconnect, …-primary-application-
    state-with-multiple-servers-walk and -single-server, …-edge-node-birth-sequence-wait;
    bdSeq: tck-id-message-flow-edge-node-birth-publish-will-message-payload-bdSeq,
    tck-id-topics-nbirth-bdseq-increment, tck-id-payloads-nbirth-bdseq-repeat,
    tck-id-operational-behavior-data-commands-rebirth-action-3.

    The host's session on a server ends (its will: offline, with the timestamp of its
    birth there): the node publishes its NDEATH there, with the bdSeq of its NBIRTH, leaves
    with a DISCONNECT (no second NDEATH: the will is not delivered), and connects to the next
    server, where it waits for the host's online STATE. A to B to C and round to A; every
    CONNECT takes the next bdSeq, a rebirth (NCMD, encoded by Tahu) keeps it.
    """
    stamp = {name: host_clock_ms() + offset for offset, name in enumerate("abc")}
    async with simulated(tmp_path, ANIMATED), servers(tmp_path) as (a, b, c):
        await a.say(online=True, timestamp=stamp["a"])
        async with gateway(edge_yaml(tmp_path, [a, b, c])) as state:
            spb = state.sparkplug
            # A: born.
            await eventually(lambda: len(a.node("DDATA")) >= 3, within_s=20)
            first = spb.bd_seq

            async def host_leaves(here: Server, there: Server) -> None:
                """The host's will on ``here``; the node moves to ``there`` and waits."""
                since = len(there.heard)
                await here.say(online=False, timestamp=stamp[here.name])
                await eventually(lambda: here.node("NDEATH"), within_s=10)
                await eventually(lambda: spb.connected and spb.server == there.address, within_s=10)
                stored = spb.queue_depth
                await eventually(lambda: spb.queue_depth >= stored + 3, within_s=15)
                assert not there.node("NBIRTH", since=since), f"born on {there.name} too early"

            async def host_comes(there: Server, timestamp: int) -> None:
                stamp[there.name] = timestamp
                since = len(there.heard)
                await there.say(online=True, timestamp=timestamp)
                await eventually(lambda: len(there.node("DDATA", since=since)) >= 3, within_s=20)

            # B: no STATE there yet; born once the host says online, then a rebirth.
            await host_leaves(a, b)
            await host_comes(b, host_clock_ms())
            ncmd = {"timestamp": host_clock_ms(), "metrics": [rebirth_metric()]}
            assert b.host is not None
            await b.host.publish(f"{NODE}/NCMD/{EDGE}", tahu_encode(ncmd), qos=0)
            await eventually(lambda: len(b.node("NBIRTH")) == 2, within_s=10)
            # C, then round to A, whose retained STATE is still the host's will.
            await host_leaves(b, c)
            await host_comes(c, host_clock_ms())
            await host_leaves(c, a)
            await host_comes(a, host_clock_ms())
            assert spb.switches == 3
        await eventually(lambda: len(a.node("NDEATH")) == 2, within_s=10)  # the clean stop's
        await all_read(a, b, c)
    assert on_one_server_at_a_time(a, b, c) == ["a", "b", "c", "a"]
    for server in (a, b, c):
        births_follow_online(server)
    sessions = [first, first + 1, first + 2, first + 3]
    expected = {"a": [0, 3], "b": [1, 1], "c": [2]}
    for server in (a, b, c):
        born = [h.bd_seq for h in server.node("NBIRTH")]
        assert born == [sessions[i] % 256 for i in expected[server.name]], server.name
        assert all(h.seq == 0 for h in server.node("NBIRTH"))
        # One NDEATH per session, with its NBIRTH's bdSeq.
        assert [h.bd_seq for h in server.node("NDEATH")] == list(dict.fromkeys(born))


def rebirth_metric() -> dict[str, object]:
    return {"name": "Node Control/Rebirth", "type": "Boolean", "value": True}


@pytest.mark.line
@pytest.mark.broker
async def test_a_stale_offline_state_is_ignored_and_the_edge_stays(tmp_path: Path) -> None:
    """tck-id-operational-behavior-edge-node-termination-host-offline-timestamp.

    An offline STATE older than the online one acted on (the late will of an earlier
    session of the host) neither ends the session nor moves the node: it goes on
    publishing its data on the same server, and nothing reaches the others.
    """
    async with simulated(tmp_path, ANIMATED), servers(tmp_path) as (a, b, c):
        online = host_clock_ms()
        await a.say(online=True, timestamp=online)
        async with gateway(edge_yaml(tmp_path, [a, b, c])) as state:
            spb = state.sparkplug
            await eventually(lambda: len(a.node("DDATA")) >= 3, within_s=20)
            since = len(a.heard)
            await a.say(online=False, timestamp=online - 60_000)
            stale = await eventually(
                lambda: [i for i, h in enumerate(a.heard) if i >= since and h.kind == "STATE"],
                within_s=5,
            )
            await eventually(lambda: len(a.node("DDATA", since=stale[0])) >= 6, within_s=15)
            assert (spb.server, spb.switches, spb.connected) == (a.address, 0, True)
            assert spb.host_online
            assert not a.node("NDEATH")
        await all_read(a, b, c)
    assert a.heard[stale[0]].state()["online"] is False
    assert b.node() == []
    assert c.node() == []
    assert len(a.node("NBIRTH")) == 1


@pytest.mark.line
@pytest.mark.broker
async def test_each_servers_state_is_judged_by_its_own_timestamps(tmp_path: Path) -> None:
    """tck-id-operational-behavior-host-application-multi-server-timestamp, with the edge's…

    …tck-id-message-flow-edge-node-birth-publish-phid-wait-timestamp and
    tck-id-operational-behavior-edge-node-termination-host-offline-timestamp.

    A host keeps its STATE timestamp per server: it connected to B long before it last
    connected to A. When its session on A ends, its online STATE on B is older than the
    will the node acted on, on A, and yet the host is online on B: the node is born there.
    A timestamp is compared with the STATE before it on the same server only.
    """
    async with simulated(tmp_path, ANIMATED), servers(tmp_path) as (a, b, c):
        on_b = host_clock_ms() - 3_600_000  # an hour ago
        on_a = host_clock_ms()
        await b.say(online=True, timestamp=on_b)
        await c.say(online=True, timestamp=on_b + 1)
        await a.say(online=True, timestamp=on_a)
        async with gateway(edge_yaml(tmp_path, [a, b, c], host_wait_s=60)) as state:
            spb = state.sparkplug
            await eventually(lambda: len(a.node("DDATA")) >= 3, within_s=20)
            await a.say(online=False, timestamp=on_a)  # its will on A
            await eventually(lambda: spb.server == b.address, within_s=10)
            await eventually(lambda: len(b.node("DDATA")) >= 3, within_s=15)
            assert spb.switches == 1
        await all_read(a, b, c)
    assert on_one_server_at_a_time(a, b, c) == ["a", "b"]
    assert len(b.node("NBIRTH")) == 1
    assert c.node() == []


@pytest.mark.line
@pytest.mark.broker
async def test_no_host_anywhere_walks_the_list_round_robin(tmp_path: Path) -> None:
    """tck-id-operational-behavior-primary-application-state-with-multiple-servers-walk,…

    …tck-id-operational-behavior-edge-node-birth-sequence-wait, tck-id-topics-nbirth-bdseq-
    increment. The host is online nowhere: on each server the node waits
    ``host_wait_s`` (2 s here), then publishes its NDEATH and tries the next, A, B, C, A,
    B, with the next bdSeq at each CONNECT, never born.
    """
    wait_s = 2.0
    async with simulated(tmp_path, ANIMATED), servers(tmp_path) as (a, b, c):
        async with gateway(edge_yaml(tmp_path, [a, b, c], host_wait_s=wait_s)) as state:
            spb = state.sparkplug
            await eventually(lambda: len(b.node("NDEATH")) >= 2, within_s=40)
            assert spb.births == 0
        await all_read(a, b, c)
    deaths = sorted((h for s in (a, b, c) for h in s.node("NDEATH")), key=lambda h: h.at)
    assert [h.server for h in deaths][:5] == ["a", "b", "c", "a", "b"]
    bd_seqs = [h.bd_seq for h in deaths]
    assert bd_seqs == [(bd_seqs[0] + i) % 256 for i in range(len(bd_seqs))]
    assert not [h for s in (a, b, c) for h in s.node() if h.kind != "NDEATH"]
    stays = [after.at - before.at for before, after in itertools.pairwise(deaths[:4])]
    print("time on each server: " + ", ".join(f"{s:.2f} s" for s in stays))  # noqa: T201
    assert all(stay >= wait_s - 0.1 for stay in stays), stays


# --- one identity per gateway --------------------------------------------------------------


@pytest.mark.line
@pytest.mark.broker
@pytest.mark.parametrize("client_ids", ["same", "own"])
async def test_a_copied_config_stands_down_on_sparkplug_too_and_the_first_node_lives_on(
    tmp_path: Path, client_ids: str
) -> None:
    """tck-id-intro-edge-node-id-uniqueness, tck-id-payloads-nbirth-edge-node-descriptor.

    Two gateways from one config (one base topic, one edge node, one Sparkplug client id;
    the plain client ids the same or not) on one mosquitto. The second finds the first's
    owner marker and stands down on both connections: its Sparkplug session never connects,
    so it publishes no NBIRTH and no NDEATH and no will can be delivered, and /healthz says
    why. The first publishes on, and the host never sees its node die (a host takes an
    NDEATH whose bdSeq matches the NBIRTH it holds as the node's death: Sparkplug 3.0,
    "Death Message (NDEATH)"), nor another NBIRTH, nor a gap in its seq.
    """
    first_dir, second_dir = tmp_path / "first", tmp_path / "second"
    first_dir.mkdir()
    second_dir.mkdir()

    def config(directory: Path, client_id: str, on: Server) -> str:
        mqtt = (
            f"{{host: 127.0.0.1, port: {on.broker.port}, base_topic: gw, client_id: {client_id},"
            " reconnect_max_s: 1}"
        )
        return edge_yaml(directory, [on], host=None, mqtt=mqtt)

    async with (
        simulated(first_dir, ANIMATED),
        simulated(second_dir, ANIMATED),
        servers(tmp_path, "a") as (on,),
    ):
        async with gateway(config(first_dir, "cab-1", on)) as first:
            await eventually(lambda: len(on.node("DDATA")) >= 3, within_s=20)
            loop = asyncio.get_running_loop()
            second_id = "cab-1" if client_ids == "same" else "cab-2"
            async with gateway(config(second_dir, second_id, on)) as second:
                started = loop.time()
                await eventually(lambda: second.sparkplug.identity_conflict, within_s=60)
                stood_down_s = loop.time() - started
                since = len(on.heard)
                await eventually(lambda: len(on.node("DDATA", since=since)) >= 5, within_s=15)
                assert_stood_down(second)
            assert not on.node("NDEATH")  # the second's stop: nothing of it either
            assert first.sparkplug.identity_conflict is None
            assert first.mqtt.identity_conflict is None
            assert (first.sparkplug.births, first.sparkplug.connected) == (1, True)
            bd_seq = first.sparkplug.bd_seq
        await eventually(lambda: on.node("NDEATH"), within_s=10)  # the first's clean stop
        await all_read(on)
    print(f"stood down after {stood_down_s:.2f} s ({client_ids} client id)")  # noqa: T201
    assert [h.bd_seq for h in on.node("NBIRTH")] == [bd_seq]
    assert [h.bd_seq for h in on.node("NDEATH")] == [bd_seq]
    seqs = [h.seq for h in on.node() if h.kind != "NDEATH"]
    assert seqs == [n % 256 for n in range(len(seqs))]  # one sender: no gap, no repeat


@pytest.mark.broker
@pytest.mark.parametrize("born", [True, False], ids=["born", "waiting-for-the-host"])
async def test_a_conflict_found_while_connected_ends_the_session_cleanly(
    tmp_path: Path, *, born: bool
) -> None:
    """tck-id-operational-behavior-edge-node-intentional-disconnect-ndeath, and its limit.

    The session connected without a claim that stood (the plain topics' broker away past
    the gate's bound), then the verdict comes. Born: its NDEATH, with its NBIRTH's bdSeq
    (a host holding another NBIRTH ignores it), then a DISCONNECT, so no second NDEATH from
    the will. Not born yet (the host not online): a DISCONNECT alone, no NDEATH that could
    match the holder's bdSeq. Nothing more is published either way.
    """
    host = "" if born else f", primary_host_id: {HOST}"
    async with servers(tmp_path, "a") as (on,):
        config = parse_config(
            "buses: [{name: a, port: /dev/ttyUSB0}]\n"
            f"mqtt: {{host: 127.0.0.1, port: {on.broker.port}, reconnect_max_s: 1}}\n"
            f"sparkplug: {{enabled: true, group_id: {GROUP}, edge_node_id: {EDGE}{host}}}\n",
            environ={},
        )
        state = GatewayState()  # MQTT not enabled: the gate lets the session connect
        sink = SparkplugSink(config.sparkplug, config.mqtt, [], state_dir=tmp_path, state=state)
        task = asyncio.create_task(sink.run(), name="test[sparkplug]")
        try:
            spb = state.sparkplug
            await eventually(lambda: spb.connected, within_s=10)
            if born:
                await eventually(lambda: on.node("NBIRTH"), within_s=10)
            await eventually(lambda: on.clients[-1:] == [2], within_s=10)
            state.mqtt.identity_conflict = "another gateway publishes under base topic 'gw'"
            await eventually(lambda: spb.identity_conflict, within_s=5)
            await eventually(lambda: on.clients[-1:] == [1], within_s=10)  # disconnected
            heard = len(on.heard)
            sink.session.enqueue([Message(topic=f"{NODE}/DDATA/{EDGE}/basin", payload=b"")])
            assert spb.queue_depth == 1  # kept, not sent
        finally:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task
        await all_read(on)
    assert len(on.heard) == heard  # nothing after the stand-down
    assert not spb.connected
    deaths = [h.bd_seq for h in on.node("NDEATH")]
    assert deaths == ([on.node("NBIRTH")[0].bd_seq] if born else [])


def assert_stood_down(second: GatewayState) -> None:
    """The second gateway: both connections stood down, and /healthz says why."""
    spb = second.sparkplug
    assert second.mqtt.identity_conflict is not None
    assert (spb.connected, spb.births, spb.published) == (False, 0, 0)
    why = spb.identity_conflict or ""
    assert f"edge node {GROUP}/{EDGE}" in why
    assert "cab-1" in why  # who holds the identity
    assert "sparkplug.edge_node_id" in why  # and what to change
    healthy, body = health_report(second)
    assert not healthy
    reasons, shown = body["reasons"], body["sparkplug"]
    assert isinstance(reasons, list)
    assert isinstance(shown, dict)
    assert f"sparkplug: {why}" in reasons
    assert shown["identity_conflict"] == why


# --- the identity gate, without a broker ---------------------------------------------------


async def test_the_session_connects_once_the_claim_has_stood_and_not_without_mqtt() -> None:
    """The claim must stand ``settle_s`` on one connection; without MQTT there is none."""
    mqtt = MqttStatus(enabled=True)
    gate = GatewayIdentity(mqtt, settle_s=0.3, wait_max_s=30)
    held = asyncio.create_task(gate.held())
    mqtt.identity_claimed_at = time.monotonic()
    # The time under test: a claim that stood half the settling time, then none.
    await asyncio.sleep(0.15)
    mqtt.identity_claimed_at = None  # thrown off (a holder with the same client id)
    await asyncio.sleep(0.3)
    assert not held.done()
    claimed = mqtt.identity_claimed_at = time.monotonic()  # claimed again, and it stands
    await asyncio.wait_for(held, timeout=2)
    assert time.monotonic() - claimed >= 0.3
    await asyncio.wait_for(GatewayIdentity(MqttStatus(enabled=False)).held(), timeout=1)
    # The connection's verdict, before the claim stood or after: raised.
    mqtt.identity_conflict = "another gateway publishes under 'gw'"
    with pytest.raises(IdentityConflictError, match="another gateway"):
        await asyncio.wait_for(gate.held(), timeout=1)
    with pytest.raises(IdentityConflictError, match="another gateway"):
        await asyncio.wait_for(gate.contested(), timeout=1)


async def test_an_unreachable_mqtt_broker_holds_sparkplug_back_only_so_long(
    caplog: pytest.LogCaptureFixture,
) -> None:
    gate = GatewayIdentity(MqttStatus(enabled=True), settle_s=3, wait_max_s=0.3)
    with caplog.at_level(logging.WARNING):
        await asyncio.wait_for(gate.held(), timeout=2)
    assert "connecting without it" in caplog.text


async def test_a_conflict_stands_the_session_down_before_it_connects(tmp_path: Path) -> None:
    """Found before the first CONNECT: no bdSeq taken, no connection tried, the status says why."""
    mqtt = MqttStatus(enabled=True, identity_conflict="another gateway publishes under 'gw'")
    config = parse_config(
        "buses: [{name: a, port: /dev/ttyUSB0}]\n"
        "mqtt: {host: 127.0.0.1, port: 9}\n"  # nothing listens: a try would say so
        "sparkplug: {enabled: true}\n",
        environ={},
    )
    status = SparkplugStatus()
    session = SparkplugSession(
        config.mqtt,
        config.sparkplug,
        SparkplugTopics(GROUP, EDGE),
        MessageStore(tmp_path / "q.sqlite", max_messages=1000),
        births=NoBirths(),
        client_id="t",
        bd_seq_path=tmp_path / "bdseq",
        status=status,
        identity=GatewayIdentity(mqtt),
    )
    task = asyncio.create_task(session.run())
    await eventually(lambda: status.identity_conflict is not None, within_s=5)
    session.enqueue([Message(topic=f"{NODE}/DDATA/{EDGE}/basin", payload=b"")])
    assert status.queue_depth == 1  # data is kept, within the queue's bound
    task.cancel()
    with contextlib.suppress(asyncio.CancelledError):
        await task
    assert status.identity_conflict is not None
    assert "another gateway publishes under 'gw'" in status.identity_conflict
    assert status.last_error == status.identity_conflict  # not a connection error
    assert not (tmp_path / "bdseq").exists()  # no CONNECT took a bdSeq
    assert (status.connected, status.births, status.published) == (False, 0, 0)


class NoBirths:
    def births(self, bd_seq: int, now_ms: int) -> list[Message]:  # noqa: ARG002
        raise AssertionError("no birth without a connection")

    def born_devices(self) -> set[str]:
        return set()


def test_two_endings_at_once_leave_as_the_one_that_decides() -> None:
    """The host's offline STATE as the connection drops: one ending, the host's, not a group.

    Raised as a group, it would have left the session's reconnect loop and ended its task.
    """
    lost = aiomqtt.MqttError("the broker closed the connection")
    offline = HostOfflineError()
    conflict = IdentityConflictError("another gateway publishes under 'gw'")
    assert _deciding(ExceptionGroup("", [lost, offline])) is offline
    assert _deciding(ExceptionGroup("", [offline, lost, conflict])) is conflict
    assert _deciding(ExceptionGroup("", [lost])) is lost


class SwallowingClient:
    """A client whose publish, cancelled as it completes, returns (``asyncio.wait_for``, 3.11)."""

    def __init__(self) -> None:
        self.sent = 0

    async def publish(self, topic: str, payload: bytes, *, qos: int, retain: bool) -> None:  # noqa: ARG002
        self.sent += 1
        with contextlib.suppress(asyncio.CancelledError):
            await asyncio.sleep(0.01)


async def test_a_stand_down_while_the_backlog_drains_stops_the_sender(tmp_path: Path) -> None:
    """The plain connection's sender, cancelled in a publish that swallows it, still stops.

    The copied-config test above found it: the second gateway's connection had judged the
    marker and raised, but its sender, draining the backlog, lost the cancellation in a
    publish and went on publishing under the first's base topic, so the stand-down (and
    the Sparkplug session's with it) waited until the test's end.
    """
    store = MessageStore(tmp_path / "q.sqlite", max_messages=1000)
    store.append([Message(topic=f"gw/basin/{i}", payload=b"1") for i in range(200)])
    client = SwallowingClient()
    sender = asyncio.create_task(Outbox(store, MqttStatus(enabled=True))._drain(client))  # type: ignore[arg-type]
    await eventually(lambda: client.sent >= 20, within_s=5)
    sender.cancel()
    done, _ = await asyncio.wait([sender], timeout=5)
    assert sender in done
    assert sender.cancelled()
    assert client.sent < 200
    store.close()
