"""Pinned serial numbers in the metrics and ``/healthz``: which sensor answered instead.

One gauge per pinned device, ``gateway_device_identity_mismatch{bus,device}`` 1 while
another serial number answers. The serials themselves are not labels: a wrong serial is
whatever sensor happens to sit behind the swapped adapter, so every swap would start new
series, and an alert needs only the 1. They are in ``/healthz`` (and the ERROR log), with
what to do; the pinned serial as read is ``gateway_device_info``'s ``serial`` label.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Final

from prometheus_client.metrics_core import GaugeMetricFamily, Metric

from gateway.publish.prometheus.naming import DEVICE_LABELS

if TYPE_CHECKING:
    from collections.abc import Iterator, Sequence

    from gateway.line.engine.health import DeviceHealth

MISMATCH: Final = "mismatch"
UNPINNED: Final = "unpinned"
HELD: Final = frozenset({"mismatch", "unread"})  # not published, only the serial read
REMEDY: Final = (
    "check which adapter is which: give each bus its /dev/serial/by-id/... name as port "
    "(ls -l /dev/serial/by-id); if the sensor was replaced on purpose, set the device's "
    "serial_number to the serial that answered"
)
UNREAD_REMEDY: Final = (
    "the sensor answers but not its serial number: check the profile and the device, or "
    "remove serial_number to publish it unchecked"
)


def identity_families(health: Sequence[DeviceHealth]) -> Iterator[Metric]:
    """``gateway_device_identity_mismatch`` of every device with a pinned serial number."""
    mismatch = GaugeMetricFamily(
        "gateway_device_identity_mismatch",
        "1 while another serial number than the pinned serial_number answers at the "
        "device's address (nothing is published for it; /healthz names both), else 0; "
        "only devices with serial_number",
        labels=DEVICE_LABELS,
    )
    for entry in health:
        if entry.identity != UNPINNED:
            mismatch.add_metric([entry.bus, entry.device], float(entry.identity == MISMATCH))
    yield mismatch


def identity_report(health: Sequence[DeviceHealth]) -> list[dict[str, object]]:
    """The held devices for ``/healthz``: pinned and answering serials, and what to do."""
    return [
        {
            "bus": entry.bus,
            "device": entry.device,
            "address": entry.address,
            "identity": entry.identity,
            "expected_serial": entry.expected_serial,
            "answered_serial": entry.answered_serial,
            "action": REMEDY if entry.identity == MISMATCH else UNREAD_REMEDY,
        }
        for entry in health
        if entry.identity in HELD
    ]
