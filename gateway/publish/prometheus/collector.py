"""The collector: every metric family built from one snapshot of the state per scrape."""

from __future__ import annotations

import time
from typing import TYPE_CHECKING

from prometheus_client.metrics_core import GaugeMetricFamily, Metric
from prometheus_client.registry import Collector

from gateway.publish.prometheus.care import care_families
from gateway.publish.prometheus.clock import clock_families
from gateway.publish.prometheus.health import device_families, line_families
from gateway.publish.prometheus.identity_mismatch import identity_families
from gateway.publish.prometheus.reloads import reload_families
from gateway.publish.prometheus.selection import Selection
from gateway.publish.prometheus.shared_bus import shared_bus_families
from gateway.publish.prometheus.storage import storage_families
from gateway.publish.prometheus.values import value_families
from gateway.publish.prometheus.writes import (
    mqtt_families,
    sparkplug_families,
    web_families,
    write_families,
)

if TYPE_CHECKING:
    from collections.abc import Iterator

    from gateway.shared.state import GatewayState


class GatewayCollector(Collector):
    """Builds every metric family from one snapshot of the gateway state per scrape.

    Example::

        registry = CollectorRegistry()
        registry.register(GatewayCollector(state, selection=Selection.of(config.prometheus)))
        generate_latest(registry)  # the text exposition
    """

    def __init__(self, state: GatewayState, *, selection: Selection | None = None) -> None:
        """Read ``state`` at every scrape; export the points ``selection`` selects.

        Default: the process values and status of every device, new names only.
        """
        self._state = state
        self.selection = selection or Selection()
        # The wall-clock start, from the state's monotonic start, fixed once.
        self._start_time = time.time() - (time.monotonic() - state.started)

    def describe(self) -> list[Metric]:
        """Nothing to describe up front: the families depend on the devices polled."""
        return []

    def collect(self) -> Iterator[Metric]:
        """Every family, from one consistent snapshot."""
        now = time.monotonic()
        snapshot = self._state.snapshot()
        health = snapshot.health()
        up = GaugeMetricFamily("gateway_up", "1 while the gateway serves metrics")
        up.add_metric([], 1.0)
        yield up
        yield GaugeMetricFamily(
            "gateway_start_time_seconds",
            "Start time of the gateway, seconds since the Unix epoch",
            value=self._start_time,
        )
        yield from value_families(snapshot, now, self.selection)
        yield from device_families(snapshot, health)
        yield from identity_families(health)
        yield from care_families(snapshot)
        yield from line_families(snapshot, health, now)
        yield from mqtt_families(snapshot)
        yield from sparkplug_families(snapshot)
        yield from write_families(snapshot, now)
        yield from web_families(snapshot, now)
        yield from shared_bus_families(snapshot)
        yield from storage_families(snapshot)
        yield from reload_families(snapshot)
        yield from clock_families(snapshot)
