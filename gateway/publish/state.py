"""The gateway's latest view of every value and device, shared by the sinks.

The bus tasks write it through :class:`StateSink` (the first sink of every bus); the
Prometheus endpoint, which runs in its own thread so a scrape never blocks a bus task,
reads consistent snapshots of it; ``/healthz`` and the MQTT state documents use it too.
One lock guards it; every critical section is a few dictionary operations.
"""

from __future__ import annotations

import threading
import time
from collections import Counter
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING

from gateway.line.samples import Quality

if TYPE_CHECKING:
    from collections.abc import Callable, Mapping, Sequence
    from datetime import date

    from gateway.line.foreign import ForeignStats
    from gateway.line.health import DeviceHealth
    from gateway.line.port import LineStats
    from gateway.line.samples import DeviceEvent, Sample

STALE_FACTOR = 2.0  # a value is stale when older than two intervals (plus a timeout)
STALE_MARGIN_S = 1.0


@dataclass(frozen=True, slots=True, kw_only=True)
class DeviceInfo:
    """What sinks need to know about a configured device."""

    bus: str
    name: str
    profile: str
    address: int
    intervals: Mapping[str, float | None]  # point -> seconds; None: identity, read once
    online: bool | None = None  # None: not heard of yet
    reason: str = ""


@dataclass(slots=True)
class MqttStatus:
    """The MQTT sink's state, for ``/healthz`` and the metrics."""

    enabled: bool = False
    connected: bool = False
    queue_depth: int = 0
    queue_max: int = 0
    dropped: int = 0
    published: int = 0
    last_error: str | None = None

    @property
    def healthy(self) -> bool:
        """Connected, or buffering within the queue's bound."""
        return not self.enabled or self.connected or self.queue_depth < self.queue_max


@dataclass(slots=True)
class FeedStatus:
    """One feed as the metrics see it."""

    feed: str  # device/point written
    source: str  # device/point or mqtt:topic read
    writes: int = 0
    errors: int = 0
    source_value: float | None = None
    source_at: float | None = None  # monotonic time of the newest source value
    stale: bool = False
    fallback: bool = False  # the sensor was switched back to its own source


@dataclass(frozen=True, slots=True, kw_only=True)
class FlashCounts:
    """A copy of the ledger's counts, safe to read from another thread (the metrics)."""

    day: date | None  # the UTC day ``today`` counts; None before any write this run
    totals: dict[tuple[str, str], int]  # every flash write ever recorded
    today: dict[tuple[str, str], int]


@dataclass(slots=True)
class WriteStatus:
    """Commands and feeds: counts by outcome, flash writes, and each feed's state."""

    # (device, kind "set"/"command"/"feed", outcome "ok"/"unchanged"/"rejected"/"failed")
    outcomes: Counter[tuple[str, str, str]] = field(default_factory=Counter)
    flash_counts: Callable[[], FlashCounts] | None = None
    flash_budgets: dict[tuple[str, str], int] = field(default_factory=dict)
    feeds: dict[str, FeedStatus] = field(default_factory=dict)


WAIT_BUCKETS_S = (0.01, 0.05, 0.1, 0.25, 0.5, 1.0, 2.0, 5.0)


@dataclass(slots=True)
class SharedBusClient:
    """What one client of the shared bus did (its configured name, or ``other``)."""

    requests: Counter[int] = field(default_factory=Counter)  # by function code
    exceptions: Counter[int] = field(default_factory=Counter)  # by the code answered
    refused: Counter[str] = field(default_factory=Counter)  # writes refused, by reason
    received_bytes: int = 0
    sent_bytes: int = 0
    cache_answers: int = 0  # reads answered from what the device last sent
    shed: Counter[str] = field(default_factory=Counter)  # answered 06, not served, by reason
    throttled_s: float = 0.0  # time its requests waited for its rate limit
    closed: Counter[str] = field(default_factory=Counter)  # connections ended, by reason
    wait_buckets: Counter[float] = field(default_factory=Counter)  # queue wait histogram
    wait_sum_s: float = 0.0
    peers: dict[str, float] = field(default_factory=dict)  # connected now: "host:port" -> since

    def observe_wait(self, seconds: float) -> None:
        """Add one request's wait for the line to the histogram."""
        self.wait_sum_s += seconds
        for bound in (*WAIT_BUCKETS_S, float("inf")):
            if seconds <= bound:
                self.wait_buckets[bound] += 1


@dataclass(slots=True)
class SharedBusStatus:
    """The shared bus (other masters through the gateway), for ``/healthz`` and the metrics."""

    enabled: bool = False
    listening: list[str] = field(default_factory=list)  # "tcp://127.0.0.1:1502"
    share: float = 0.0
    clients: dict[str, SharedBusClient] = field(default_factory=dict)
    buses: dict[str, ForeignStats] = field(default_factory=dict)

    def client(self, name: str) -> SharedBusClient:
        """The counters of a client, created at its first request."""
        found = self.clients.get(name)
        if found is None:
            found = self.clients[name] = SharedBusClient()
        return found


@dataclass(slots=True)
class SparkplugStatus:
    """The Sparkplug B session's state, for ``/healthz`` and the metrics."""

    enabled: bool = False
    connected: bool = False
    host_online: bool = False  # the primary host's STATE (true without a primary host)
    bd_seq: int = 0  # of the current or last session
    births: int = 0  # NBIRTHs sent (sessions and rebirths)
    published: int = 0  # messages handed to the broker
    queue_depth: int = 0  # DDATA stored while the host or the broker is away
    dropped: int = 0
    last_error: str | None = None


@dataclass(slots=True)
class WebStatus:
    """The web page's sign-ins, as the metrics read them (the page counts them here)."""

    enabled: bool = False
    sign_ins: Counter[str] = field(default_factory=Counter)  # by outcome
    lockouts: int = 0  # addresses locked out for guessing, ever
    locked_until: dict[str, float] = field(default_factory=dict)  # address -> monotonic

    def locked_out(self, now: float) -> int:
        """How many addresses are locked out at ``now``."""
        return sum(1 for until in self.locked_until.values() if until > now)


@dataclass(slots=True)
class GatewayState:
    """Latest samples, device availability, line statistics and the MQTT status."""

    devices: dict[tuple[str, str], DeviceInfo] = field(default_factory=dict)
    latest: dict[tuple[str, str, str], Sample] = field(default_factory=dict)
    last_good: dict[tuple[str, str, str], Sample] = field(default_factory=dict)
    lines: dict[str, LineStats] = field(default_factory=dict)
    health_sources: dict[str, Callable[[], list[DeviceHealth]]] = field(default_factory=dict)
    mqtt: MqttStatus = field(default_factory=MqttStatus)
    writes: WriteStatus = field(default_factory=WriteStatus)
    # Shared, not copied by a snapshot: counters of the event loop's, read as the lines'.
    shared_bus: SharedBusStatus = field(default_factory=SharedBusStatus)
    sparkplug: SparkplugStatus = field(default_factory=SparkplugStatus)
    web: WebStatus = field(default_factory=WebStatus)
    started: float = field(default_factory=time.monotonic)
    _lock: threading.Lock = field(default_factory=threading.Lock)
    _by_device: dict[tuple[str, str], dict[str, Sample]] = field(default_factory=dict)

    def add_device(self, info: DeviceInfo) -> None:
        """Register a configured device before polling starts."""
        with self._lock:
            self.devices[info.bus, info.name] = info

    def add_line(
        self, bus: str, stats: LineStats, health: Callable[[], list[DeviceHealth]]
    ) -> None:
        """Register a bus's line statistics and its device health (read at scrape time)."""
        with self._lock:
            self.lines[bus] = stats
            self.health_sources[bus] = health

    def health(self) -> list[DeviceHealth]:
        """Every device's health, asked of its bus task (plain attribute reads)."""
        with self._lock:
            sources = list(self.health_sources.values())
        return [entry for source in sources for entry in source()]

    def record(self, samples: Sequence[Sample]) -> None:
        """Keep the newest sample of every point, and the newest good one apart."""
        with self._lock:
            for sample in samples:
                key = (sample.bus, sample.device, sample.point)
                self.latest[key] = sample
                self._by_device.setdefault((sample.bus, sample.device), {})[sample.point] = sample
                if sample.quality is Quality.GOOD:
                    self.last_good[key] = sample

    def record_event(self, event: DeviceEvent) -> None:
        """Keep a device's availability."""
        with self._lock:
            key = (event.bus, event.device)
            info = self.devices.get(key)
            if info is not None:
                self.devices[key] = replace(info, online=event.online, reason=event.reason)

    def count_write(self, device: str, kind: str, outcome: str) -> None:
        """Count one command or feed write by its outcome."""
        with self._lock:
            self.writes.outcomes[device, kind, outcome] += 1

    def count_sign_in(self, outcome: str, remote: str, locked_until: float = 0.0) -> None:
        """Count one sign-in to the page by its outcome; a new lock-out of ``remote``."""
        with self._lock:
            web = self.web
            web.sign_ins[outcome] += 1
            if locked_until > web.locked_until.get(remote, 0.0):
                web.lockouts += 1
                now = time.monotonic()
                web.locked_until = {
                    a: t for a, t in web.locked_until.items() if t > now
                }  # the lapsed ones go
                web.locked_until[remote] = locked_until

    def device_samples(self, bus: str, device: str) -> dict[str, Sample]:
        """The latest sample of each point of one device (cheap: no full snapshot)."""
        with self._lock:
            return dict(self._by_device.get((bus, device), {}))

    def snapshot(self) -> GatewayState:
        """A consistent copy to read without the lock (line stats are shared, read-only)."""
        with self._lock:
            return GatewayState(
                devices=dict(self.devices),
                latest=dict(self.latest),
                last_good=dict(self.last_good),
                lines=dict(self.lines),
                health_sources=dict(self.health_sources),
                mqtt=replace(self.mqtt),
                writes=WriteStatus(
                    outcomes=Counter(self.writes.outcomes),
                    flash_counts=self.writes.flash_counts,
                    flash_budgets=dict(self.writes.flash_budgets),
                    feeds={k: replace(v) for k, v in self.writes.feeds.items()},
                ),
                shared_bus=self.shared_bus,
                sparkplug=replace(self.sparkplug),
                web=WebStatus(
                    enabled=self.web.enabled,
                    sign_ins=Counter(self.web.sign_ins),
                    lockouts=self.web.lockouts,
                    locked_until=dict(self.web.locked_until),
                ),
                started=self.started,
            )

    def is_stale(self, sample: Sample, now: float | None = None) -> bool:
        """Whether a good value is older than its interval allows."""
        info = self.devices.get((sample.bus, sample.device))
        interval = info.intervals.get(sample.point) if info else None
        if interval is None:
            return False  # identity: read once, never stale
        age = (now if now is not None else time.monotonic()) - sample.monotonic
        return age > STALE_FACTOR * interval + STALE_MARGIN_S


class StateSink:
    """Feeds :class:`GatewayState` from the bus tasks."""

    def __init__(self, state: GatewayState) -> None:
        """Write into ``state``."""
        self.state = state

    async def publish(self, samples: Sequence[Sample]) -> None:
        """Record the samples of one poll cycle."""
        self.state.record(samples)

    async def device_event(self, event: DeviceEvent) -> None:
        """Record a change of availability."""
        self.state.record_event(event)
