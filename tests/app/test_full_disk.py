"""A full disk and a read-only ``state_dir`` under the running gateway, and their end.

Real parts: ``gateway run`` as a process, the simulator as a process on a pseudo-terminal,
a real mosquitto and subscriber, ``/healthz`` and ``/metrics`` over HTTP, and real file
systems (the tests run as root): a tmpfs of 2 MiB filled by a file, an ext4 image that
the kernel makes read-only after an error (``errors=remount-ro``, as after an I/O error of
an SD card), and a read-only bind mount.

What must hold (README: What survives a power cut, and a full disk): polling and live
publishing go on; a full ``state_dir`` is said at once, before any file failed; the
queue's failure (at once with ``mqtt.persist: always``, at the next broker outage with
the default) is logged once with the path and the cause;
``/healthz`` and ``gateway_storage_writable`` say so; flash writes are refused with the
reason and nothing reaches the sensor; and once the disk can be written again, all of it
recovers by itself: the health, the metric, flash writes, and what waited in memory.
"""

from __future__ import annotations

import contextlib
import itertools
import json
import time
from dataclasses import dataclass
from datetime import datetime
from typing import TYPE_CHECKING, Any

import paho.mqtt.client as paho
import pytest
from paho.mqtt.enums import CallbackAPIVersion

from gateway.shared.storage import RETRY_S
from tests.mqtt_broker import free_port
from tests.rigs import simulate_process, stats_of
from tests.storage_rig import (
    GatewayProcess,
    Subscriber,
    ext4_image,
    fill,
    healthz,
    ledger_counts,
    metric,
    read_only_bind,
    small_tmpfs,
)
from tests.waiting import wait_until

if TYPE_CHECKING:
    from collections.abc import Callable, Iterator
    from pathlib import Path

    from tests.mqtt_broker import Broker

pytestmark = [pytest.mark.line, pytest.mark.broker, pytest.mark.root, pytest.mark.timeout(180)]

BASE = "fd"
QUEUE = "mqtt-queue.sqlite"
RECORDS = "records.sqlite"
LEDGER = "flash-writes.sqlite"
SIMULATED = (
    "line: {baudrate: 38400, parity: E, stopbits: 1}\n"
    "devices:\n"
    "  - {profile: reiss-m0c, address: 10}\n"
    "  - {profile: jumo-tecline-cl2, address: 20, values: {cell_current: 76.5}}\n"
)


@dataclass
class Plant:
    """The gateway on a state directory of the test's file system, and what watches it."""

    state_dir: Path
    stats: Path
    gateway: GatewayProcess
    subscriber: Subscriber
    commands: paho.Client
    metrics_port: int
    scratch: Path
    _ids: itertools.count[int]

    def health(self) -> tuple[int, dict[str, Any]]:
        return healthz(self.metrics_port)

    def writable(self, name: str) -> float | None:
        return metric(self.metrics_port, "gateway_storage_writable", file=name)

    def documents_since(self, since: float) -> int:
        """State documents of polls made after ``since`` (seconds since the epoch)."""
        return sum(
            1
            for a in self.subscriber.received()
            if a.topic.endswith("/state")
            and datetime.fromisoformat(json.loads(a.payload)["time"]).timestamp() > since
        )

    def set_x_zero(self, value: float) -> dict[str, Any]:
        """``{base}/cl2/x_zero/set`` (a flash point), and its result."""
        ident = str(next(self._ids))
        topic = f"{BASE}/cl2/x_zero/set"
        sent = time.time()
        self.commands.publish(topic, json.dumps({"value": value, "id": ident}), qos=1)

        def result() -> dict[str, Any] | None:
            for a in self.subscriber.received():
                if a.topic == f"{topic}/result" and a.at >= sent:
                    body: dict[str, Any] = json.loads(a.payload)
                    if body.get("id") == ident:
                        return body
            return None

        found: dict[str, Any] = wait_until(result, within_s=15)
        return found

    def x_zero_writes(self) -> int:
        """Writes of X_Zero the simulated tecLine accepted: its own record."""
        writes = stats_of(self.stats)["devices"]["20"]["writes"]
        return sum(1 for w in writes if "x_zero" in w["points"] and w["exception"] is None)

    def warnings(self, *words: str) -> list[str]:
        return [
            line
            for line in self.gateway.log_text().splitlines()
            if " WARNING " in line and all(word in line for word in words)
        ]


@pytest.fixture
def plant_on(tmp_path: Path, broker: Broker) -> Iterator[Callable[..., Plant]]:
    """A function that starts the plant with ``state_dir`` where the test says.

    Everything it starts is stopped when the test ends, whatever its outcome.
    """
    with contextlib.ExitStack() as stack:

        def start(state_dir: Path, persist: str = "outage") -> Plant:
            port, stats = stack.enter_context(simulate_process(tmp_path, SIMULATED))
            metrics_port = free_port()
            config = tmp_path / "gateway.yaml"
            config.write_text(
                f"buses:\n  - {{name: line1, port: {port}, baudrate: 38400, parity: E}}\n"
                "devices:\n"
                "  - {name: basin, bus: line1, address: 10, profile: reiss-m0c,"
                " poll_interval: 0.25}\n"
                "  - {name: cl2, bus: line1, address: 20, profile: jumo-tecline-cl2,"
                " poll_interval: 1, flash_writes: [x_zero]}\n"
                f"mqtt: {{host: 127.0.0.1, port: {broker.port}, base_topic: {BASE},"
                f" reconnect_max_s: 0.5, persist: {persist}}}\n"
                f"prometheus: {{host: 127.0.0.1, port: {metrics_port}}}\n"
                f"state_dir: {state_dir}\n",
                encoding="utf-8",
            )
            commands = paho.Client(CallbackAPIVersion.VERSION2, client_id="full-disk-commands")
            commands.connect("127.0.0.1", broker.port)
            commands.loop_start()
            stack.callback(commands.loop_stop)
            stack.callback(commands.disconnect)
            subscriber = stack.enter_context(
                Subscriber(broker.port, f"{BASE}/#", name="full-disk-recorder")
            )
            gateway = GatewayProcess(config=config, log=tmp_path / "gateway.log")
            gateway.start()
            stack.callback(lambda: gateway.kill() if gateway.alive() else None)
            plant = Plant(
                state_dir=state_dir,
                stats=stats,
                gateway=gateway,
                subscriber=subscriber,
                commands=commands,
                metrics_port=metrics_port,
                scratch=tmp_path / "scratch",
                _ids=itertools.count(1),
            )
            wait_until(lambda: plant.documents_since(0) > 0, within_s=20)
            return plant

        yield start


def unhealthy_for(plant: Plant, path: Path) -> str:
    """Wait for ``/healthz`` to answer 503 with a reason about ``path``: the reason."""

    def reason() -> str | None:
        status, body = plant.health()
        found = [r for r in body["reasons"] if str(path) in r]
        return found[0] if status == 503 and found else None

    found: str = wait_until(reason, within_s=5)
    return found


def assert_polling_and_publishing_go_on(plant: Plant) -> None:
    since = time.time()
    wait_until(lambda: plant.documents_since(since) >= 4, within_s=5)  # basin every 0.25 s


def assert_flash_writes_refused(plant: Plant, cause: str) -> None:
    before = plant.x_zero_writes()
    result = plant.set_x_zero(0.125)
    assert result["status"] == "error", result
    reason = result["reason"]
    assert str(plant.state_dir / LEDGER) in reason, reason
    assert cause in reason, reason
    assert "refused" in reason, reason
    assert plant.x_zero_writes() == before  # nothing reached the sensor


def assert_recovered(plant: Plant, value: float) -> None:
    """Healthy again by itself (the next retry), flash writes counted and sent again."""
    wait_until(lambda: plant.health()[0] == 200, within_s=3 * RETRY_S)
    assert plant.writable(QUEUE) == 1.0
    before = plant.x_zero_writes()
    counted = ledger_counts(plant.state_dir, plant.scratch)[("cl2", "x_zero")]
    result = plant.set_x_zero(value)
    assert result["status"] == "ok", result
    assert result["written"] is True
    assert plant.x_zero_writes() == before + 1
    assert ledger_counts(plant.state_dir, plant.scratch)[("cl2", "x_zero")] == counted + 1
    assert plant.health()[0] == 200  # the ledger's file too
    assert plant.writable(LEDGER) == 1.0
    assert plant.writable(RECORDS) == 1.0


def test_a_full_disk_keeps_the_gateway_polling_and_it_recovers_when_space_returns(
    tmp_path: Path, plant_on: Callable[..., Plant], broker: Broker
) -> None:
    """The default ``mqtt.persist: outage``: the queue is written only in an outage."""
    with small_tmpfs(tmp_path / "disk", 2048) as disk:
        plant = plant_on(disk / "state")
        assert plant.health()[0] == 200
        assert plant.writable(QUEUE) == 1.0
        filler = fill(disk)
        # Full before any file failed: said at once, for the directory.
        reason = unhealthy_for(plant, disk / "state")
        assert "the disk is full" in reason
        assert metric(plant.metrics_port, "gateway_storage_free_bytes") == 0.0
        assert_polling_and_publishing_go_on(plant)
        assert_flash_writes_refused(plant, "the disk is full")
        assert plant.writable(LEDGER) == 0.0
        # A broker outage: the queue must be written now, and cannot; the cycles' messages
        # wait in memory and go out when the broker is back.
        broker.stop()
        outage = time.time()
        queue = disk / "state" / QUEUE
        reason = unhealthy_for(plant, queue)
        assert "the disk is full" in reason
        assert "messages wait in memory" in reason
        assert plant.health()[1]["storage"]["files"][QUEUE]["writable"] is False
        assert plant.writable(QUEUE) == 0.0
        time.sleep(2.0)
        broker.start()
        wait_until(lambda: plant.documents_since(outage + 1.0) > 0, within_s=15)
        # Failing for longer than two retries: still logged once, each file.
        time.sleep(max(0.0, outage + 2.5 * RETRY_S - time.time()))
        assert len(plant.warnings(str(queue), "cannot be written", "the disk is full")) == 1
        ledger = str(disk / "state" / LEDGER)
        assert len(plant.warnings("gateway.control.flash:", ledger, "cannot be written")) == 1
        filler.unlink()
        assert_recovered(plant, 0.25)
        assert "can be written again" in plant.gateway.log_text()
        assert plant.gateway.stop() == 0
        # What waited in memory during the outage was sent: nothing lost.
        made = [
            datetime.fromisoformat(json.loads(a.payload)["time"]).timestamp()
            for a in plant.subscriber.received()
            if a.topic == f"{BASE}/basin/state"
        ]
        during = [t for t in made if outage < t < outage + 2.0]
        assert len(during) >= 5  # a poll every 0.25 s for 2 s


def test_a_state_dir_the_kernel_made_read_only_and_its_repair(
    tmp_path: Path, plant_on: Callable[..., Plant]
) -> None:
    with ext4_image(tmp_path) as image:
        # Every message is written before it is sent: the failure is seen at once.
        plant = plant_on(image.mount_point / "state", persist="always")
        assert plant.health()[0] == 200
        image.fail()  # an I/O error: the kernel stops writing it
        queue = image.mount_point / "state" / QUEUE
        reason = unhealthy_for(plant, queue)
        assert "read-only" in reason, reason
        assert plant.writable(QUEUE) == 0.0
        assert_polling_and_publishing_go_on(plant)
        assert_flash_writes_refused(plant, "read-only")
        time.sleep(2.5 * RETRY_S)
        assert len(plant.warnings(str(queue), "cannot be written", "read-only")) == 1
        # The operator unmounts, checks and mounts the file system again; the gateway
        # opens its files afresh at its next retry.
        image.repair()
        assert_recovered(plant, 0.5)
        assert plant.gateway.stop() == 0


def test_a_read_only_state_dir_at_the_start_and_made_writable(
    tmp_path: Path, plant_on: Callable[..., Plant]
) -> None:
    source = tmp_path / "state"
    source.mkdir()
    with read_only_bind(source, tmp_path / "ro") as make_writable:
        plant = plant_on(tmp_path / "ro")  # polling and publishing, from the start
        reason = unhealthy_for(plant, tmp_path / "ro" / QUEUE)
        assert "read-only" in reason, reason
        assert_polling_and_publishing_go_on(plant)
        assert_flash_writes_refused(plant, "read-only")
        make_writable()
        assert_recovered(plant, 0.75)
        assert plant.gateway.stop() == 0
    assert (source / QUEUE).exists()
