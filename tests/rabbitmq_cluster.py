"""A real three-node RabbitMQ cluster with its MQTT plugin, for tests.

RabbitMQ 3.10 (Debian 12's 3.10.8) as the test's own processes, not the system service (the
package enables ``rabbitmq-server.service``; the tests neither need nor touch it). Each
node is a ``rabbitmq-server`` of its own:

- its name ``rabbit-N@localhost`` (short names: ``localhost`` needs no resolver set-up);
  its Mnesia directory, logs, ``rabbitmq.conf``, enabled plugins file and pid file in its
  own directory (``RABBITMQ_MNESIA_BASE``, ``RABBITMQ_LOG_BASE``, ``RABBITMQ_CONFIG_FILE``,
  ``RABBITMQ_ENABLED_PLUGINS_FILE``, ``RABBITMQ_PID_FILE``), and an empty environment file
  and advanced config of its own, so that nothing of ``/etc/rabbitmq`` applies;
- ``HOME`` is its directory, which holds the cluster's Erlang cookie (``.erlang.cookie``,
  mode 0400, the same for the three: ``RABBITMQ_ERLANG_COOKIE`` is deprecated). The CLI
  (``rabbitmqctl``) is run with the same ``HOME``, so it presents the same cookie;
- its AMQP and MQTT listeners and its management HTTP API on its own loopback address
  (127.0.0.2, .3, .4: they reach this machine with no set-up), on ports of its own; its
  Erlang distribution port (``RABBITMQ_DIST_PORT``) on 127.0.0.1 only;
- the three register with a port mapper (``epmd``) that the cluster starts itself on a
  port of its own (``ERL_EPMD_PORT``, which the nodes and the CLI both read), so that
  another RabbitMQ or Erlang node on the machine, or a test running beside this one, never
  shares it; the cluster stops it at the end, as it stops the nodes.

Plugins: ``rabbitmq_mqtt``, and ``rabbitmq_management`` for its HTTP API, which answers in
milliseconds where a ``rabbitmqctl`` call costs a second of CPU: which MQTT clients are on
which node (``/api/connections``, refreshed every :data:`STATISTICS_INTERVAL_MS`), the
queues and their nodes (``/api/queues``), which nodes run (``/api/nodes``).

MQTT clients are anonymous: ``mqtt.allow_anonymous = true`` maps them to ``guest`` in the
vhost ``/``. ``guest`` may only connect from a loopback address (``loopback_users``, left
as it is): RabbitMQ counts all of 127.0.0.0/8 as loopback, and the clients connect from
127.0.0.1 anyway.

The cluster is formed as RabbitMQ's clustering guide does it by hand: the three nodes boot
on their own, then nodes 2 and 3 each ``stop_app``, ``join_cluster rabbit-1@localhost`` and
``start_app``, one after the other. Peer discovery (``classic_config``) would form it at
boot, but three nodes booting at once may each form a cluster of their own (3.10 has no
lock on the first formation); the joins are slower (some 10 s each) and certain.

A node is killed with SIGKILL of its Erlang VM, ``beam.smp``, whose pid the node writes to
its pid file. (``rabbitmq-server`` is a shell script that runs the VM as its child, to turn
SIGTERM into a clean stop; it only ``exec``s the VM under systemd or with the Erlang shell
on stdin.) It is started again on the same Mnesia directory, and rejoins the cluster from
it. Ready means: every running node has finished booting (``rabbitmqctl await_startup``),
sees every running node as running (``/api/nodes``) and accepts TCP on its MQTT port.

What RabbitMQ 3.10's MQTT plugin keeps where (its documentation, "MQTT Plugin"):

- retained messages in a store local to each node (``rabbit_mqtt_retained_msg_store_dets``:
  a DETS table in the node's Mnesia directory, opened with ``ram_file`` and ``auto_save``
  2000 ms, so written to its file once 2 s pass without a write, and at a clean stop): a
  node gives a new subscriber only what was published through it, and only for a topic
  filter without wildcards; a node killed while retained messages keep coming (a value
  every poll) comes back without those written since its last quiet moment;
- a client's subscriptions are one queue per QoS, named after its client id, on the node
  it is connected to. A clean session's QoS 1 queue is a classic queue: when its node
  dies, the others have dropped it with the node (the client id subscribes again elsewhere
  at once), or its record stayed until the node was back, the same client id refused a
  QoS 1 subscription on every other node meanwhile; both have been seen. A persistent
  session's (``clean_session=False``) QoS 1 queue is durable, of the type
  ``mqtt.durable_queue_type`` says: a classic queue (the default) lives on that one node;
  a quorum queue has a replica on each of three nodes and a leader elected again when one
  dies;
- the client ids connected in the whole cluster are kept by a Raft cluster of all nodes
  (``mqtt_node``), so that one client id is connected once, cluster-wide.
"""

from __future__ import annotations

import base64
import contextlib
import json
import os
import re
import shutil
import signal
import socket
import subprocess
import time
import urllib.request
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Final

from tests.mqtt_broker import free_port

if TYPE_CHECKING:
    from collections.abc import Iterator, Sequence

# The scripts themselves, not the /usr/sbin wrappers of Debian's package: those switch to the
# ``rabbitmq`` user and its home (/var/lib/rabbitmq) when run as root.
RABBITMQ_BIN: Final = Path("/usr/lib/rabbitmq/bin")
RABBITMQ_SERVER: Final = RABBITMQ_BIN / "rabbitmq-server"
RABBITMQCTL: Final = RABBITMQ_BIN / "rabbitmqctl"
EPMD: Final = shutil.which("epmd") or "/usr/bin/epmd"
ADDRESSES: Final = ("127.0.0.2", "127.0.0.3", "127.0.0.4")
PLUGINS: Final = ("rabbitmq_mqtt", "rabbitmq_management")
QUEUE_TYPES: Final = ("classic", "quorum")  # mqtt.durable_queue_type: persistent sessions
# How often each node's management agent refreshes what /api/connections lists (the
# default is 5000 ms): the reconnect times are read from it.
STATISTICS_INTERVAL_MS: Final = 500
READY_WITHIN_S: Final = 120.0  # three cold boots and two joins, on a busy 2-core machine
STOP_WITHIN_S: Final = 60.0  # a clean stop flushes queues and Mnesia: seconds, not minutes
CTL_TIMEOUT_S: Final = 90.0
_GUEST: Final = "Basic " + base64.b64encode(b"guest:guest").decode()


@dataclass
class Node:
    """One RabbitMQ node of the cluster, on its own loopback address and directory."""

    name: str  # rabbit-1 ...
    host: str
    directory: Path
    cookie: str
    epmd_port: int
    durable_queue_type: str
    amqp_port: int = field(default_factory=free_port)
    dist_port: int = field(default_factory=free_port)
    management_port: int = field(default_factory=free_port)
    mqtt_port: int = field(default_factory=free_port)
    process: subprocess.Popen[bytes] | None = None  # the rabbitmq-server script
    starts: int = 0

    @property
    def nodename(self) -> str:
        """The Erlang node name, as the CLI and the cluster name it."""
        return f"{self.name}@localhost"

    @property
    def mqtt(self) -> tuple[str, int]:
        """Where MQTT clients connect to this node."""
        return self.host, self.mqtt_port

    @property
    def log(self) -> Path:
        return self.directory / "log" / f"{self.nodename}.log"

    @property
    def pid_file(self) -> Path:
        return self.directory / "beam.pid"

    @property
    def running(self) -> bool:
        return self.process is not None and self.process.poll() is None

    def write_config(self) -> None:
        """Its rabbitmq.conf, enabled plugins, Erlang cookie and (empty) environment file."""
        self.directory.mkdir(parents=True, exist_ok=True)
        (self.directory / "log").mkdir(exist_ok=True)
        text = (
            f"listeners.tcp.1 = {self.host}:{self.amqp_port}\n"
            f"mqtt.listeners.tcp.1 = {self.host}:{self.mqtt_port}\n"
            f"management.tcp.ip = {self.host}\n"
            f"management.tcp.port = {self.management_port}\n"
            "mqtt.allow_anonymous = true\n"
            "mqtt.default_user = guest\n"
            "mqtt.default_pass = guest\n"
            "mqtt.vhost = /\n"
            f"mqtt.durable_queue_type = {self.durable_queue_type}\n"
            f"collect_statistics_interval = {STATISTICS_INTERVAL_MS}\n"
            "log.console = false\n"
            "log.file.level = info\n"
        )
        (self.directory / "rabbitmq.conf").write_text(text, encoding="utf-8")
        plugins = f"[{','.join(PLUGINS)}].\n"  # what rabbitmq-plugins enable writes
        (self.directory / "enabled_plugins").write_text(plugins, encoding="utf-8")
        (self.directory / "rabbitmq-env.conf").write_text("", encoding="utf-8")
        cookie = self.directory / ".erlang.cookie"
        if not cookie.exists():
            cookie.write_text(self.cookie, encoding="ascii")
            cookie.chmod(0o400)  # Erlang refuses a cookie others may read

    def environment(self) -> dict[str, str]:
        """What the node's scripts and the CLI run with: its files, its ports, its cookie."""
        here = self.directory
        return {
            **os.environ,
            "HOME": str(here),
            "RABBITMQ_NODENAME": self.nodename,
            "RABBITMQ_MNESIA_BASE": str(here / "mnesia"),
            "RABBITMQ_LOG_BASE": str(here / "log"),
            "RABBITMQ_CONFIG_FILE": str(here / "rabbitmq.conf"),
            "RABBITMQ_ADVANCED_CONFIG_FILE": str(here / "advanced.config"),  # none
            "RABBITMQ_ENABLED_PLUGINS_FILE": str(here / "enabled_plugins"),
            "RABBITMQ_CONF_ENV_FILE": str(here / "rabbitmq-env.conf"),
            "RABBITMQ_PID_FILE": str(self.pid_file),
            "RABBITMQ_DIST_PORT": str(self.dist_port),
            "RABBITMQ_SERVER_ADDITIONAL_ERL_ARGS": "-kernel inet_dist_use_interface {127,0,0,1}",
            "ERL_EPMD_PORT": str(self.epmd_port),
            "ERL_EPMD_ADDRESS": "127.0.0.1",
        }

    def start(self) -> None:
        assert os.access(RABBITMQ_SERVER, os.X_OK), (
            "rabbitmq-server is missing: apt-get install rabbitmq-server (as root)"
        )
        assert not self.running, f"{self.name} runs already"
        self.pid_file.unlink(missing_ok=True)  # the one of a killed run would mislead
        with (self.directory / "stdout.log").open("ab") as out:  # a file: no pipe to fill
            self.process = subprocess.Popen(
                [str(RABBITMQ_SERVER)],
                env=self.environment(),
                cwd=self.directory,
                stdin=subprocess.DEVNULL,
                stdout=out,
                stderr=subprocess.STDOUT,
            )
        self.starts += 1

    def beam_pid(self) -> int:
        """The pid of the node's Erlang VM, from its pid file, checked in /proc."""
        pid = int(self.pid_file.read_text(encoding="ascii").strip())
        command = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
        assert Path(os.fsdecode(command[0])).name == "beam.smp", command
        assert f"-home {self.directory}".encode() in b" ".join(command), command
        return pid

    def kill(self) -> None:
        """SIGKILL of the VM: no goodbye to its peers, its clients or its files."""
        if self.process is None:
            return
        with contextlib.suppress(OSError):
            os.kill(self.beam_pid(), signal.SIGKILL)
        self.process.wait(timeout=10)  # the script ends with the VM it waited for
        self.process = None

    def terminate(self) -> None:
        """Ask for a clean stop (SIGTERM: the script stops the VM and waits for it)."""
        if self.running:
            assert self.process is not None
            self.process.terminate()

    def wait_stopped(self, within_s: float = STOP_WITHIN_S) -> None:
        """Until the node has stopped; killed if it takes longer than ``within_s``."""
        if self.process is None:
            return
        try:
            self.process.wait(timeout=within_s)
        except subprocess.TimeoutExpired:
            with contextlib.suppress(OSError, ValueError, AssertionError):
                os.kill(self.beam_pid(), signal.SIGKILL)
            self.process.kill()
            self.process.wait(timeout=10)
        self.process = None

    def ctl(self, *args: str, timeout_s: float = CTL_TIMEOUT_S) -> subprocess.CompletedProcess[str]:
        """``rabbitmqctl -n`` this node, with its cookie and port mapper; not checked."""
        return subprocess.run(
            [str(RABBITMQCTL), "-q", "-n", self.nodename, *args],
            env=self.environment(),
            capture_output=True,
            text=True,
            timeout=timeout_s,
            check=False,
        )

    def ctl_ok(self, *args: str) -> str:
        """``rabbitmqctl`` that must succeed; its output."""
        done = self.ctl(*args)
        assert done.returncode == 0, (
            f"rabbitmqctl {' '.join(args)} on {self.name}: {done.stdout}{done.stderr}"
            f"\n{self.log_tail()}"
        )
        return done.stdout

    def api(self, path: str) -> Any:
        """A management API answer (JSON), or None when the node does not answer."""
        request = urllib.request.Request(
            f"http://{self.host}:{self.management_port}/api/{path}",
            headers={"Authorization": _GUEST},
        )
        try:
            with urllib.request.urlopen(request, timeout=5) as response:  # noqa: S310 - http, loopback
                return json.loads(response.read())
        except (OSError, ValueError):
            return None

    def mqtt_clients(self) -> set[str]:
        """The MQTT client ids connected to this node (empty when it is down), as its
        management API lists them (refreshed every :data:`STATISTICS_INTERVAL_MS`)."""
        connections = (
            self.api("connections?columns=node,client_properties") if self.running else None
        )
        return {
            properties["client_id"]
            for connection in connections or []
            if connection.get("node") == self.nodename
            and "client_id" in (properties := connection.get("client_properties") or {})
        }

    def wait_booted(self, deadline: float) -> None:
        """Until the node's rabbit application has started (or the deadline: an error)."""
        while True:
            if not self.running:
                raise AssertionError(f"{self.name} ended while booting\n{self.log_tail()}")
            # The CLI reaches the node once its distribution listens; before, it fails at once.
            if _accepts("127.0.0.1", self.dist_port):
                left = max(1, int(deadline - time.monotonic()))
                if self.ctl("await_startup", "--timeout", str(left)).returncode == 0:
                    return
            if time.monotonic() > deadline:
                raise AssertionError(f"{self.name} not booted in time\n{self.log_tail()}")
            time.sleep(0.2)

    def why_not_ready(self, running: Sequence[str]) -> str | None:
        """What this running node still lacks to serve MQTT in the cluster, or None."""
        nodes = self.api("nodes?columns=name,running")
        if nodes is None:
            return "no answer on the management port"
        seen = {n["name"] for n in nodes if n.get("running")}
        if not set(running) <= seen:
            return f"sees {sorted(seen)} running, not {sorted(running)}"
        if not _accepts(self.host, self.mqtt_port):
            return "MQTT port closed"
        return None

    def log_tail(self, lines: int = 30) -> str:
        try:
            text = self.log.read_text(encoding="utf-8", errors="replace")
        except OSError:
            return ""
        return "\n".join(text.splitlines()[-lines:])


def _accepts(host: str, port: int) -> bool:
    with contextlib.suppress(OSError), socket.create_connection((host, port), 0.5):
        return True
    return False


@dataclass
class RabbitCluster:
    """Three nodes on 127.0.0.2-4, clustered; each may be killed and started again."""

    directory: Path
    nodes: list[Node]
    epmd_port: int
    epmd: subprocess.Popen[bytes] | None = None
    boot_s: float = 0.0  # from the first start until ready: the three booted and joined

    @classmethod
    def make(cls, directory: Path, *, durable_queue_type: str = "classic") -> RabbitCluster:
        """Three nodes' files in ``directory``; ``durable_queue_type``: the persistent
        sessions' queues (``classic`` or ``quorum``)."""
        assert durable_queue_type in QUEUE_TYPES, durable_queue_type
        cookie = base64.b32encode(os.urandom(20)).decode()  # [A-Z2-7]: a valid cookie
        epmd_port = free_port()
        nodes = []
        for index, host in enumerate(ADDRESSES):
            node = Node(
                name=f"rabbit-{index + 1}",
                host=host,
                directory=directory / f"rabbit-{index + 1}",
                cookie=cookie,
                epmd_port=epmd_port,
                durable_queue_type=durable_queue_type,
            )
            node.write_config()
            nodes.append(node)
        return cls(directory=directory, nodes=nodes, epmd_port=epmd_port)

    @property
    def up(self) -> list[Node]:
        return [node for node in self.nodes if node.running]

    def start(self) -> None:
        """The port mapper, the three nodes booted at once, then nodes 2 and 3 joined to 1."""
        started = time.monotonic()
        deadline = started + READY_WITHIN_S
        self.epmd = subprocess.Popen(
            [EPMD, "-port", str(self.epmd_port), "-address", "127.0.0.1"],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        for node in self.nodes:
            node.start()
        for node in self.nodes:
            node.wait_booted(deadline)
        seed = self.nodes[0]
        for node in self.nodes[1:]:
            node.ctl_ok("stop_app")
            node.ctl_ok("join_cluster", seed.nodename)
            node.ctl_ok("start_app")
        self.wait_ready(deadline - time.monotonic())
        members = self.mqtt_members()
        assert members == {n.nodename for n in self.nodes}, f"mqtt_node members: {members}"
        self.boot_s = time.monotonic() - started

    def wait_ready(self, within_s: float = READY_WITHIN_S) -> None:
        """Until every running node has booted, sees the others running and serves MQTT."""
        deadline = time.monotonic() + within_s
        for node in self.up:
            node.wait_booted(deadline)
        while True:
            running = self.up
            names = [n.nodename for n in running]
            reasons = {n.name: n.why_not_ready(names) for n in running}
            if not any(reasons.values()):
                return
            if time.monotonic() > deadline:
                tails = "\n".join(f"--- {n.name}\n{n.log_tail()}" for n in self.nodes)
                raise AssertionError(f"cluster not ready in {within_s} s: {reasons}\n{tails}")
            time.sleep(0.1)

    def kill(self, node: Node) -> float:
        """SIGKILL ``node``'s VM; when it happened (monotonic)."""
        node.kill()
        return time.monotonic()

    def restart(self, node: Node, *, within_s: float = READY_WITHIN_S) -> float:
        """Start ``node`` again on its directory, wait until the cluster is whole; how long
        that took (s)."""
        started = time.monotonic()
        node.start()
        self.wait_ready(within_s)
        return time.monotonic() - started

    def stop(self) -> None:
        """Every node stopped cleanly (at once), then the port mapper."""
        for node in self.nodes:
            node.terminate()
        for node in self.nodes:
            node.wait_stopped()
        if self.epmd is not None:
            self.epmd.terminate()
            self.epmd.wait(timeout=10)
            self.epmd = None

    def api(self, path: str) -> Any:
        """A management API answer from the first running node that gives one."""
        for node in self.up:
            answer = node.api(path)
            if answer is not None:
                return answer
        return None

    def where(self, client_id: str) -> Node | None:
        """The running node the MQTT client ``client_id`` is connected to, if any."""
        return next((n for n in self.up if client_id in n.mqtt_clients()), None)

    def queue(self, name: str) -> dict[str, Any]:
        """A queue as the management API shows it (type, node or leader and members...);
        empty when no node knows it."""
        queues = self.api("queues?columns=name,type,node,leader,members,online,state,messages")
        return next((q for q in queues or [] if q.get("name") == name), {})

    def mqtt_members(self) -> set[str]:
        """The nodes of the Raft cluster that keeps MQTT client ids (``mqtt_node``)."""
        return set(self._mqtt_raft()[0])

    def mqtt_leader(self) -> Node | None:
        """The node that leads the Raft cluster of MQTT client ids."""
        leader = self._mqtt_raft()[1]
        return next((n for n in self.nodes if n.nodename == leader), None)

    def _mqtt_raft(self) -> tuple[list[str], str | None]:
        """``ra:members`` of ``mqtt_node``, asked of the first running node: (members, leader)."""
        for node in self.up:
            done = node.ctl("eval", "ra:members({mqtt_node, node()}).")
            if done.returncode != 0:
                continue
            # It prints the members, then the leader, each as {mqtt_node, Node}.
            servers = re.findall(r"\{mqtt_node,\s*'([^']+)'\}", done.stdout)
            if servers:
                return servers[:-1], servers[-1]
        return [], None


@contextlib.contextmanager
def running_cluster(
    directory: Path, *, durable_queue_type: str = "classic"
) -> Iterator[RabbitCluster]:
    """A started cluster in ``directory``, stopped at the end (whatever the test killed)."""
    cluster = RabbitCluster.make(directory, durable_queue_type=durable_queue_type)
    try:
        cluster.start()
        yield cluster
    finally:
        cluster.stop()
