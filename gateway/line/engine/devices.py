"""The devices of one line: each as configured (a target) and as its worker knows it (a state).

A device's running state is in parts, each with the one module that writes it: the
schedule's :class:`Deadlines`, the availability's :class:`Presence`, the transactions'
:class:`Holds`, the decoder's values. The others read a part, or ask its owner through a
method; the part classes sit here, beside the state, so that the owners (which all read
the whole state) need not import each other.
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import TYPE_CHECKING, Final

from gateway.profiles import PollGroup
from gateway.wire import codec

if TYPE_CHECKING:
    from collections.abc import Iterable, Mapping

    from gateway.profiles import Point, Profile
    from gateway.profiles.serial_number import PinnedSerial

PROBE_MAX_S: Final = 5.0  # largest wait between probes of an offline device
# Polled in the time process values leave free (the schedule's "slow" class).
SLOW_GROUPS: Final = frozenset({PollGroup.DIAGNOSTICS, PollGroup.CONFIGURATION})


@dataclass(frozen=True, slots=True)
class _Resolved:
    """What a device's target derives from its profile and its intervals alone."""

    profile: Profile  # held so that its ``id()``, part of the key, is not reused
    intervals: Mapping[str, float | None]
    slow_points: frozenset[str]
    unit_tables: Mapping[str, Mapping[int, str]]


# One entry per profile and interval settings, shared by every device that has them: at 16
# buses of 16 sensors, a map, a set and a table per device cost megabytes for a handful of
# distinct contents. Keyed by the profile's identity (profiles are not hashable, and two
# loaded with one id need not agree) and the intervals in their order, which is the order
# points are read in. Few entries (the configured combinations), so it is never pruned.
_RESOLVED: dict[tuple[int, tuple[tuple[str, float | None], ...]], _Resolved] = {}


def _resolved(profile: Profile, intervals: Mapping[str, float | None]) -> _Resolved:
    """The shared, read-only structures of a device with this profile and these intervals."""
    key = (id(profile), tuple(intervals.items()))
    found = _RESOLVED.get(key)
    if found is None:
        slow = frozenset(n for n in intervals if profile.point(n).group in SLOW_GROUPS)
        selectors = {p.unit_from for p in profile.points if p.unit_from is not None}
        tables = {name: profile.point(name).enum_units for name in selectors}
        found = _RESOLVED[key] = _Resolved(
            profile=profile,
            # A copy, read-only: the caller's dict may change, and every device shares it.
            intervals=MappingProxyType(dict(intervals)),
            slow_points=slow,
            unit_tables=MappingProxyType(tables),
        )
    return found


@dataclass(frozen=True, slots=True, kw_only=True)
class DeviceTarget:
    """One device to poll, with everything resolved from the config and its profile."""

    name: str
    address: int
    profile: Profile
    intervals: Mapping[str, float | None]  # point -> seconds; None: identity, read once
    float_order: codec.WordOrder | None = None  # explicit override of the profile/register
    timeout_s: float | None = None  # None: computed from the profile's timing
    min_response_time_s: float = 0.0
    extra_gap_s: float = 0.0
    retries: int = 2
    offline_after: int = 3
    probe_max_s: float = PROBE_MAX_S
    serial_number: PinnedSerial | None = None  # the serial it must report; None: any
    # Where in its poll interval its values fall due (0 <= phase < 1, a fraction of the
    # interval, on the monotonic clock: see gateway.line.engine.schedule); None: counted from each
    # (re)start, as a one-off command reads.
    phase: float | None = None

    # Points of the diagnostics and configuration groups, polled in free line time; resolved
    # once here, not looked up on every scheduling step.
    slow_points: frozenset[str] = field(init=False, repr=False, compare=False)
    # The units each unit register selects (an O-DO's ``oxygen_unit``: code -> unit), by the
    # register's name as points give it in ``unit_from``; resolved once here, not looked up
    # for every sample decoded.
    unit_tables: Mapping[str, Mapping[int, str]] = field(init=False, repr=False, compare=False)
    # The register with the device's minimum response time (digiLine 0x0305), resolved once.
    min_response_point: Point | None = field(init=False, repr=False, compare=False)
    # The phase in seconds: ``phase`` of the poll interval, the same offset for every value
    # point, so points at multiples of the poll interval keep falling due with the others
    # (and are read in the same request).
    phase_s: float | None = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        """Resolve the slow points and the unit registers from the profile.

        The intervals, the slow points and the unit tables are those every device of the
        same profile and intervals shares (read-only), not a copy per device.
        """
        profile = self.profile
        shared = _resolved(profile, self.intervals)
        object.__setattr__(self, "intervals", shared.intervals)
        object.__setattr__(self, "slow_points", shared.slow_points)
        object.__setattr__(self, "unit_tables", shared.unit_tables)
        learn = profile.timing.min_response_time_point
        object.__setattr__(
            self, "min_response_point", profile.point(learn) if learn is not None else None
        )
        phase_s = None if self.phase is None else self.phase * self.poll_interval_s
        object.__setattr__(self, "phase_s", phase_s)

    @property
    def poll_interval_s(self) -> float:
        """The shortest interval of its points: the pace of its probes when offline."""
        return min((i for i in self.intervals.values() if i), default=1.0)


@dataclass(slots=True)
class Deadlines:
    """When a device's points fall due and how late it runs: the schedule's, and only its.

    Written by :class:`~gateway.line.engine.schedule.Schedule` and by this class's methods
    alone; the decoder asks through :meth:`identity_read` and :meth:`identity_failed`, the
    transactions through :meth:`changed`, and every other reader only reads.
    """

    next_due: dict[str, float] = field(default_factory=dict)
    identity_pending: set[str] = field(default_factory=set)
    # The earliest deadline of each class (slow: diagnostics), cleared whenever a deadline,
    # the pending identity or the unreadable points change: asked for on every scheduling
    # step of every device, it must not walk all points each time.
    cache: dict[bool, float] = field(default_factory=dict)
    fresh: set[str] = field(default_factory=set)  # periodic, not polled since (re)start: no lag yet
    missed_deadlines: int = 0
    lag_s: float = 0.0
    lag_reported: bool = False

    def identity_read(self, name: str) -> None:
        """A pending identity point was read: no longer pending."""
        self.identity_pending.discard(name)
        self.cache.clear()

    def identity_failed(self, names: Iterable[str]) -> None:
        """A read of these points failed: an identity point among them waits for a restart."""
        for name in names:
            self.identity_pending.discard(name)
        self.cache.clear()

    def changed(self) -> None:
        """What the deadlines skip changed (a point found unreadable): computed again."""
        self.cache.clear()

    def carried_over(self) -> Deadlines:
        """The deadlines of a re-planned device: new ones, its count of missed ones kept."""
        return Deadlines(missed_deadlines=self.missed_deadlines)

    def earliest(self, points: Iterable[Point]) -> float:
        """The earliest deadline of these points (identity, with none, comes first).

        A plain loop: the generator it was cost two calls per point on every poll's path.
        """
        next_due = self.next_due
        earliest = math.inf
        for point in points:
            deadline = next_due.get(point.name, 0.0)
            if deadline < earliest:  # noqa: PLR1730 - a comparison, not a call per point
                earliest = deadline
        return earliest


@dataclass(slots=True)
class Presence:
    """Whether a device answers, and when to probe it.

    Written by :class:`~gateway.line.engine.health.Availability` alone; the identity guard
    asks it to hold a device that is not the configured sensor.
    """

    online: bool | None = None  # None until the first answer or the first offline verdict
    failures: int = 0  # failed transactions in a row
    probe_at: float = 0.0  # an offline device's next probe (monotonic)
    backoff_s: float = 0.0  # the wait between its probes, doubled up to a cap


@dataclass(slots=True)
class Holds:
    """What the transactions keep of a device between requests: theirs, and only theirs.

    The wait before its next request (a post-write wait, the late-answer window, a foreign
    master's write), its retries, the blocks it made read apart (exception 02) and the
    points it refuses alone. Written by
    :class:`~gateway.line.engine.transactions.Transactions` and this class's methods alone;
    others ask through :meth:`hold_until` (the shared bus's writes) and :meth:`restarted`
    (the schedule, when the device is read in full again).
    """

    not_before: float = 0.0  # no request to the device before this monotonic time
    attempts: Counter[str] = field(default_factory=Counter)  # retries so far, by point
    split_before: set[int] = field(default_factory=set)  # addresses a block must not span
    unreadable: set[str] = field(default_factory=set)  # points refused alone: not polled
    late_hint_given: bool = False  # an answer after its timeout was explained in the log

    def hold_until(self, at: float) -> None:
        """No request to the device before ``at`` (a longer wait already set stands)."""
        self.not_before = max(self.not_before, at)

    def restarted(self) -> None:
        """The device is read in full again (a start, back online): retries from none."""
        self.attempts.clear()


@dataclass(slots=True)
class DeviceState:
    """What the worker knows about a device while running, each part with its one writer.

    The schedule writes the :class:`Deadlines`, the availability the :class:`Presence`
    (online, failures, probes), the transactions the :class:`Holds` (waits, retries,
    splits, unreadable points), the decoder the values. Everyone else reads them, or asks
    the owner through the part's methods.
    """

    target: DeviceTarget
    deadlines: Deadlines = field(default_factory=Deadlines)
    presence: Presence = field(default_factory=Presence)
    holds: Holds = field(default_factory=Holds)
    values: dict[str, codec.Decoded] = field(default_factory=dict)  # the last decoded
    undecodable: set[str] = field(default_factory=set)  # points whose registers did not decode

    def carried_over(self, target: DeviceTarget) -> DeviceState:
        """The same sensor with other settings (a reload): new deadlines on ``target``.

        What it answered, its waits and verdicts and its counters are kept (a counter that
        went back would read as a reset).
        """
        return DeviceState(
            target=target,
            deadlines=self.deadlines.carried_over(),
            presence=self.presence,
            holds=self.holds,
            values=self.values,
            undecodable=self.undecodable,
        )

    @property
    def profile(self) -> Profile:
        """The device's register map."""
        return self.target.profile

    @property
    def float_order(self) -> codec.WordOrder:
        """Configured order, else the one the device's format register reports, else CDAB."""
        target = self.target
        if target.float_order is not None:
            return target.float_order
        profile = target.profile  # not ``self.profile``: a call less on every float's read
        selector = profile.float_order_register
        if selector is not None:
            value = self.values.get(selector.point)
            if isinstance(value, codec.EnumValue) and value.code in selector.orders:
                return selector.orders[value.code]
        return profile.float_order

    def unit_of(self, point: Point) -> str | None:
        """The point's unit, looked up in the unit register it names if need be."""
        if point.unit_from is None:
            return point.unit
        selected = self.values.get(point.unit_from)
        if isinstance(selected, codec.EnumValue):
            return self.target.unit_tables[point.unit_from].get(selected.code)
        return None
