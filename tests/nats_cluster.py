"""A real three-node NATS cluster with JetStream and its MQTT interface, for tests.

Each node listens on its own loopback address (127.0.0.2, .3, .4: they reach this machine
with no set-up), keeps its JetStream store in its own directory, has routes to the other
two, a monitoring port and an MQTT listener. JetStream's MQTT keeps sessions, retained
messages and the QoS 1 messages of persistent sessions in streams; ``stream_replicas: 3``
gives each of them a copy on every node, so a node may die without them.

A node can be killed with SIGKILL and started again on the same store directory; the
cluster is ready when every running node has its routes to the others, JetStream has a
meta leader and each node's ``/healthz`` (JetStream current) says ok.

NATS 2.9 (Debian 12's 2.9.10) refuses ``.`` in MQTT topics (and ``' '``): Sparkplug's
``spBv1.0`` namespace cannot go through it, so only the plain topics are tested here.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import shutil
import signal
import socket
import subprocess
import time
import urllib.error
import urllib.request
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Final

import aiomqtt

from tests.mqtt_broker import free_port
from tests.waiting import cancelled

if TYPE_CHECKING:
    from collections.abc import AsyncIterator, Callable, Iterator, Sequence
    from pathlib import Path

NATS_SERVER: Final = shutil.which("nats-server") or "/usr/sbin/nats-server"
ADDRESSES: Final = ("127.0.0.2", "127.0.0.3", "127.0.0.4")
CLUSTER_NAME: Final = "gateway-test"
# The streams JetStream's MQTT keeps (nats-server, server/mqtt.go): sessions, the QoS 1
# messages for persistent sessions, retained messages.
MQTT_STREAMS: Final = ("$MQTT_sess", "$MQTT_msgs", "$MQTT_rmsgs")
READY_WITHIN_S: Final = 60.0  # a cold start or a restarted node catching up, on a busy machine


@dataclass
class Node:
    """One nats-server of the cluster, on its own loopback address and store directory."""

    name: str
    host: str
    directory: Path
    client_port: int = field(default_factory=free_port)
    cluster_port: int = field(default_factory=free_port)
    monitor_port: int = field(default_factory=free_port)
    mqtt_port: int = field(default_factory=free_port)
    process: subprocess.Popen[bytes] | None = None
    starts: int = 0

    @property
    def mqtt(self) -> tuple[str, int]:
        """Where MQTT clients connect to this node."""
        return self.host, self.mqtt_port

    @property
    def log(self) -> Path:
        return self.directory / "nats.log"

    @property
    def running(self) -> bool:
        return self.process is not None and self.process.poll() is None

    def write_config(self, peers: Sequence[Node]) -> Path:
        routes = ", ".join(f"nats-route://{p.host}:{p.cluster_port}" for p in peers)
        store = self.directory / "jetstream"
        text = (
            f"server_name: {self.name}\n"
            f"listen: {self.host}:{self.client_port}\n"
            f"http: {self.host}:{self.monitor_port}\n"
            f'log_file: "{self.log}"\n'
            # Small limits: JetStream would otherwise reserve 75 % of the machine's memory.
            f'jetstream {{ store_dir: "{store}", max_memory_store: 64MB, max_file_store: 1GB }}\n'
            f"cluster {{ name: {CLUSTER_NAME}, listen: {self.host}:{self.cluster_port},"
            f" routes: [{routes}] }}\n"
            f"mqtt {{ listen: {self.host}:{self.mqtt_port}, stream_replicas: 3 }}\n"
        )
        config = self.directory / "nats.conf"
        config.write_text(text, encoding="utf-8")
        return config

    def start(self) -> None:
        assert os.access(NATS_SERVER, os.X_OK), (
            "nats-server is missing: scripts/setup installs it (as root)"
        )
        assert not self.running, f"{self.name} runs already"
        self.process = subprocess.Popen(
            [NATS_SERVER, "-c", str(self.directory / "nats.conf")],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        self.starts += 1

    def kill(self) -> None:
        """SIGKILL: no goodbye to the routes, the clients or the store."""
        if self.process is not None:
            self.process.send_signal(signal.SIGKILL)
            self.process.wait(timeout=10)
            self.process = None

    def stop(self) -> None:
        if self.process is not None:
            self.process.terminate()
            try:
                self.process.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait(timeout=10)
            self.process = None

    def monitor(self, endpoint: str) -> dict[str, Any] | None:
        """A monitoring endpoint's JSON (``jsz``, ``routez``, ``connz?subs=1``...), or None
        when the node does not answer (down, starting)."""
        url = f"http://{self.host}:{self.monitor_port}/{endpoint}"
        try:
            with urllib.request.urlopen(url, timeout=2) as response:
                body: dict[str, Any] = json.loads(response.read())
        except urllib.error.HTTPError as exc:  # /healthz answers 503 with its reason
            body = json.loads(exc.read())
        except (OSError, ValueError):
            return None
        return body

    def mqtt_clients(self) -> set[str]:
        """The MQTT client ids connected to this node (empty when it is down)."""
        connz = self.monitor("connz?subs=1&limit=10000") if self.running else None
        if connz is None:
            return set()
        return {c["mqtt_client"] for c in connz.get("connections") or [] if c.get("mqtt_client")}

    def why_not_ready(self, running: int) -> str | None:
        """What this running node still lacks to serve MQTT, or None."""
        routez = self.monitor("routez")
        if routez is None:
            return "no answer on the monitoring port"
        peers = {r.get("remote_name") or r.get("remote_id") for r in routez.get("routes") or []}
        if len(peers) < running - 1:
            return f"routes to {len(peers)} of {running - 1} peers"
        jsz = self.monitor("jsz") or {}
        if not (jsz.get("meta_cluster") or {}).get("leader"):
            return "no JetStream meta leader"
        # The server's own JetStream current with the meta leader; not every stream and
        # consumer: an idle consumer of a session can stay "not current" on a restarted node
        # for over a minute, while the node serves MQTT well (NATS 2.9.10).
        health = self.monitor("healthz?js-server-only=true") or {}
        if health.get("status") != "ok":
            return f"healthz: {health.get('error') or health}"
        with contextlib.suppress(OSError), socket.create_connection(self.mqtt, 0.5):
            return None
        return "MQTT port closed"

    def log_tail(self, lines: int = 30) -> str:
        try:
            text = self.log.read_text(encoding="utf-8", errors="replace")
        except OSError:
            return ""
        return "\n".join(text.splitlines()[-lines:])


@dataclass
class NatsCluster:
    """Three nodes on 127.0.0.2-4; each may be killed and started again."""

    directory: Path
    nodes: list[Node]

    @classmethod
    def make(cls, directory: Path) -> NatsCluster:
        nodes = []
        for index, host in enumerate(ADDRESSES):
            where = directory / f"nats-{index + 1}"
            where.mkdir(parents=True, exist_ok=True)
            nodes.append(Node(name=f"nats-{index + 1}", host=host, directory=where))
        for node in nodes:
            node.write_config([peer for peer in nodes if peer is not node])
        return cls(directory=directory, nodes=nodes)

    @property
    def up(self) -> list[Node]:
        return [node for node in self.nodes if node.running]

    def start(self) -> None:
        for node in self.nodes:
            node.start()
        self.wait_ready()

    def wait_ready(self, within_s: float = READY_WITHIN_S) -> None:
        """Until every running node serves MQTT with a formed cluster behind it."""
        deadline = time.monotonic() + within_s
        while True:
            running = self.up
            reasons = {n.name: n.why_not_ready(len(running)) for n in running}
            if not any(reasons.values()):
                return
            if time.monotonic() > deadline:
                tails = "\n".join(f"--- {n.name}\n{n.log_tail()}" for n in self.nodes)
                raise AssertionError(f"cluster not ready in {within_s} s: {reasons}\n{tails}")
            time.sleep(0.1)

    def kill(self, node: Node) -> float:
        """SIGKILL ``node``; when it happened (monotonic)."""
        node.kill()
        return time.monotonic()

    def restart(self, node: Node, *, within_s: float = READY_WITHIN_S) -> None:
        """Start ``node`` again on its store directory and wait until the cluster is whole."""
        node.start()
        self.wait_ready(within_s)

    def stop(self) -> None:
        for node in self.nodes:
            node.stop()

    def where(self, client_id: str) -> Node | None:
        """The running node the MQTT client ``client_id`` is connected to, if any."""
        return next((n for n in self.up if client_id in n.mqtt_clients()), None)

    def meta_leader(self) -> Node | None:
        """The node that leads JetStream's meta group (streams, consumers, placement)."""
        for node in self.up:
            leader = ((node.monitor("jsz") or {}).get("meta_cluster") or {}).get("leader")
            if leader:
                return next((n for n in self.nodes if n.name == leader), None)
        return None

    def stream_leaders(self) -> dict[str, str]:
        """The node that leads each MQTT stream, by stream name (as a node sees it)."""
        return {name: leader for name, (_, leader) in self._streams().items()}

    def stream_replicas(self) -> dict[str, int]:
        """The MQTT streams JetStream made, by name, with their number of replicas."""
        return {name: replicas for name, (replicas, _) in self._streams().items()}

    def _streams(self) -> dict[str, tuple[int, str]]:
        for node in self.up:
            jsz = node.monitor("jsz?accounts=true&streams=true&config=true")
            if jsz is None:
                continue
            return {
                stream["name"]: (
                    stream["config"]["num_replicas"],
                    (stream.get("cluster") or {}).get("leader", ""),
                )
                for account in jsz.get("account_details") or []
                for stream in account.get("stream_detail") or []
                if stream["name"] in MQTT_STREAMS
            }
        return {}


@contextlib.contextmanager
def running_cluster(directory: Path) -> Iterator[NatsCluster]:
    """A started cluster in ``directory``, stopped at the end (whatever the test killed)."""
    cluster = NatsCluster.make(directory)
    try:
        cluster.start()
        yield cluster
    finally:
        cluster.stop()


# --- MQTT clients that walk the nodes, as a gateway with a server list does -------------


@dataclass(frozen=True)
class Arrival:
    topic: str
    payload: bytes
    retain: bool
    node: str  # host:port of the node it came through
    at: float = field(default_factory=time.monotonic)


@contextlib.asynccontextmanager
async def subscriber(
    servers: Sequence[tuple[str, int]],
    topic_filters: Sequence[str],
    on_message: Callable[[Arrival], None],
    *,
    name: str,
    clean_session: bool,
    qos: int = 1,
) -> AsyncIterator[list[str]]:
    """A subscriber on the first server that answers, moving to the next when its node
    goes away; subscribed when the block starts. Yields the servers it connected to, in
    order (``host:port``), as it goes.

    With ``clean_session=False`` the session (its subscriptions and the QoS 1 messages not
    yet acknowledged) is the broker's to keep across the move: it subscribes at its first
    connection only, so what it gets after a move shows what the broker kept. In NATS each QoS 1
    subscription is a JetStream consumer, made at the subscribe and deleted when a clean
    session ends; a QoS 0 one is a plain subscription, which JetStream never sees.
    """
    ready = asyncio.Event()
    path: list[str] = []

    async def listen() -> None:
        turn = 0
        subscribed = False
        while True:
            host, port = servers[turn % len(servers)]
            where = f"{host}:{port}"
            try:
                client = aiomqtt.Client(
                    host, port, identifier=name, clean_session=clean_session, timeout=10
                )
                async with client:
                    path.append(where)
                    if clean_session or not subscribed:
                        for topic_filter in topic_filters:
                            await client.subscribe(topic_filter, qos=qos)
                        subscribed = True
                    ready.set()
                    async for message in client.messages:
                        payload = message.payload
                        data = payload if isinstance(payload, bytes) else str(payload).encode()
                        on_message(Arrival(str(message.topic), data, message.retain, where))
            except aiomqtt.MqttError:
                turn += 1
                await asyncio.sleep(0.1)

    task = asyncio.create_task(listen(), name=f"subscriber[{name}]")
    try:
        await asyncio.wait_for(ready.wait(), timeout=30)
        yield path
    finally:
        await cancelled(task)  # asked again if aiomqtt's wait_for swallowed it (Python 3.11)


async def retained_on(
    node: tuple[str, int], topic_filters: Sequence[str], wanted: set[str], *, within_s: float
) -> dict[str, bytes]:
    """The retained messages a new subscriber on ``node`` gets, once they include every
    topic of ``wanted`` (or the deadline passed: then what came).

    At QoS 0, so that the check costs JetStream no consumer to make and delete: under
    NATS 2.9 such an API call that times out holds the node's other clients up to 4 s.
    """
    found: dict[str, bytes] = {}
    complete = asyncio.Event()

    def keep(arrival: Arrival) -> None:
        if arrival.retain:
            found[arrival.topic] = arrival.payload
            if wanted <= found.keys():
                complete.set()

    name = f"retained-check-{node[0]}-{time.monotonic_ns()}"
    async with subscriber([node], topic_filters, keep, name=name, clean_session=True, qos=0):
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(complete.wait(), timeout=within_s)
    return found
