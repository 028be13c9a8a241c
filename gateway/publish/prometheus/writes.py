"""The families of what goes out: the MQTT and Sparkplug sessions and queues, writes, feeds.

And the web page's sign-ins, the way in for writes from a browser.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from prometheus_client.metrics_core import CounterMetricFamily, GaugeMetricFamily, Metric

if TYPE_CHECKING:
    from collections.abc import Iterator

    from gateway.shared.state import GatewayState


def mqtt_families(snapshot: GatewayState) -> Iterator[Metric]:
    """The MQTT sink's connection and queue, when MQTT is enabled."""
    mqtt = snapshot.mqtt
    if not mqtt.enabled:
        return
    yield GaugeMetricFamily(
        "gateway_mqtt_connected", "1 while connected to the broker", value=float(mqtt.connected)
    )
    yield GaugeMetricFamily(
        "gateway_mqtt_queue_depth", "Messages waiting for the broker", value=mqtt.queue_depth
    )
    yield GaugeMetricFamily(
        "gateway_mqtt_queue_max", "Bound of the store-and-forward queue", value=mqtt.queue_max
    )
    yield CounterMetricFamily(
        "gateway_mqtt_dropped", "Messages dropped because the queue was full", value=mqtt.dropped
    )
    yield CounterMetricFamily(
        "gateway_mqtt_published", "Messages delivered to the broker", value=mqtt.published
    )
    yield from _servers("gateway_mqtt", "MQTT connection", mqtt.server, mqtt.servers, mqtt.switches)
    yield GaugeMetricFamily(
        "gateway_mqtt_identity_conflict",
        "1 while another gateway holds this base topic first and this one stands down",
        value=float(mqtt.identity_conflict is not None),
    )


def _servers(
    prefix: str, what: str, server: str, servers: tuple[str, ...], switches: int
) -> Iterator[Metric]:
    """Which server of the list is in use (1) and the others (0); the moves between them."""
    info = GaugeMetricFamily(
        f"{prefix}_server",
        f"1 for the server of the list the {what} uses or tries now, 0 for the others",
        labels=["server", "position"],
    )
    for position, address in enumerate(servers):
        info.add_metric([address, str(position)], float(address == server))
    yield info
    yield CounterMetricFamily(
        f"{prefix}_server_switches",
        f"Moves of the {what} to another server of its list",
        value=switches,
    )


def sparkplug_families(snapshot: GatewayState) -> Iterator[Metric]:
    """The Sparkplug B session, when Sparkplug is enabled."""
    sparkplug = snapshot.sparkplug
    if not sparkplug.enabled:
        return
    yield GaugeMetricFamily(
        "gateway_sparkplug_connected",
        "1 while the Sparkplug session is connected to the broker",
        value=float(sparkplug.connected),
    )
    yield GaugeMetricFamily(
        "gateway_sparkplug_host_online",
        "1 while the primary host's STATE says online (always 1 without a primary host)",
        value=float(sparkplug.host_online),
    )
    yield GaugeMetricFamily(
        "gateway_sparkplug_bdseq", "bdSeq of the current Sparkplug session", value=sparkplug.bd_seq
    )
    yield from _servers(
        "gateway_sparkplug",
        "Sparkplug session",
        sparkplug.server,
        sparkplug.servers,
        sparkplug.switches,
    )
    yield CounterMetricFamily(
        "gateway_sparkplug_births",
        "NBIRTHs sent (new sessions and rebirths)",
        value=sparkplug.births,
    )
    yield CounterMetricFamily(
        "gateway_sparkplug_published",
        "Sparkplug messages handed to the broker",
        value=sparkplug.published,
    )
    yield GaugeMetricFamily(
        "gateway_sparkplug_queue_depth",
        "Sparkplug data stored while the host or the broker is away",
        value=sparkplug.queue_depth,
    )
    yield CounterMetricFamily(
        "gateway_sparkplug_dropped",
        "Sparkplug data dropped because the queue was full",
        value=sparkplug.dropped,
    )


def write_families(snapshot: GatewayState, now: float) -> Iterator[Metric]:
    """Commands and feeds by outcome, flash writes against their budget, feed health."""
    writes = snapshot.writes
    outcomes = CounterMetricFamily(
        "gateway_writes",
        "Commands and feed writes by kind (set, command, feed) and outcome",
        labels=["device", "kind", "outcome"],
    )
    for (device, kind, outcome), count in sorted(writes.outcomes.items()):
        outcomes.add_metric([device, kind, outcome], count)
    yield outcomes
    if writes.flash_counts is not None:
        counts = writes.flash_counts()
        total = CounterMetricFamily(
            "gateway_flash_writes",
            "Writes to flash-backed registers, ever (kept across restarts)",
            labels=["device", "point"],
        )
        today = GaugeMetricFamily(
            "gateway_flash_writes_today",
            "Writes to flash-backed registers this UTC day",
            labels=["device", "point"],
        )
        for key in sorted(counts.totals.keys() | writes.flash_budgets.keys()):
            total.add_metric(list(key), counts.totals.get(key, 0))
            today.add_metric(list(key), counts.today.get(key, 0))
        yield total
        yield today
    budget = GaugeMetricFamily(
        "gateway_flash_write_budget",
        "Flash writes allowed per point and UTC day (flash_write_budget)",
        labels=["device", "point"],
    )
    for key, allowed in sorted(writes.flash_budgets.items()):
        budget.add_metric(list(key), allowed)
    yield budget
    if writes.records_head is not None:
        head = writes.records_head()
        yield GaugeMetricFamily(
            "gateway_records_head_sequence",
            "Number of the newest record in the record store (numbered from 1, no gaps)",
            value=head.seq,
        )
        info = GaugeMetricFamily(
            "gateway_records_head",
            "The newest record's SHA-256 chain hash as a label: a copy kept elsewhere "
            "proves that nothing before it was rewritten",
            labels=["seq", "hash"],
        )
        info.add_metric([str(head.seq), head.hash], 1.0)
        yield info
    if not writes.feeds:
        return
    labels = ["feed", "source"]
    feed_writes = CounterMetricFamily(
        "gateway_feed_writes", "Values written by a feed", labels=labels
    )
    feed_errors = CounterMetricFamily(
        "gateway_feed_errors", "Failed feed writes and unusable source values", labels=labels
    )
    age = GaugeMetricFamily(
        "gateway_feed_source_age_seconds", "Age of the newest source value", labels=labels
    )
    stale = GaugeMetricFamily(
        "gateway_feed_stale", "1 while the source is older than max_age", labels=labels
    )
    fallback = GaugeMetricFamily(
        "gateway_feed_fallback",
        "1 while the sensor uses its own source because the feed's went stale",
        labels=labels,
    )
    for name, feed in sorted(writes.feeds.items()):
        labels_of = [name, feed.source]
        feed_writes.add_metric(labels_of, feed.writes)
        feed_errors.add_metric(labels_of, feed.errors)
        if feed.source_at is not None:
            age.add_metric(labels_of, max(0.0, now - feed.source_at))
        stale.add_metric(labels_of, float(feed.stale))
        fallback.add_metric(labels_of, float(feed.fallback))
    yield from (feed_writes, feed_errors, age, stale, fallback)


def web_families(snapshot: GatewayState, now: float) -> Iterator[Metric]:
    """The web page's sign-ins by outcome and its lock-outs, when the page is enabled."""
    web = snapshot.web
    if not web.enabled:
        return
    sign_ins = CounterMetricFamily(
        "gateway_web_sign_ins",
        "Sign-ins to the web page by outcome (ok, wrong, locked_out, busy)",
        labels=["outcome"],
    )
    for outcome in ("ok", "wrong", "locked_out", "busy"):
        sign_ins.add_metric([outcome], web.sign_ins.get(outcome, 0))
    yield sign_ins
    yield CounterMetricFamily(
        "gateway_web_lockouts",
        "Client addresses locked out of the web page's sign-in for guessing",
        value=web.lockouts,
    )
    yield GaugeMetricFamily(
        "gateway_web_locked_out_addresses",
        "Client addresses locked out of the web page's sign-in now",
        value=web.locked_out(now),
    )
