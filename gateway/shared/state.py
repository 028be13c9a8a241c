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
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Protocol

from gateway.care import CareBook
from gateway.line.samples import Quality
from gateway.shared.host_clock import HostClock
from gateway.shared.storage import StorageStatus

if TYPE_CHECKING:
    from collections.abc import Callable, Iterator, Sequence
    from datetime import date

    from gateway.line.engine.foreign import ForeignStats
    from gateway.line.engine.health import DeviceHealth
    from gateway.line.samples import DeviceEvent, Sample
    from gateway.line.stats import LineStats

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
    server: str = ""  # host:port of the server in use, or tried last
    servers: tuple[str, ...] = ()  # the list, in order
    switches: int = 0  # moves to another server of the list since the start
    # Another gateway holds this identity (base topic, client id): this one stood down
    # and publishes nothing until its config is fixed (publish/mqtt/identity).
    identity_conflict: str | None = None
    # Monotonic time this connection published its owner claim; None while not connected.
    # The Sparkplug session connects once a claim has stood a while (sparkplug/identity).
    identity_claimed_at: float | None = None

    @property
    def healthy(self) -> bool:
        """Connected, or buffering within the queue's bound; not standing down."""
        if self.identity_conflict is not None:
            return False
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


class RecordsHead(Protocol):
    """What the state shows of the records' head (:class:`gateway.records.Head`)."""

    @property
    def seq(self) -> int:
        """The newest record's number."""

    @property
    def hash(self) -> str:
        """The newest record's hash."""


@dataclass(slots=True)
class WriteStatus:
    """Commands and feeds: counts by outcome, flash writes, and each feed's state."""

    # (device, kind "set"/"command"/"feed", outcome "ok"/"unchanged"/"rejected"/"failed")
    outcomes: Counter[tuple[str, str, str]] = field(default_factory=Counter)
    flash_counts: Callable[[], FlashCounts] | None = None
    flash_budgets: dict[tuple[str, str], int] = field(default_factory=dict)
    # The record store's head (its ``seq`` and ``hash``), for the metrics and /healthz.
    records_head: Callable[[], RecordsHead] | None = None
    # A grab-sample verification asked through the metrics port (``gateway verify``, from
    # this machine): the JSON request in, the HTTP status and the JSON answer out.
    verify: Callable[[Mapping[str, object]], tuple[int, dict[str, object]]] | None = None
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
    server: str = ""  # host:port of the server in use, or tried last
    servers: tuple[str, ...] = ()  # the list, in order
    switches: int = 0  # moves to another server of the list since the start
    # The gateway's MQTT identity is another gateway's: the session stood down and
    # publishes nothing until a reload (sparkplug/identity).
    identity_conflict: str | None = None


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
class ConfigStatus:
    """The config the gateway runs and its last reload, for ``/healthz`` and the metrics.

    ``reloads`` counts every reload asked for, applied or not, so that ``gateway reload``
    tells its own from an older one; ``problems`` says why the last one was not applied.
    """

    last_reload_ok: bool = True  # the running config is the file's (Prometheus' own idea)
    last_success_at: float = field(default_factory=time.time)  # the start counts as one
    reloads: int = 0
    problems: tuple[str, ...] = ()
    applied: str = ""  # what the last reload applied, in one line

    def reloaded(self, applied: str) -> None:
        """A reload was applied."""
        self.reloads += 1
        self.last_reload_ok = True
        self.last_success_at = time.time()
        self.problems = ()
        self.applied = applied

    def refused(self, problems: Sequence[str]) -> None:
        """A reload was not applied: the file has these problems; the running config stays."""
        self.reloads += 1
        self.last_reload_ok = False
        self.problems = tuple(problems)
        self.applied = ""


_Samples = dict[tuple[str, str], dict[str, "Sample"]]  # (bus, device) -> point -> sample


class PointSamples(Mapping[tuple[str, str, str], "Sample"]):
    """One sample per point, keyed ``(bus, device, point)``, kept by device.

    At 16 buses x 16 devices the gateway polls some 26,000 points; a key of three names
    per point in a flat dict (and a second for the last good samples) cost some 200 bytes
    a point. Here the points of a device are one dict keyed by the point's name (a
    string of the profile, shared); the flat keys are made only when iterated.
    """

    __slots__ = ("_devices",)

    def __init__(self, devices: _Samples) -> None:
        """A view of ``devices`` (not a copy: the owner copies under its lock)."""
        self._devices = devices

    def __getitem__(self, key: tuple[str, str, str]) -> Sample:
        """The sample of ``(bus, device, point)``."""
        bus, device, point = key
        return self._devices[bus, device][point]

    def __iter__(self) -> Iterator[tuple[str, str, str]]:
        """Every ``(bus, device, point)``, device by device."""
        for (bus, device), points in self._devices.items():
            for point in points:
                yield bus, device, point

    def __len__(self) -> int:
        """How many points have a sample."""
        return sum(len(points) for points in self._devices.values())

    def values(self) -> Iterator[Sample]:  # type: ignore[override]
        """Every sample, device by device (without making the keys)."""
        for points in self._devices.values():
            yield from points.values()


class LastGood(Mapping[tuple[str, str, str], "Sample"]):
    """The newest good sample of each point, keyed ``(bus, device, point)``.

    The latest sample where it is good (most points, most of the time), else the one kept
    apart when the point's latest stopped being good: no second sample or key per point.
    """

    __slots__ = ("_before", "_devices")

    def __init__(self, devices: _Samples, before: _Samples) -> None:
        """A view of the latest samples and of the good ones kept apart."""
        self._devices = devices
        self._before = before

    def _good(self, bus: str, device: str, point: str, latest: Sample) -> Sample | None:
        if latest.quality is Quality.GOOD:
            return latest
        return self._before.get((bus, device), {}).get(point)

    def __getitem__(self, key: tuple[str, str, str]) -> Sample:
        """The newest good sample of ``(bus, device, point)``."""
        bus, device, point = key
        good = self._good(bus, device, point, self._devices[bus, device][point])
        if good is None:
            raise KeyError(key)
        return good

    def __iter__(self) -> Iterator[tuple[str, str, str]]:
        """Every ``(bus, device, point)`` that has had a good sample."""
        for item in self.items():
            yield item[0]

    def __len__(self) -> int:
        """How many points have had a good sample."""
        return sum(1 for _ in self.items())

    def items(self) -> Iterator[tuple[tuple[str, str, str], Sample]]:  # type: ignore[override]
        """Every point that has had a good sample, with it, device by device."""
        for (bus, device), points in self._devices.items():
            for point, latest in points.items():
                good = self._good(bus, device, point, latest)
                if good is not None:
                    yield (bus, device, point), good


@dataclass(slots=True)
class GatewayState:
    """Latest samples, device availability, line statistics and the MQTT status."""

    devices: dict[tuple[str, str], DeviceInfo] = field(default_factory=dict)
    lines: dict[str, LineStats] = field(default_factory=dict)
    health_sources: dict[str, Callable[[], list[DeviceHealth]]] = field(default_factory=dict)
    mqtt: MqttStatus = field(default_factory=MqttStatus)
    writes: WriteStatus = field(default_factory=WriteStatus)
    # Shared, not copied by a snapshot: counters of the event loop's, read as the lines'.
    shared_bus: SharedBusStatus = field(default_factory=SharedBusStatus)
    sparkplug: SparkplugStatus = field(default_factory=SparkplugStatus)
    web: WebStatus = field(default_factory=WebStatus)
    config: ConfigStatus = field(default_factory=ConfigStatus)
    # Shared, not copied by a snapshot: it keeps its own lock (sensor care, the manual).
    care: CareBook = field(default_factory=CareBook)
    # Shared, not copied by a snapshot: it keeps its own lock (the files of state_dir).
    storage: StorageStatus = field(default_factory=StorageStatus)
    # Shared, not copied by a snapshot: the host clock, asked at each read (clock_trust).
    clock: HostClock = field(default_factory=HostClock)
    started: float = field(default_factory=time.monotonic)
    _lock: threading.Lock = field(default_factory=threading.Lock)
    _by_device: _Samples = field(default_factory=dict)  # the latest sample of each point
    # The last good sample of the points whose latest is not good (while it is, the latest
    # is the last good one: kept once).
    _good_before: _Samples = field(default_factory=dict)

    @property
    def latest(self) -> PointSamples:
        """The latest sample of every point, by ``(bus, device, point)``.

        A view: read it from a :meth:`snapshot` where another thread records.
        """
        return PointSamples(self._by_device)

    @property
    def last_good(self) -> LastGood:
        """The newest good sample of every point that has had one, by ``(bus, device, point)``.

        A view: read it from a :meth:`snapshot` where another thread records.
        """
        return LastGood(self._by_device, self._good_before)

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

    def remove_line(self, bus: str) -> None:
        """A bus a reload removed or replaced: its statistics and its devices' health go."""
        with self._lock:
            self.lines.pop(bus, None)
            self.health_sources.pop(bus, None)

    def remove_device(self, bus: str, device: str) -> None:
        """A device a reload removed or moved: it and its samples are forgotten."""
        with self._lock:
            self.devices.pop((bus, device), None)
            self._by_device.pop((bus, device), None)
            self._good_before.pop((bus, device), None)
        self.care.remove_device(device)

    def health(self) -> list[DeviceHealth]:
        """Every device's health, asked of its bus task (plain attribute reads)."""
        with self._lock:
            sources = list(self.health_sources.values())
        return [entry for source in sources for entry in source()]

    def record(self, samples: Sequence[Sample]) -> None:
        """Keep the newest sample of every point, and the newest good one apart."""
        good = Quality.GOOD
        with self._lock:
            for sample in samples:
                device = (sample.bus, sample.device)
                points = self._by_device.get(device)
                if points is None:
                    points = self._by_device[device] = {}
                previous = points.get(sample.point)
                points[sample.point] = sample
                if sample.quality is good:
                    if (before := self._good_before.get(device)) is not None:
                        before.pop(sample.point, None)
                elif previous is not None and previous.quality is good:
                    self._good_before.setdefault(device, {})[sample.point] = previous

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
            copy = GatewayState(
                devices=dict(self.devices),
                lines=dict(self.lines),
                health_sources=dict(self.health_sources),
                mqtt=replace(self.mqtt),
                writes=WriteStatus(
                    outcomes=Counter(self.writes.outcomes),
                    flash_counts=self.writes.flash_counts,
                    records_head=self.writes.records_head,
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
                config=replace(self.config),
                care=self.care,
                storage=self.storage,
                clock=self.clock,
                started=self.started,
            )
            copy._by_device = {device: dict(points) for device, points in self._by_device.items()}
            copy._good_before = {
                device: dict(points) for device, points in self._good_before.items() if points
            }
            return copy

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
        """Record the samples of one poll cycle; care takes its records from them."""
        self.state.record(samples)
        self.state.care.observe(samples)

    async def device_event(self, event: DeviceEvent) -> None:
        """Record a change of availability."""
        self.state.record_event(event)
