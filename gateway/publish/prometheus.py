"""Prometheus: ``/metrics`` built at scrape time from the gateway state, and ``/healthz``.

:class:`GatewayCollector` is a custom collector: it keeps no metric objects of its own
and builds every family from one :meth:`GatewayState.snapshot` when Prometheus scrapes.
Measured on prometheus-client 0.26, that costs about 1 ms per 10,000 values, against
8-23 ms for the same updates through labelled ``Gauge.set()`` calls on every poll, and
the bus tasks do no metrics work at all.

:class:`MetricsServer` serves the collector's own registry (never the global one) from a
``ThreadingHTTPServer`` in a daemon thread, so a slow scrape never blocks a bus task.

Naming (the full table is ``docs/metrics.md``): a value is ``gateway_<point>``, with its
unit in the name where the profile fixes it (``gateway_temperature_celsius``) and in a
``unit`` label where a unit register selects it (``gateway_oxygen{unit="mg/l"}``) or the
unit has no conventional name (``gateway_nominal_slope{unit="nA/ppm"}``). Faults are
never numbers: a point whose latest sample is a fault has no value sample, and
``gateway_value_fault{fault="overrange"}`` says why. Identity is not a measurement: serial,
firmware and hardware are labels of one info series per device,
``gateway_device_info{serial="...",firmware="1503",hardware="1130"} 1``.
"""

from __future__ import annotations

import functools
import json
import logging
import math
import socket
import socketserver
import sys
import threading
import time
from dataclasses import dataclass, field
from datetime import datetime
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import TYPE_CHECKING, Final, Self
from urllib.parse import urlsplit

from prometheus_client import CollectorRegistry
from prometheus_client.exposition import CONTENT_TYPE_PLAIN_0_0_4, generate_latest
from prometheus_client.metrics_core import (
    CounterMetricFamily,
    GaugeMetricFamily,
    HistogramMetricFamily,
    InfoMetricFamily,
    Metric,
)
from prometheus_client.registry import Collector

from gateway.errors import ConfigError, PublishError
from gateway.line.port import LATENCY_BUCKETS_S, ErrorKind
from gateway.line.samples import Quality
from gateway.profiles import builtin_profiles, get_profile
from gateway.wire.codec import NUMERIC_TYPES, BitfieldValue, DataType, EnumValue

if TYPE_CHECKING:
    from collections.abc import Iterable, Iterator, Mapping

    from gateway.line.health import DeviceHealth
    from gateway.line.port import LineStats
    from gateway.line.samples import Sample
    from gateway.publish.state import GatewayState

_LOGGER = logging.getLogger(__name__)

PREFIX: Final = "gateway_"
DEFAULT_HOST: Final = "0.0.0.0"  # noqa: S104 - prometheus.host's documented default
DEFAULT_PORT: Final = 9108  # prometheus.port's default, as in the product contract
POLL_INTERVAL_S: Final = 0.1  # serve_forever checks for shutdown this often: bounds stop()
STOP_TIMEOUT_S: Final = 2.0  # wait for the server thread to end after shutdown
REQUEST_TIMEOUT_S: Final = 10.0  # socket timeout of one HTTP connection
_INTERNAL_ERROR: Final = (HTTPStatus.INTERNAL_SERVER_ERROR, "text/plain", b"internal error\n")

# Units the profiles fix, as Prometheus names them in a metric name. The sensor's own unit
# is kept (no conversion to amperes or pascals): the value is the one the sensor sent.
UNIT_SUFFIXES: Final[Mapping[str, str]] = {
    "°C": "celsius",
    "nA": "nanoamperes",
    "mA": "milliamperes",
    "\u00b5V": "microvolts",  # MICRO SIGN, as in the profiles
    "\u03bcV": "microvolts",  # GREEK SMALL LETTER MU, its look-alike
    "hPa": "hectopascals",
    "mbar": "millibars",
    "s": "seconds",
    "ms": "milliseconds",
    "°": "degrees",
    "mS/cm": "millisiemens_per_centimetre",
    "h": "hours",
    "min": "minutes",
}

# The failure classes exported (zero included) for every configured device.
ERROR_KINDS: Final = (
    ErrorKind.TIMEOUT,
    ErrorKind.CRC,
    ErrorKind.EXCEPTION,
    ErrorKind.WRONG_ADDRESS,
    ErrorKind.STALE,
    ErrorKind.NOISE,
    ErrorKind.MALFORMED,
)

# The identity labels of ``gateway_device_info`` and the points that fill each, first one
# read wins; the points of one choice are joined with dots (digiLine hardware major.minor,
# S10 6.1 and H10 6.1.1). tecLine and Reiss send versions as plain integers ("Device data":
# Hardware 1130, Firmware 1503): they stay as sent, no decimal point guessed into them.
IDENTITY_LABELS: Final[Mapping[str, tuple[tuple[str, ...], ...]]] = {
    "serial": (("serial_number",),),
    "firmware": (("software_version",), ("firmware_version",)),
    "hardware": (("hardware_version_major", "hardware_version_minor"), ("hardware_version",)),
}
# Identity numbers that were gauges before they were labels of ``gateway_device_info``
# (``gateway_firmware_version 1503``). Still exported for one release, marked deprecated in
# their HELP and in docs/metrics.md; removed in the next release.
DEPRECATED_IDENTITY_GAUGES: Final = frozenset(
    {"firmware_version", "hardware_version", "hardware_version_major", "hardware_version_minor"}
)
DEPRECATION_NOTE: Final = (
    " (deprecated: a label of gateway_device_info now; this gauge goes in the next release)"
)

_NUMERIC_POINT_TYPES: Final = NUMERIC_TYPES | {DataType.BOOL}
_DEVICE: Final = ("bus", "device")
_VALUE: Final = ("bus", "device", "profile")
_POINT: Final = ("bus", "device", "profile", "point")

# Every series name the collector exports besides the values (histogram and counter
# suffixes included). A point whose value family would take one of them gets ``_value``.
RESERVED_NAMES: Final = frozenset(
    {
        "gateway_up",
        "gateway_start_time_seconds",
        "gateway_value_age_seconds",
        "gateway_value_fault",
        "gateway_status_flag",
        "gateway_enum_info",
        "gateway_device_info",
        "gateway_device_online",
        "gateway_poll_lag_seconds",
        "gateway_unreadable_points",
        "gateway_bus_utilisation_ratio",
        "gateway_bus_port_open",
        "gateway_mqtt_connected",
        "gateway_mqtt_queue_depth",
        "gateway_mqtt_queue_max",
        "gateway_request_latency_seconds",
        "gateway_request_latency_seconds_bucket",
        "gateway_request_latency_seconds_sum",
        "gateway_request_latency_seconds_count",
        "gateway_flash_writes_today",
        "gateway_flash_write_budget",
        "gateway_feed_source_age_seconds",
        "gateway_feed_stale",
        "gateway_feed_fallback",
    }
    | {
        name + suffix
        for name in (
            "gateway_requests",
            "gateway_responses",
            "gateway_errors",
            "gateway_exceptions",
            "gateway_retries",
            "gateway_tolerated_quirks",
            "gateway_missed_deadlines",
            "gateway_bus_busy_seconds",
            "gateway_bus_port_failures",
            "gateway_mqtt_dropped",
            "gateway_mqtt_published",
            "gateway_writes",
            "gateway_flash_writes",
            "gateway_feed_writes",
            "gateway_feed_errors",
        )
        for suffix in ("", "_total")
    }
)


# --- value naming -------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class ValueNaming:
    """Where a numeric point's value goes: its family and how its unit is shown.

    Example::

        value_naming("temperature", "°C")  # gateway_temperature_celsius, no unit label
        value_naming("oxygen", None, unit_from=True)  # gateway_oxygen, unit label from the sample
        value_naming("nominal_slope", "nA/ppm")  # gateway_nominal_slope, unit="nA/ppm"
    """

    family: str
    unit_label: bool = False  # the family's samples carry a ``unit`` label
    from_register: bool = False  # ... taken from the sample (a unit register selected it)
    fixed_unit: str | None = None  # ... or this fixed unit without a conventional name


def value_naming(point: str, unit: str | None, *, unit_from: bool = False) -> ValueNaming:
    """The family of a point's value, after Prometheus's naming conventions."""
    base = PREFIX + point
    if unit_from:
        return ValueNaming(_unreserved(base), unit_label=True, from_register=True)
    if not unit:
        return ValueNaming(_unreserved(base))
    suffix = UNIT_SUFFIXES.get(unit)
    if suffix is None:
        return ValueNaming(_unreserved(base), unit_label=True, fixed_unit=unit)
    # ``operating_seconds`` in s stays gateway_operating_seconds, not ..._seconds_seconds.
    name = base if base.endswith("_" + suffix) else f"{base}_{suffix}"
    return ValueNaming(_unreserved(name))


def _unreserved(name: str) -> str:
    return f"{name}_value" if name in RESERVED_NAMES else name


@functools.cache
def _profile_naming(profile_id: str, point_name: str) -> tuple[ValueNaming, str] | None:
    """A profile point's naming and description; ``None`` for an unknown profile or point."""
    try:
        point = get_profile(profile_id).point(point_name)
    except ConfigError:
        return None
    naming = value_naming(point.name, point.unit, unit_from=point.unit_from is not None)
    deprecated = point.name in DEPRECATED_IDENTITY_GAUGES
    return naming, point.description + (DEPRECATION_NOTE if deprecated else "")


@functools.cache
def _labelled_families() -> frozenset[str]:
    """Value families that carry a ``unit`` label for some point of some built-in profile.

    Decided from the profiles, not from what one scrape happens to hold, so a family's
    label names never change between scrapes: a point without a unit that shares such a
    family gets ``unit=""`` (which Prometheus stores as no label at all).
    """
    families = set()
    for profile in builtin_profiles().values():
        for point in profile.points:
            if point.dtype in _NUMERIC_POINT_TYPES:
                unit_from = point.unit_from is not None
                naming = value_naming(point.name, point.unit, unit_from=unit_from)
                if naming.unit_label:
                    families.add(naming.family)
    return frozenset(families)


def _naming_of(sample: Sample) -> tuple[ValueNaming, str]:
    known = _profile_naming(sample.profile, sample.point)
    if known is not None:
        return known
    # A profile the gateway does not ship: judge by the sample's unit alone.
    return value_naming(sample.point, sample.unit), f"{sample.point} of {sample.profile}"


@dataclass(slots=True)
class _ValueFamily:
    documentation: str
    rows: dict[tuple[str, ...], tuple[str | None, float]] = field(default_factory=dict)
    has_unit: bool = False


# --- the collector --------------------------------------------------------------------------


class GatewayCollector(Collector):
    """Builds every metric family from one snapshot of the gateway state per scrape.

    Example::

        registry = CollectorRegistry()
        registry.register(GatewayCollector(state))
        generate_latest(registry)  # the text exposition
    """

    def __init__(self, state: GatewayState) -> None:
        """Read ``state`` at every scrape."""
        self._state = state
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
        yield from _values(snapshot, now)
        yield from _devices(snapshot, health)
        yield from _lines(snapshot, health, now)
        yield from _mqtt(snapshot)
        yield from _writes(snapshot, now)


def _values(snapshot: GatewayState, now: float) -> Iterator[Metric]:
    """Values, faults, status bits, enums and ages of every point's latest sample."""
    values = _Values()
    for sample in snapshot.latest.values():
        if not snapshot.is_stale(sample, now):  # an old reading is not the present
            values.add(sample)
    yield from values.families()
    yield _ages(snapshot, now)


class _Values:
    """The value-like families of one scrape, filled sample by sample."""

    def __init__(self) -> None:
        self._values: dict[str, _ValueFamily] = {}
        self._faults = GaugeMetricFamily(
            "gateway_value_fault",
            "1 while the latest sample of a point is a sensor fault (named in 'fault')",
            labels=[*_POINT, "fault"],
        )
        self._flags = GaugeMetricFamily(
            "gateway_status_flag",
            "State of one named bit of a status or error word (0 or 1)",
            labels=[*_POINT, "flag"],
        )
        self._enums = GaugeMetricFamily(
            "gateway_enum_info",
            "The current label (and code) of an enumerated point; always 1",
            labels=[*_POINT, "label", "code"],
        )

    def add(self, sample: Sample) -> None:
        """Export one latest sample: a fault by name, never a number; comms errors not."""
        point = [sample.bus, sample.device, sample.profile, sample.point]
        if sample.quality is Quality.FAULT:
            self._faults.add_metric([*point, sample.fault or "unknown"], 1.0)
            return
        if sample.quality is not Quality.GOOD:
            return
        value = sample.value
        if isinstance(value, BitfieldValue):
            for flag, state in value.flags:
                self._flags.add_metric([*point, flag], float(state))
        elif isinstance(value, EnumValue):
            self._enums.add_metric([*point, value.label, str(value.code)], 1.0)
        elif isinstance(value, bool | int | float):
            self._add_value(sample, float(value))
        # strings and date-times are not numbers: MQTT carries them

    def _add_value(self, sample: Sample, value: float) -> None:
        naming, description = _naming_of(sample)
        unit: str | None = None
        if naming.from_register:
            if not sample.unit:
                return  # the unit register is unread or unknown: a number without its unit
            unit = sample.unit
        elif naming.fixed_unit is not None:
            unit = naming.fixed_unit
        family = self._values.get(naming.family)
        if family is None:
            family = self._values[naming.family] = _ValueFamily(description)
        key = (sample.bus, sample.device, sample.profile)
        if key in family.rows:
            # Two points of one device named into one family (``x`` in s next to a
            # dimensionless ``x_seconds``): no profile has such a pair; keep the first.
            _LOGGER.debug("%s: %s also maps to %s; left out", sample.device, sample.point, naming)
            return
        family.rows[key] = (unit, value)
        family.has_unit |= unit is not None

    def families(self) -> Iterator[Metric]:
        """One gauge per value family (label names fixed per family), then the rest."""
        labelled = _labelled_families()
        for name in sorted(self._values):
            family = self._values[name]
            with_unit = family.has_unit or name in labelled
            gauge = GaugeMetricFamily(
                name, family.documentation, labels=[*_VALUE, "unit"] if with_unit else _VALUE
            )
            for key, (unit, value) in family.rows.items():
                gauge.add_metric([*key, unit or ""] if with_unit else list(key), value)
            yield gauge
        yield from (self._faults, self._flags, self._enums)


def _ages(snapshot: GatewayState, now: float) -> Metric:
    ages = GaugeMetricFamily(
        "gateway_value_age_seconds",
        "Seconds since the last good sample of a polled point",
        labels=_POINT,
    )
    for (bus, device, point), sample in snapshot.last_good.items():
        info = snapshot.devices.get((bus, device))
        if info is not None and point in info.intervals and info.intervals[point] is None:
            continue  # identity, read once per connection: its age says nothing
        ages.add_metric([bus, device, sample.profile, point], max(0.0, now - sample.monotonic))
    return ages


def _identity_text(
    snapshot: GatewayState, bus: str, device: str, choices: Iterable[tuple[str, ...]]
) -> str:
    """The first choice whose points have all been read, joined with dots; else ``""``."""
    for points in choices:
        parts = [_point_text(snapshot, bus, device, point) for point in points]
        if all(parts):
            return ".".join(parts)
    return ""


def _point_text(snapshot: GatewayState, bus: str, device: str, point: str) -> str:
    sample = snapshot.last_good.get((bus, device, point))
    if sample is None or sample.value is None:
        return ""
    value = sample.value
    return (value.isoformat() if isinstance(value, datetime) else str(value)).strip()


def _devices(snapshot: GatewayState, health: list[DeviceHealth]) -> Iterator[Metric]:
    """Identity and availability of every configured device."""
    # An info family: ``gateway_device_info{...} 1``, the Prometheus way to export text
    # that names rather than measures (a ``gauge`` in the 0.0.4 text format).
    info_family = InfoMetricFamily(
        "gateway_device",
        "A configured device, its address and identity as last read; always 1",
        labels=[*_VALUE, "address"],
    )
    for (bus, name), info in snapshot.devices.items():
        identity = {
            label: _identity_text(snapshot, bus, name, choices)
            for label, choices in IDENTITY_LABELS.items()
        }
        info_family.add_metric([bus, name, info.profile, str(info.address)], identity)
    yield info_family
    online = GaugeMetricFamily(
        "gateway_device_online",
        "1 while a device answers, 0 once it is offline; absent until it is first heard of",
        labels=_VALUE,
    )
    # The bus task's view is the freshest; the state's events cover devices it lacks.
    availability = {(h.bus, h.device): h.online for h in health}
    for key, info in snapshot.devices.items():
        state = availability.get(key, info.online)
        if state is not None:
            online.add_metric([info.bus, info.name, info.profile], float(state))
    yield online
    lag = GaugeMetricFamily(
        "gateway_poll_lag_seconds",
        "How late the device's last poll started after its deadline",
        labels=_DEVICE,
    )
    missed = CounterMetricFamily(
        "gateway_missed_deadlines",
        "Poll deadlines skipped because the line could not keep up",
        labels=_DEVICE,
    )
    unreadable = GaugeMetricFamily(
        "gateway_unreadable_points",
        "Points the device refuses to return (exception 02 to a single read)",
        labels=_DEVICE,
    )
    for entry in health:
        labels = [entry.bus, entry.device]
        lag.add_metric(labels, entry.lag_s)
        missed.add_metric(labels, entry.missed_deadlines)
        unreadable.add_metric(labels, entry.unreadable_points)
    yield lag
    yield missed
    yield unreadable


@dataclass(frozen=True, slots=True)
class _LineCopy:
    """One bus's counters, copied (``dict()`` of a dict is atomic under the GIL).

    Configured devices get every counter and error kind from zero, so ``rate()`` and
    alerts work before the first failure; other addresses (a stray answer, a broadcast
    as address 0) only show what they have.
    """

    requests: dict[int, int]
    responses: dict[int, int]
    errors: dict[tuple[int, str], int]
    exception_codes: dict[tuple[int, int], int]
    retries: dict[int, int]
    tolerated: dict[tuple[int, str], int]
    latency_buckets: dict[tuple[int, float], int]
    latency_sum_s: dict[int, float]

    @classmethod
    def of(cls, stats: LineStats, configured: Iterable[int]) -> _LineCopy:
        copy = cls(
            requests=dict(stats.requests),
            responses=dict(stats.responses),
            errors=dict(stats.errors),
            exception_codes=dict(stats.exception_codes),
            retries=dict(stats.retries),
            tolerated=dict(stats.tolerated),
            latency_buckets=dict(stats.latency_buckets),
            latency_sum_s=dict(stats.latency_sum_s),
        )
        for address in configured:
            for counts in (copy.requests, copy.responses, copy.retries):
                counts.setdefault(address, 0)
            for kind in ERROR_KINDS:
                copy.errors.setdefault((address, kind), 0)
            copy.latency_sum_s.setdefault(address, 0.0)
        return copy


def _lines(snapshot: GatewayState, health: list[DeviceHealth], now: float) -> Iterator[Metric]:
    """Transactions, failures and latency per bus and device; the port of every bus."""
    names_of: dict[str, dict[int, str]] = {}
    for info in snapshot.devices.values():
        names_of.setdefault(info.bus, {})[info.address] = info.name
    for entry in health:  # a device the state was not told about still has a name
        names_of.setdefault(entry.bus, {}).setdefault(entry.address, entry.device)
    families = _LineFamilies()
    for bus, stats in sorted(snapshot.lines.items()):
        families.add(bus, stats, names_of.get(bus, {}), now)
    return families.families()


class _LineFamilies:
    """The bus and transaction families of one scrape, filled bus by bus."""

    def __init__(self) -> None:
        self._requests = CounterMetricFamily("gateway_requests", "Requests sent", labels=_DEVICE)
        self._responses = CounterMetricFamily(
            "gateway_responses", "Valid answers received (exceptions excluded)", labels=_DEVICE
        )
        self._errors = CounterMetricFamily(
            "gateway_errors",
            "Failed transactions and discarded input, by kind",
            labels=[*_DEVICE, "kind"],
        )
        self._exceptions = CounterMetricFamily(
            "gateway_exceptions", "Modbus exception answers, by code", labels=[*_DEVICE, "code"]
        )
        self._retries = CounterMetricFamily("gateway_retries", "Requests retried", labels=_DEVICE)
        self._quirks = CounterMetricFamily(
            "gateway_tolerated_quirks",
            "Answers accepted through a documented device quirk",
            labels=[*_DEVICE, "quirk"],
        )
        self._latency = HistogramMetricFamily(
            "gateway_request_latency_seconds",
            "Time from sending a request to the answer's last byte",
            labels=_DEVICE,
        )
        self._utilisation = GaugeMetricFamily(
            "gateway_bus_utilisation_ratio",
            "Share of time since start the line carried the gateway's transactions",
            labels=["bus"],
        )
        self._busy = CounterMetricFamily(
            "gateway_bus_busy_seconds",
            "Time the line carried the gateway's transactions (rate() it for utilisation)",
            labels=["bus"],
        )
        self._port_open = GaugeMetricFamily(
            "gateway_bus_port_open", "1 while the bus's serial port is open", labels=["bus"]
        )
        self._port_failures = CounterMetricFamily(
            "gateway_bus_port_failures",
            "Times the port could not be opened or was lost",
            labels=["bus"],
        )

    def add(self, bus: str, stats: LineStats, names: Mapping[int, str], now: float) -> None:
        """One bus: its counters per device (by name; ``address_N`` if not configured)."""
        copy = _LineCopy.of(stats, names)

        def device(address: int) -> str:
            return names.get(address, f"address_{address}")

        for family, counts in (
            (self._requests, copy.requests),
            (self._responses, copy.responses),
            (self._retries, copy.retries),
        ):
            for address, count in sorted(counts.items()):
                family.add_metric([bus, device(address)], count)
        for (address, kind), count in sorted(copy.errors.items()):
            self._errors.add_metric([bus, device(address), kind], count)
        for (address, code), count in sorted(copy.exception_codes.items()):
            self._exceptions.add_metric([bus, device(address), f"{code:02d}"], count)
        for (address, quirk), count in sorted(copy.tolerated.items()):
            self._quirks.add_metric([bus, device(address), quirk], count)
        for address, total_s in sorted(copy.latency_sum_s.items()):
            buckets = _buckets(copy.latency_buckets, address)
            self._latency.add_metric([bus, device(address)], buckets, total_s)
        self._utilisation.add_metric([bus], stats.utilisation(now))
        self._busy.add_metric([bus], stats.busy_s)
        self._port_open.add_metric([bus], float(stats.port_open))
        self._port_failures.add_metric([bus], stats.port_failures)

    def families(self) -> Iterator[Metric]:
        """Every family, empty ones included (their HELP and TYPE still document them)."""
        yield from (self._requests, self._responses, self._errors, self._exceptions)
        yield from (self._retries, self._quirks, self._latency)
        yield from (self._utilisation, self._busy, self._port_open, self._port_failures)


def _buckets(counts: Mapping[tuple[int, float], int], address: int) -> list[tuple[str, float]]:
    """Cumulative buckets, made non-decreasing.

    The bus task adds one observation bucket by bucket; a copy taken in between can hold
    a lower bucket already counted and a higher one not yet: the running maximum keeps
    the histogram valid (the observation then shows fully at the next scrape).
    """
    buckets = []
    running = 0
    for bound in (*LATENCY_BUCKETS_S, math.inf):
        running = max(running, counts.get((address, bound), 0))
        buckets.append(("+Inf" if math.isinf(bound) else repr(bound), float(running)))
    return buckets


def _mqtt(snapshot: GatewayState) -> Iterator[Metric]:
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


def _writes(snapshot: GatewayState, now: float) -> Iterator[Metric]:
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


# --- /healthz --------------------------------------------------------------------------------


def health_report(state: GatewayState) -> tuple[bool, dict[str, object]]:
    """Whether the gateway is healthy, and the ``/healthz`` body that says why (not).

    Healthy: every bus port is open, and MQTT is connected or buffering within its bound.
    A device that does not answer is the device's problem, not the gateway's: it shows
    in ``devices_online`` and the metrics, not in the status.
    """
    snapshot = state.snapshot()
    availability = {(h.bus, h.device): h.online for h in snapshot.health()}
    reasons: list[str] = []
    buses: dict[str, object] = {}
    for bus, stats in sorted(snapshot.lines.items()):
        devices = [info for info in snapshot.devices.values() if info.bus == bus]
        online = sum(
            1 for info in devices if availability.get((bus, info.name), info.online) is True
        )
        buses[bus] = {
            "port_open": stats.port_open,
            "devices_online": online,
            "devices": len(devices),
        }
        if not stats.port_open:
            reasons.append(f"bus {bus}: port not open ({stats.port_failures} failures)")
    mqtt = snapshot.mqtt
    if not mqtt.healthy:
        why = f": {mqtt.last_error}" if mqtt.last_error else ""
        reasons.append(
            f"mqtt: not connected and the queue is full ({mqtt.queue_depth}/{mqtt.queue_max}){why}"
        )
    body: dict[str, object] = {
        "status": "unhealthy" if reasons else "ok",
        "reasons": reasons,
        "buses": buses,
        "mqtt": {
            "enabled": mqtt.enabled,
            "connected": mqtt.connected,
            "healthy": mqtt.healthy,
            "queue_depth": mqtt.queue_depth,
            "queue_max": mqtt.queue_max,
            "dropped": mqtt.dropped,
            "published": mqtt.published,
            "last_error": mqtt.last_error,
        },
    }
    return not reasons, body


# --- the HTTP server -------------------------------------------------------------------------


class _Server(ThreadingHTTPServer):
    """The HTTP server with what its handlers read."""

    daemon_threads = True  # a hung scraper never holds up shutdown

    def __init__(
        self, address: tuple[str, int], *, state: GatewayState, registry: CollectorRegistry
    ) -> None:
        self.state = state
        self.registry = registry
        super().__init__(address, _Handler)

    def server_bind(self) -> None:
        # HTTPServer.server_bind looks the host's FQDN up (reverse DNS, slow or hanging
        # on a plant network); the name is never used here.
        socketserver.TCPServer.server_bind(self)
        host, port = self.server_address[:2]
        self.server_name = str(host)
        self.server_port = int(port)

    def handle_error(self, request: object, client_address: object) -> None:  # noqa: ARG002
        # Called in the except block of the request's thread. A scraper that hangs up
        # mid-answer is not worth the base's traceback on standard error.
        _LOGGER.debug("metrics request from %s failed: %r", client_address, sys.exc_info()[1])


class _Server6(_Server):
    address_family = socket.AF_INET6


class _Handler(BaseHTTPRequestHandler):
    """``GET /metrics``, ``GET /healthz``; anything else is 404."""

    server: _Server
    server_version = "rs485-gateway"
    timeout = REQUEST_TIMEOUT_S  # a client that connects and says nothing is let go

    def do_GET(self) -> None:  # the name http.server dispatches to
        """Answer one request."""
        path = urlsplit(self.path).path
        try:
            status, content_type, body = self._answer(path)
        except Exception:  # a broken scrape must not end the thread silently: log, answer 500
            _LOGGER.exception("GET %s failed", path)
            status, content_type, body = _INTERNAL_ERROR
        self.send_response(status)
        self.send_header("Content-Type", content_type)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "no-store")
        self.end_headers()
        self.wfile.write(body)

    def _answer(self, path: str) -> tuple[HTTPStatus, str, bytes]:
        if path == "/metrics":
            return HTTPStatus.OK, CONTENT_TYPE_PLAIN_0_0_4, generate_latest(self.server.registry)
        if path == "/healthz":
            healthy, report = health_report(self.server.state)
            status = HTTPStatus.OK if healthy else HTTPStatus.SERVICE_UNAVAILABLE
            return status, "application/json", json.dumps(report).encode()
        text = f"{path} not found: GET /metrics or /healthz\n"
        return HTTPStatus.NOT_FOUND, "text/plain; charset=utf-8", text.encode()

    def log_message(self, format: str, *args: object) -> None:  # noqa: A002 - the base's name
        """Requests go to the debug log, not to standard error."""
        _LOGGER.debug("%s %s", self.address_string(), format % args)


class MetricsServer:
    """Serves ``/metrics`` and ``/healthz`` for a :class:`GatewayState` in its own thread.

    Example::

        server = MetricsServer(state, host="0.0.0.0", port=9108)
        server.start()  # PublishError if the port is taken
        ...
        server.stop()

    ``port=0`` binds a free port; :attr:`port` tells which.
    """

    def __init__(
        self, state: GatewayState, *, host: str = DEFAULT_HOST, port: int = DEFAULT_PORT
    ) -> None:
        """Serve ``state`` on ``host:port`` once started."""
        self.state = state
        self.host = host
        self.registry = CollectorRegistry()
        self.collector = GatewayCollector(state)
        self.registry.register(self.collector)
        self._requested_port = port
        self._bound_port: int | None = None
        self._server: _Server | None = None
        self._thread: threading.Thread | None = None

    @property
    def port(self) -> int:
        """The port bound by the last start (the requested one before any)."""
        return self._requested_port if self._bound_port is None else self._bound_port

    def start(self) -> None:
        """Bind and serve in a daemon thread; a port in use raises :class:`PublishError`."""
        if self._server is not None:
            return
        server_class = _Server6 if ":" in self.host else _Server
        where = f"[{self.host}]" if ":" in self.host else self.host
        try:
            server = server_class(
                (self.host, self._requested_port), state=self.state, registry=self.registry
            )
        except OSError as exc:
            raise PublishError(
                f"cannot serve metrics on {where}:{self._requested_port}: "
                f"{exc.strerror or exc} (prometheus.host, prometheus.port)"
            ) from exc
        thread = threading.Thread(
            target=server.serve_forever,
            kwargs={"poll_interval": POLL_INTERVAL_S},
            name=f"prometheus[{where}:{server.server_address[1]}]",
            daemon=True,
        )
        self._server, self._thread = server, thread
        self._bound_port = int(server.server_address[1])
        thread.start()
        _LOGGER.info("serving /metrics and /healthz on %s:%d", where, self.port)

    def stop(self) -> None:
        """Stop serving and close the socket (idempotent).

        Bounded: ``shutdown()`` returns once the serving loop sees the request, within
        :data:`POLL_INTERVAL_S` (it only accepts connections; each is handled in a daemon
        thread of its own), and the thread is joined for at most :data:`STOP_TIMEOUT_S`.
        """
        server, thread = self._server, self._thread
        self._server = self._thread = None
        if server is None:
            return
        server.shutdown()
        server.server_close()
        if thread is not None:
            thread.join(STOP_TIMEOUT_S)
            if thread.is_alive():
                _LOGGER.warning("metrics server thread still running after %.1f s", STOP_TIMEOUT_S)

    def __enter__(self) -> Self:
        """Start serving."""
        self.start()
        return self

    def __exit__(self, *exc_info: object) -> None:
        """Stop serving."""
        self.stop()
