"""The families of the shared bus: other masters' requests per client, and their bus time."""

from __future__ import annotations

from collections import Counter
from typing import TYPE_CHECKING

from prometheus_client.metrics_core import (
    CounterMetricFamily,
    GaugeMetricFamily,
    HistogramMetricFamily,
    Metric,
)

from gateway.publish.prometheus.health import cumulative_buckets
from gateway.shared.state import WAIT_BUCKETS_S

if TYPE_CHECKING:
    from collections.abc import Iterator

    from gateway.shared.state import GatewayState


def shared_bus_families(snapshot: GatewayState) -> Iterator[Metric]:
    """Every family of the shared bus, per client and per bus (if it is enabled).

    The counters belong to the event loop; each is copied whole (``dict()``, atomic in
    CPython) before it is read here, as the lines' counters are.
    """
    shared = snapshot.shared_bus
    if not shared.enabled:
        return
    clients = dict(shared.clients)
    requests = CounterMetricFamily(
        "gateway_shared_bus_requests",
        "Requests of other masters, by client and Modbus function code",
        labels=["client", "function"],
    )
    exceptions = CounterMetricFamily(
        "gateway_shared_bus_exceptions",
        "Exception answers to other masters, by client and code (the device's or the gateway's)",
        labels=["client", "code"],
    )
    refused = CounterMetricFamily(
        "gateway_shared_bus_refused",
        "Requests the gateway answered itself, by client and reason",
        labels=["client", "reason"],
    )
    received = CounterMetricFamily(
        "gateway_shared_bus_received_bytes", "Bytes received from other masters", labels=["client"]
    )
    sent = CounterMetricFamily(
        "gateway_shared_bus_sent_bytes", "Bytes sent to other masters", labels=["client"]
    )
    cached = CounterMetricFamily(
        "gateway_shared_bus_cache_answers",
        "Reads answered from registers the device sent within the client's age",
        labels=["client"],
    )
    connections = GaugeMetricFamily(
        "gateway_shared_bus_connections", "Connections open now", labels=["client"]
    )
    shed = CounterMetricFamily(
        "gateway_shared_bus_shed",
        "Requests answered with exception 06 without being served, to keep the process for "
        "the polls, by client and reason",
        labels=["client", "reason"],
    )
    throttled = CounterMetricFamily(
        "gateway_shared_bus_throttled_seconds",
        "Time the client's connections waited for its rate limit, reading nothing",
        labels=["client"],
    )
    closed = CounterMetricFamily(
        "gateway_shared_bus_connections_closed",
        "Connections ended, by client and reason",
        labels=["client", "reason"],
    )
    wait = HistogramMetricFamily(
        "gateway_shared_bus_queue_wait_seconds",
        "Time other masters' requests waited for the line",
        labels=["client"],
    )
    for name, client in sorted(clients.items()):
        for function, count in sorted(dict(client.requests).items()):
            requests.add_metric([name, f"{function:02d}"], count)
        for code, count in sorted(dict(client.exceptions).items()):
            exceptions.add_metric([name, f"{code:02X}"], count)
        for reason, count in sorted(dict(client.refused).items()):
            refused.add_metric([name, reason], count)
        received.add_metric([name], client.received_bytes)
        sent.add_metric([name], client.sent_bytes)
        cached.add_metric([name], client.cache_answers)
        connections.add_metric([name], len(dict(client.peers)))
        for reason, count in sorted(dict(client.shed).items()):
            shed.add_metric([name, reason], count)
        throttled.add_metric([name], client.throttled_s)
        for reason, count in sorted(dict(client.closed).items()):
            closed.add_metric([name, reason], count)
        wait.add_metric(
            [name],
            cumulative_buckets(WAIT_BUCKETS_S, Counter(client.wait_buckets).__getitem__),
            sum_value=client.wait_sum_s,
        )
    yield from (requests, exceptions, refused, received, sent, cached, connections, wait)
    yield from (shed, throttled, closed)
    yield from _bus_families(snapshot)


def _bus_families(snapshot: GatewayState) -> Iterator[Metric]:
    shared = snapshot.shared_bus
    busy = CounterMetricFamily(
        "gateway_shared_bus_busy_seconds",
        "Bus time other masters' transactions took (part of gateway_bus_busy_seconds)",
        labels=["bus"],
    )
    share = GaugeMetricFamily(
        "gateway_shared_bus_share", "The share of bus time other masters may take", labels=["bus"]
    )
    refused = CounterMetricFamily(
        "gateway_shared_bus_busy_answers",
        "Requests answered with exception 06: no bus time within the wait, or the queue full",
        labels=["bus", "reason"],
    )
    for bus, stats in sorted(dict(shared.buses).items()):
        busy.add_metric([bus], stats.busy_s)
        share.add_metric([bus], shared.share)
        for reason, count in sorted(dict(stats.refused).items()):
            refused.add_metric([bus, reason], count)
    yield from (busy, share, refused)
