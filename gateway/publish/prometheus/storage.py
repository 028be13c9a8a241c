"""The state directory's files as metrics and in ``/healthz``: can each be written, and room.

A full disk or a read-only file system under ``state_dir`` does not stop the polling: the
queues keep messages in memory and flash writes are refused (``shared/storage``). That is
a state the plant must hear of, so ``/healthz`` names each file that cannot be written,
with the cause and since when, and the metrics carry it for an alert; the room left is a
metric too, so a disk that fills up is seen before the first write fails.
"""

from __future__ import annotations

from datetime import UTC, datetime
from typing import TYPE_CHECKING

from prometheus_client.metrics_core import CounterMetricFamily, GaugeMetricFamily, Metric

if TYPE_CHECKING:
    from collections.abc import Iterator

    from gateway.shared.state import GatewayState
    from gateway.shared.storage import FileHealth


def storage_families(snapshot: GatewayState) -> Iterator[Metric]:
    """Each file's writability and failures, and the room left where they are."""
    files = snapshot.storage.files()
    if not files:
        return
    writable = GaugeMetricFamily(
        "gateway_storage_writable",
        "1 while the file in state_dir could be written at the last try (the MQTT queues, "
        "the flash-write ledger); 0: messages wait in memory, or flash writes are refused",
        labels=["file"],
    )
    failures = CounterMetricFamily(
        "gateway_storage_failures",
        "Times the file in state_dir stopped being writable (a full disk, a read-only file system)",
        labels=["file"],
    )
    for health in files:
        writable.add_metric([health.path.name], float(health.writable))
        failures.add_metric([health.path.name], float(health.failures))
    yield writable
    yield failures
    free = [d.free_bytes for d in snapshot.storage.directories() if d.free_bytes is not None]
    if free:
        yield GaugeMetricFamily(
            "gateway_storage_free_bytes",
            "Bytes left for the gateway on the file system of state_dir",
            value=float(min(free)),
        )


def storage_health(snapshot: GatewayState) -> tuple[list[str], dict[str, object]]:
    """The reasons ``/healthz`` gives for the files, and its ``storage`` part.

    A file that cannot be written is a reason; so is a state directory on a full or
    read-only file system before any of its files failed (a queue is written only during
    an outage with ``mqtt.persist: outage``, the ledger only at a flash write).
    """
    files = snapshot.storage.files()
    failing = {health.path.parent for health in files if not health.writable}
    reasons = [
        f"storage: {health.path} cannot be written since {_when(health)}: "
        f"{health.cause}; {health.meanwhile}"
        for health in files
        if not health.writable
    ]
    directories = snapshot.storage.directories()
    for directory in directories:
        if directory.path in failing:
            continue
        if directory.read_only:
            reasons.append(f"storage: {directory.path} is on a read-only file system")
        elif directory.free_bytes == 0:
            reasons.append(f"storage: {directory.path}: the disk is full")
    body: dict[str, object] = {
        "files": {
            health.path.name: {
                "path": str(health.path),
                "writable": health.writable,
                "cause": health.cause or None,
                "since": _when(health),
                "meanwhile": None if health.writable else health.meanwhile,
            }
            for health in files
        },
        "directories": {
            str(d.path): {"free_bytes": d.free_bytes, "read_only": d.read_only} for d in directories
        },
    }
    return reasons, body


def _when(health: FileHealth) -> str | None:
    if health.since is None:
        return None
    return datetime.fromtimestamp(health.since, UTC).isoformat(timespec="seconds")
