"""Rigs for the state directory's tests: real file systems, the gateway as a process, a
subscriber that keeps every message with its DUP flag, and reading what is on disk.

The file systems are real (the tests run as root): a tmpfs of a few hundred kilobytes that
a filler file fills up, an ext4 image on a loop device mounted ``errors=remount-ro`` whose
error the kernel is told to raise (the kernel then makes it read-only, as after an I/O
error of an SD card), and a read-only bind mount.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import signal
import sqlite3
import subprocess
import sys
import threading
import time
import urllib.error
import urllib.request
from collections import Counter
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Self

import paho.mqtt.client as paho
from paho.mqtt.enums import CallbackAPIVersion

from tests.waiting import wait_until

if TYPE_CHECKING:
    from collections.abc import Callable, Iterator
    from pathlib import Path


QUEUE_FILE = "mqtt-queue.sqlite"
LEDGER_FILE = "flash-writes.sqlite"


# --- file systems ---------------------------------------------------------------------------


def _run(tool: str, *args: str, check: bool = True) -> str:
    """A system tool (mount, umount, mkfs.ext4, e2fsck, findmnt): its output."""
    path = shutil.which(tool)
    assert path, f"{tool} is missing: the storage tests need it (and root)"
    return subprocess.run([path, *args], check=check, capture_output=True, text=True).stdout


@contextlib.contextmanager
def small_tmpfs(path: Path, size_kib: int) -> Iterator[Path]:
    """A tmpfs of ``size_kib`` KiB mounted at ``path``, unmounted afterwards."""
    path.mkdir(parents=True, exist_ok=True)
    _run("mount", "-t", "tmpfs", "-o", f"size={size_kib}k", "tmpfs", str(path))
    try:
        yield path
    finally:
        _run("umount", "-l", str(path), check=False)


def fill(directory: Path) -> Path:
    """Write a file until the file system is full; the file, to delete to make room."""
    filler = directory / "filler"
    with filler.open("wb", buffering=0) as out:
        block = b"\0" * 4096
        with contextlib.suppress(OSError):
            while True:
                out.write(block)
        with contextlib.suppress(OSError):
            while True:
                out.write(b"\0")
    assert os.statvfs(directory).f_bavail == 0
    return filler


@dataclass
class Ext4Image:
    """An ext4 file system in an image file, on a loop device, ``errors=remount-ro``."""

    image: Path
    mount_point: Path
    devices: list[str] = field(default_factory=list)  # loop devices of our own

    def mount(self) -> None:
        self.mount_point.mkdir(parents=True, exist_ok=True)
        _run("mount", "-o", "loop,errors=remount-ro", str(self.image), str(self.mount_point))

    @property
    def device(self) -> str:
        """The loop device's name (``loop3``)."""
        return _run("findmnt", "-n", "-o", "SOURCE", str(self.mount_point)).strip().split("/")[-1]

    def fail(self) -> None:
        """Raise a file system error, as the kernel does at an I/O error: it goes read-only."""
        trigger_path = f"/sys/fs/ext4/{self.device}/trigger_fs_error"
        with open(trigger_path, "w", encoding="ascii") as trigger:  # noqa: PTH123 - sysfs
            trigger.write("test: the SD card failed\n")
        deadline = time.monotonic() + 5
        while not self.read_only() and time.monotonic() < deadline:
            time.sleep(0.05)
        assert self.read_only()

    def read_only(self) -> bool:
        options = _run("findmnt", "-n", "-o", "OPTIONS", str(self.mount_point))
        # ext4 says "emergency_ro" where it stopped writing after an error (Linux 6.x).
        return bool({"ro", "emergency_ro"} & set(options.strip().split(",")))

    def repair(self) -> None:
        """The card checked and mounted again: unmount (lazily: the gateway may still hold
        a file of the old mount, which keeps it alive), check, mount on a new loop device
        (the old one still carries the failed file system)."""
        _run("umount", "-l", str(self.mount_point))
        _run("e2fsck", "-fy", str(self.image), check=False)
        device = _run("losetup", "-f", "--show", str(self.image)).strip()
        self.devices.append(device)
        _run("mount", "-o", "errors=remount-ro", device, str(self.mount_point))

    def unmount(self) -> None:
        _run("umount", "-l", str(self.mount_point), check=False)
        for device in self.devices:
            _run("losetup", "-d", device, check=False)  # detached once no longer used


@contextlib.contextmanager
def ext4_image(directory: Path, size_mib: int = 16) -> Iterator[Ext4Image]:
    image = Ext4Image(image=directory / "state.ext4", mount_point=directory / "mnt")
    with image.image.open("wb") as out:
        out.truncate(size_mib * 1024 * 1024)
    _run("mkfs.ext4", "-q", "-F", str(image.image))
    image.mount()
    try:
        yield image
    finally:
        image.unmount()


def _writable(target: Path) -> None:
    _run("mount", "-o", "remount,rw,bind", str(target))


@contextlib.contextmanager
def read_only_bind(source: Path, target: Path) -> Iterator[Callable[[], None]]:
    """``source`` seen read-only at ``target``; yields a function that makes it writable."""
    target.mkdir(parents=True, exist_ok=True)
    _run("mount", "--bind", str(source), str(target))
    try:
        _run("mount", "-o", "remount,ro,bind", str(target))
        yield lambda: _writable(target)
    finally:
        _run("umount", "-l", str(target), check=False)


# --- the gateway, as a process ----------------------------------------------------------------


@dataclass
class GatewayProcess:
    """``gateway run --config`` as a service runs it, its log in a file (appended)."""

    config: Path
    log: Path
    process: subprocess.Popen[bytes] | None = None
    started: float = 0.0

    def start(self) -> None:
        assert self.process is None
        with self.log.open("ab") as log:
            self.process = subprocess.Popen(
                [sys.executable, "-m", "gateway", "run", "--config", str(self.config)],
                stdout=subprocess.DEVNULL,
                stderr=log,
            )
        self.started = time.monotonic()

    def kill(self) -> None:
        """SIGKILL: no handler runs, nothing is flushed or closed by the gateway."""
        assert self.process is not None
        self.process.send_signal(signal.SIGKILL)
        self.process.wait(timeout=10)
        self.process = None

    def stop(self) -> int:
        """SIGTERM, as systemd stops it; its exit code."""
        assert self.process is not None
        self.process.send_signal(signal.SIGTERM)
        code = self.process.wait(timeout=15)
        self.process = None
        return code

    def alive(self) -> bool:
        return self.process is not None and self.process.poll() is None

    def log_text(self) -> str:
        return self.log.read_text(encoding="utf-8", errors="replace")


def get(url: str, timeout_s: float = 5.0) -> tuple[int, str]:
    """An HTTP GET: the status and the body (an error status too)."""
    try:
        with urllib.request.urlopen(url, timeout=timeout_s) as answer:  # noqa: S310 - our own http
            return int(answer.status), answer.read().decode()
    except urllib.error.HTTPError as exc:
        return int(exc.code), exc.read().decode()


def healthz(port: int) -> tuple[int, dict[str, Any]]:
    status, body = get(f"http://127.0.0.1:{port}/healthz")
    parsed: dict[str, Any] = json.loads(body)
    return status, parsed


def metric(port: int, name: str, **labels: str) -> float | None:
    """One sample of ``/metrics`` (None if absent)."""
    _, text = get(f"http://127.0.0.1:{port}/metrics")
    wanted = ",".join(f'{k}="{v}"' for k, v in labels.items())
    prefix = f"{name}{{{wanted}}} " if labels else f"{name} "
    for line in text.splitlines():
        if line.startswith(prefix):
            return float(line.split()[-1])
    return None


# --- the subscriber ---------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Arrival:
    """One message as the subscriber got it."""

    topic: str
    payload: bytes
    retain: bool
    dup: bool  # the broker sent it again (to this subscriber), not the gateway
    at: float  # time.time()


@dataclass
class Subscriber:
    """A persistent QoS 1 subscriber in paho's own thread: every message, in arrival order.

    Its session survives a broker restart (mosquitto keeps it on disk), so nothing the
    broker took is missed; what the broker sends again to it carries the DUP flag.
    """

    port: int
    topic_filter: str | tuple[str, ...]  # one filter, or several
    name: str = "power-cut-recorder"
    arrivals: list[Arrival] = field(default_factory=list)
    _lock: threading.Lock = field(default_factory=threading.Lock)
    _subscribed: threading.Event = field(default_factory=threading.Event)

    def __post_init__(self) -> None:
        self.client = paho.Client(
            CallbackAPIVersion.VERSION2, client_id=self.name, clean_session=False
        )
        self.client.on_connect = self._on_connect
        self.client.on_message = self._on_message
        self.client.reconnect_delay_set(min_delay=1, max_delay=1)

    def _on_connect(self, client: paho.Client, *_: Any) -> None:
        filters = (self.topic_filter,) if isinstance(self.topic_filter, str) else self.topic_filter
        client.subscribe([(topic_filter, 1) for topic_filter in filters])
        self._subscribed.set()

    def _on_message(self, _client: paho.Client, _data: object, message: paho.MQTTMessage) -> None:
        arrival = Arrival(
            topic=message.topic,
            payload=bytes(message.payload),
            retain=bool(message.retain),
            dup=bool(message.dup),
            at=time.time(),
        )
        with self._lock:
            self.arrivals.append(arrival)

    def __enter__(self) -> Self:
        self.client.connect("127.0.0.1", self.port, keepalive=10)
        self.client.loop_start()
        assert self._subscribed.wait(10), "the subscriber did not connect"
        return self

    def __exit__(self, *_: object) -> None:
        self.client.disconnect()
        self.client.loop_stop()

    def received(self) -> list[Arrival]:
        with self._lock:
            return list(self.arrivals)

    def payloads(self, topic: str) -> list[bytes]:
        return [a.payload for a in self.received() if a.topic == topic]

    def wait_for(self, topic: str, *, after: float = 0.0, within_s: float = 15.0) -> Arrival:
        """The first message on ``topic`` that arrived after ``after`` (time.time())."""

        def found() -> Arrival | None:
            return next((a for a in self.received() if a.topic == topic and a.at > after), None)

        arrival: Arrival = wait_until(found, within_s=within_s)
        return arrival


# --- what is on disk --------------------------------------------------------------------------


def _copy(state_dir: Path, name: str, into: Path) -> Path | None:
    """The database and its journal or log, copied: read without touching the original."""
    if into.exists():
        shutil.rmtree(into)
    into.mkdir(parents=True)
    if not (state_dir / name).exists():
        return None
    for suffix in ("", "-wal", "-journal"):
        source = state_dir / f"{name}{suffix}"
        if source.exists():
            shutil.copyfile(source, into / source.name)
    return into / name


def spool_rows(state_dir: Path, scratch: Path) -> list[tuple[int, str, bytes]]:
    """The MQTT queue as it is on disk now (a copy is opened): id, topic, payload in order.

    The copy must pass SQLite's integrity check: a kill never leaves a damaged queue. A
    file with no table at all is one a kill cut between its creation and its schema (the
    gateway opens it with its settings first, then creates the table): nothing was queued
    in it yet, and the next start creates the table.
    """
    copy = _copy(state_dir, QUEUE_FILE, scratch)
    if copy is None:
        return []
    db = sqlite3.connect(copy)
    try:
        assert db.execute("PRAGMA integrity_check").fetchone() == ("ok",)
        if db.execute("SELECT count(*) FROM sqlite_master").fetchone() == (0,):
            return []
        rows = db.execute("SELECT id, topic, payload FROM queue ORDER BY id").fetchall()
    finally:
        db.close()
    return [(int(i), str(t), bytes(p)) for i, t, p in rows]


def ledger_counts(state_dir: Path, scratch: Path) -> Counter[tuple[str, str]]:
    """The flash-write ledger's totals by (device, point), from a copy (a hot journal too)."""
    copy = _copy(state_dir, LEDGER_FILE, scratch)
    if copy is None:
        return Counter()
    db = sqlite3.connect(copy)
    try:
        assert db.execute("PRAGMA integrity_check").fetchone() == ("ok",)
        rows = db.execute(
            "SELECT device, point, SUM(count) FROM flash_writes GROUP BY device, point"
        ).fetchall()
    finally:
        db.close()
    return Counter({(str(d), str(p)): int(n) for d, p, n in rows})
