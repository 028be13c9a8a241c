"""The health of the buses and devices: identity, availability, transactions, the port.

Identity is not a measurement: serial, firmware and hardware are labels of one info series
per device, ``gateway_device_info{serial="...",firmware="1503",hardware="1130"} 1``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from datetime import datetime
from typing import TYPE_CHECKING, Final

from prometheus_client.metrics_core import (
    CounterMetricFamily,
    GaugeMetricFamily,
    HistogramMetricFamily,
    InfoMetricFamily,
    Metric,
)

from gateway.line.stats import LATENCY_BUCKETS_S, ErrorKind
from gateway.publish.prometheus.naming import DEVICE_LABELS, VALUE_LABELS

if TYPE_CHECKING:
    from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence

    from gateway.line.engine.health import DeviceHealth
    from gateway.line.stats import LineStats
    from gateway.shared.state import GatewayState

# The failure classes exported (zero included) for every configured device.
ERROR_KINDS: Final = (
    ErrorKind.TIMEOUT,
    ErrorKind.CRC,
    ErrorKind.EXCEPTION,
    ErrorKind.WRONG_ADDRESS,
    ErrorKind.STALE,
    ErrorKind.NOISE,
    ErrorKind.MALFORMED,
    ErrorKind.ECHO,
    ErrorKind.ECHO_MISMATCH,
    ErrorKind.NO_SILENCE,
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


def device_families(snapshot: GatewayState, health: list[DeviceHealth]) -> Iterator[Metric]:
    """Identity and availability of every configured device."""
    # An info family: ``gateway_device_info{...} 1``, the Prometheus way to export text
    # that names rather than measures (a ``gauge`` in the 0.0.4 text format).
    info_family = InfoMetricFamily(
        "gateway_device",
        "A configured device, its address and identity as last read; always 1",
        labels=[*VALUE_LABELS, "address"],
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
        labels=VALUE_LABELS,
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
        labels=DEVICE_LABELS,
    )
    missed = CounterMetricFamily(
        "gateway_missed_deadlines",
        "Poll deadlines skipped because the line could not keep up",
        labels=DEVICE_LABELS,
    )
    unreadable = GaugeMetricFamily(
        "gateway_unreadable_points",
        "Points the device refuses to return (exception 02 to a single read)",
        labels=DEVICE_LABELS,
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


def line_families(
    snapshot: GatewayState, health: list[DeviceHealth], now: float
) -> Iterator[Metric]:
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
        self._requests = CounterMetricFamily(
            "gateway_requests", "Requests sent", labels=DEVICE_LABELS
        )
        self._responses = CounterMetricFamily(
            "gateway_responses",
            "Valid answers received (exceptions excluded)",
            labels=DEVICE_LABELS,
        )
        self._errors = CounterMetricFamily(
            "gateway_errors",
            "Failed transactions and discarded input, by kind",
            labels=[*DEVICE_LABELS, "kind"],
        )
        self._exceptions = CounterMetricFamily(
            "gateway_exceptions",
            "Modbus exception answers, by code",
            labels=[*DEVICE_LABELS, "code"],
        )
        self._retries = CounterMetricFamily(
            "gateway_retries", "Requests retried", labels=DEVICE_LABELS
        )
        self._quirks = CounterMetricFamily(
            "gateway_tolerated_quirks",
            "Answers accepted through a documented device quirk",
            labels=[*DEVICE_LABELS, "quirk"],
        )
        self._latency = HistogramMetricFamily(
            "gateway_request_latency_seconds",
            "Time from sending a request to the answer's last byte",
            labels=DEVICE_LABELS,
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
        self._port_problem = GaugeMetricFamily(
            "gateway_bus_port_problem",
            "1 for the reason the bus's port is not open (missing, permission_denied, "
            "in_use, no_rs485_mode, driver_error); absent while it is open",
            labels=["bus", "reason"],
        )
        self._latency_timer = GaugeMetricFamily(
            "gateway_port_latency_timer_seconds",
            "The USB adapter's latency timer (FTDI): how long it may hold received bytes",
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
        if not stats.port_open and stats.port_problem is not None:
            self._port_problem.add_metric([bus, stats.port_problem], 1.0)
        if stats.latency_timer_s is not None:
            self._latency_timer.add_metric([bus], stats.latency_timer_s)

    def families(self) -> Iterator[Metric]:
        """Every family, empty ones included (their HELP and TYPE still document them)."""
        yield from (self._requests, self._responses, self._errors, self._exceptions)
        yield from (self._retries, self._quirks, self._latency)
        yield from (self._utilisation, self._busy, self._port_open, self._port_failures)
        yield from (self._port_problem, self._latency_timer)


def _buckets(counts: Mapping[tuple[int, float], int], address: int) -> list[tuple[str, float]]:
    """The latency histogram of one device's requests."""
    return cumulative_buckets(LATENCY_BUCKETS_S, lambda bound: counts.get((address, bound), 0))


def cumulative_buckets(
    bounds: Sequence[float], count_at: Callable[[float], int]
) -> list[tuple[str, float]]:
    """A histogram's buckets (``+Inf`` added) from counts taken on another thread.

    The event loop adds one observation bucket by bucket; a copy taken in between can hold
    a lower bucket already counted and a higher one not yet: the running maximum keeps
    the histogram valid (the observation then shows fully at the next scrape).
    """
    buckets = []
    running = 0
    for bound in (*bounds, math.inf):
        running = max(running, count_at(bound))
        buckets.append(("+Inf" if math.isinf(bound) else repr(bound), float(running)))
    return buckets
