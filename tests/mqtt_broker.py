"""A real mosquitto broker for tests, and a subscriber that records everything."""

from __future__ import annotations

import asyncio
import contextlib
import getpass
import os
import random
import shutil
import socket
import subprocess
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import aiomqtt

from tests.waiting import cancelled

if TYPE_CHECKING:
    from collections.abc import AsyncIterator, Callable

MOSQUITTO = shutil.which("mosquitto") or "/usr/sbin/mosquitto"
MOSQUITTO_PASSWD = shutil.which("mosquitto_passwd") or "/usr/bin/mosquitto_passwd"


# Ports are drawn below the kernel's ephemeral range where it leaves room: a port that
# bind(("", 0)) gives is one an outgoing connection (a client reconnecting to a broker, a
# scrape) may take in the second before the process under test binds it.
_LOWEST_PORT = 20000
_EPHEMERAL_RANGE = Path("/proc/sys/net/ipv4/ip_local_port_range")
_handed_out: set[int] = set()
# Its own generator: pytest-randomly reseeds the shared one alike before every test.
_draw = random.Random()  # noqa: S311 - a port number, not a secret


def free_port() -> int:
    """A port on 127.0.0.1 free a moment ago and not handed out before in this run.

    Under pytest-xdist each worker draws from its own slice of the range, so that two
    tests running at once never get the same port between its probe and its bind.
    """
    low, high = _port_range()
    while True:
        wanted = _draw.randrange(low, high) if high - low >= 100 else 0
        with socket.socket() as probe:
            try:
                probe.bind(("127.0.0.1", wanted))
            except OSError:
                continue  # taken: draw again
            port = int(probe.getsockname()[1])
        if port not in _handed_out:
            _handed_out.add(port)
            return port


def _port_range() -> tuple[int, int]:
    """This process's ports: below the ephemeral range, its worker's slice of them."""
    try:
        ephemeral_low = int(_EPHEMERAL_RANGE.read_text(encoding="ascii").split()[0])
    except (OSError, ValueError, IndexError):
        ephemeral_low = 0
    if ephemeral_low - _LOWEST_PORT < 1000:
        return 0, 0
    worker = os.environ.get("PYTEST_XDIST_WORKER", "gw0")  # gw0, gw1, ... (pytest-xdist)
    workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
    index = int(worker.removeprefix("gw")) if worker.removeprefix("gw").isdigit() else 0
    width = (ephemeral_low - _LOWEST_PORT) // max(workers, 1)
    low = _LOWEST_PORT + index * width
    return low, low + width


@dataclass(frozen=True)
class TlsFiles:
    """A test CA, a server certificate for 127.0.0.1 and a client certificate, made by openssl."""

    ca: Path
    server_cert: Path
    server_key: Path
    client_cert: Path
    client_key: Path

    @classmethod
    def make(cls, directory: Path) -> TlsFiles:
        openssl = shutil.which("openssl")
        assert openssl, "openssl is missing: scripts/setup installs it (as root)"

        def run(*args: str) -> None:
            subprocess.run([openssl, *args], cwd=directory, check=True, capture_output=True)

        run(
            "req",
            "-x509",
            "-newkey",
            "rsa:2048",
            "-nodes",
            "-keyout",
            "ca.key",
            "-out",
            "ca.pem",
            "-days",
            "1",
            "-subj",
            "/CN=gateway-test-ca",
        )
        (directory / "san.ext").write_text("subjectAltName=IP:127.0.0.1\n", encoding="utf-8")
        for name, subject in (("server", "/CN=127.0.0.1"), ("client", "/CN=gateway")):
            run(
                "req",
                "-newkey",
                "rsa:2048",
                "-nodes",
                "-keyout",
                f"{name}.key",
                "-out",
                f"{name}.csr",
                "-subj",
                subject,
            )
            run(
                "x509",
                "-req",
                "-in",
                f"{name}.csr",
                "-CA",
                "ca.pem",
                "-CAkey",
                "ca.key",
                "-CAcreateserial",
                "-out",
                f"{name}.pem",
                "-days",
                "1",
                "-extfile",
                "san.ext",
            )
        return cls(
            ca=directory / "ca.pem",
            server_cert=directory / "server.pem",
            server_key=directory / "server.key",
            client_cert=directory / "client.pem",
            client_key=directory / "client.key",
        )


@dataclass
class Broker:
    """mosquitto on a free loopback port; can be stopped and started again."""

    directory: Path
    port: int = field(default_factory=free_port)
    users: dict[str, str] = field(default_factory=dict)
    tls: TlsFiles | None = None  # a TLS listener that requires a client certificate
    extra: list[str] = field(default_factory=list)  # more lines of mosquitto.conf
    process: subprocess.Popen[bytes] | None = None

    def start(self) -> None:
        assert shutil.which(MOSQUITTO), "mosquitto is missing: scripts/setup installs it (as root)"
        config = self.directory / "mosquitto.conf"
        # Persistence keeps the recorder's session (and what is queued for it) across a
        # broker restart, so the outage test sees every message whatever reconnects first.
        lines = [
            # Run as the test's user: as root, mosquitto would switch to its own user, which
            # cannot read the test's temporary files.
            f"user {getpass.getuser()}",
            f"listener {self.port} 127.0.0.1",
            "persistence true",
            f"persistence_location {self.directory}/",
            "max_queued_messages 1000000",
        ]
        lines += self.extra
        if self.tls is not None:
            lines += [
                f"cafile {self.tls.ca}",
                f"certfile {self.tls.server_cert}",
                f"keyfile {self.tls.server_key}",
                "require_certificate true",
            ]
        if self.users:
            passwords = self.directory / "passwords"
            passwords.write_text("", encoding="utf-8")
            for user, password in self.users.items():
                subprocess.run([MOSQUITTO_PASSWD, "-b", str(passwords), user, password], check=True)
            lines += ["allow_anonymous false", f"password_file {passwords}"]
        else:
            lines.append("allow_anonymous true")
        config.write_text("\n".join(lines) + "\n", encoding="utf-8")
        self.process = subprocess.Popen(
            [MOSQUITTO, "-c", str(config)], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
        )
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline:
            with (
                contextlib.suppress(OSError),
                socket.create_connection(("127.0.0.1", self.port), 0.2),
            ):
                return
            time.sleep(0.05)
        raise RuntimeError("mosquitto did not start")

    def stop(self) -> None:
        if self.process is not None:
            self.process.terminate()
            self.process.wait(timeout=10)
            self.process = None


@dataclass
class Received:
    topic: str
    payload: str
    retain: bool
    at: float = field(default_factory=time.monotonic)  # when it arrived here


@dataclass
class Recorder:
    """Subscribes to a topic filter and keeps every message in arrival order."""

    messages: list[Received] = field(default_factory=list)

    def on(self, topic: str) -> list[str]:
        return [m.payload for m in self.messages if m.topic == topic]

    async def wait_for(
        self, topic: str, payload: str | None = None, within_s: float = 10.0, *, skip: int = 0
    ) -> None:
        """Wait for a message on ``topic`` (with ``payload``), ignoring its first ``skip``."""
        deadline = asyncio.get_running_loop().time() + within_s
        while asyncio.get_running_loop().time() < deadline:
            if any(payload is None or p == payload for p in self.on(topic)[skip:]):
                return
            await asyncio.sleep(0.05)
        raise AssertionError(f"no {payload!r} on {topic}; got {self.on(topic)[-5:]}")


@contextlib.asynccontextmanager
async def subscribed(
    port: int,
    topic_filter: str,
    on_message: Callable[[aiomqtt.Message], None],
    *,
    name: str,
    tls: TlsFiles | None = None,
) -> AsyncIterator[None]:
    """A persistent subscriber (QoS 1) handing every message to ``on_message``, reconnecting
    after a broker restart; subscribed when the block starts."""
    ready = asyncio.Event()

    async def listen() -> None:
        while True:
            try:
                client = aiomqtt.Client(
                    "127.0.0.1",
                    port,
                    identifier=name,
                    clean_session=False,
                    tls_params=aiomqtt.TLSParameters(
                        ca_certs=str(tls.ca),
                        certfile=str(tls.client_cert),
                        keyfile=str(tls.client_key),
                    )
                    if tls
                    else None,
                )
                async with client:
                    await client.subscribe(topic_filter, qos=1)
                    ready.set()
                    async for message in client.messages:
                        on_message(message)
            except aiomqtt.MqttError:
                await asyncio.sleep(0.2)

    task = asyncio.create_task(listen())
    await asyncio.wait_for(ready.wait(), timeout=10)
    try:
        yield
    finally:
        await cancelled(task)  # asked again if aiomqtt's wait_for swallowed it (Python 3.11)


@contextlib.asynccontextmanager
async def recording(
    port: int, topic_filter: str, tls: TlsFiles | None = None, *, name: str = "test-recorder"
) -> AsyncIterator[Recorder]:
    """Every message on ``topic_filter`` as text, kept in a :class:`Recorder`."""
    recorder = Recorder()

    def keep(message: aiomqtt.Message) -> None:
        payload = message.payload
        text = payload.decode() if isinstance(payload, bytes) else str(payload)
        recorder.messages.append(Received(str(message.topic), text, message.retain))

    async with subscribed(port, topic_filter, keep, name=name, tls=tls):
        yield recorder
