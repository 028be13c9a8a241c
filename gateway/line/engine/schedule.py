"""What is due next on one line: the points' deadlines and the device to serve.

Pure: every answer is computed from the device states and ``now``; nothing here waits,
sends or logs. Every point has a monotonic deadline (``next += interval``); missed
deadlines are counted and skipped, never piled up. Values (process values and status)
come first; diagnostics and configuration (the slow class) fill the time values leave
free. Between devices the earliest deadline wins, ties to the lower address.

Phases: devices that share an interval would otherwise all fall due at the same instant,
every cycle, and their cycles reach the MQTT publisher in bursts. A device with a phase
(``DeviceTarget.phase``, a fraction of its poll interval) has its values fall due on a grid
of the monotonic clock, ``phase_s + k * interval``, the same clock for every bus, so the
gateway spreads its devices by giving each its own fraction (:func:`spread_phase`). The
first cycle after a (re)start is read at once, as before (devices come online promptly);
the next one waits for the device's first slot a whole interval or more after it (one to
two intervals: the first cycle may take long, reading identity), and every cycle after
keeps it: a device back online or a port reconnected returns to the same slots. The slow
class keeps its deadlines as they were (from the start and the cycle that read it). A
device without a phase (the command line's) counts its deadlines from its (re)start.

The earliest deadline of a device is cached per class, and the devices sit in a heap per
class keyed by it, so the next device is found in O(log n). The heap is checked lazily: an
entry whose device has since moved on is dropped or pushed again when it comes to the top,
which covers every deadline that only grows (points read, identity read, points found
unreadable). A deadline that can move earlier is pushed at once by :meth:`Schedule.touch`:
a (re)start and a device going offline (its probe may be due before its values). Waits
(quarantines, post-write waits) are not in the key: a device inside one is set aside for
that pick, as before.
"""

from __future__ import annotations

import heapq
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Final

from gateway.line.engine.devices import SLOW_GROUPS

if TYPE_CHECKING:
    from collections.abc import Mapping, Sequence

    from gateway.line.engine.devices import DeviceState
    from gateway.line.engine.plan import ReadBlock

SLOW_GROUP_DELAY_S: Final = 2.0  # after a (re)start, the slow class waits for the values


def spread_phase(*, device: int, devices: int, bus: int, buses: int) -> float:
    """The default phase of a device: device ``device`` of ``devices`` on bus ``bus`` of ``buses``.

    The devices of a bus share its interval evenly (device j of m at j/m: they take turns on
    the line anyway, and so each bus's work is spread across its interval), and the buses
    are staggered within that slot (bus b of B at b/(B*m)), so that 16 buses of 16 devices
    fall due at 256 different instants, not 16 at once::

        spread_phase(device=1, devices=4, bus=0, buses=2)  # 0.25
        spread_phase(device=1, devices=4, bus=1, buses=2)  # 0.375
    """
    return (device + bus / max(buses, 1)) / max(devices, 1)


def next_slot(after: float, *, interval_s: float, offset_s: float) -> float:
    """The first instant of the grid ``offset_s + k * interval_s`` later than ``after``.

    Computed from the grid, not added up cycle by cycle, so a phase does not drift with
    rounding however long the gateway runs.
    """
    slot = offset_s + (math.floor((after - offset_s) / interval_s) + 1) * interval_s
    if slot <= after:  # the division rounded down across a slot
        slot += interval_s
    elif slot - interval_s > after:  # ... or up
        slot -= interval_s
    return slot


def _earliest_by_class(state: DeviceState) -> tuple[float, float]:
    """The earliest deadline of the device's values and of its slow class, in one pass.

    Run after every poll, over every point of the device (an H10 has 289): both classes
    at once, with :meth:`Schedule.is_slow` written out, since at 16 x 16 a pass per class
    through a call per point took a sixth of the gateway's CPU.
    """
    fast = slow = math.inf
    unreadable = state.holds.unreadable
    slow_points = state.target.slow_points
    pending = state.deadlines.identity_pending
    for name, deadline in state.deadlines.next_due.items():
        if name in unreadable:
            continue
        if name in slow_points and name not in pending:
            if deadline < slow:  # noqa: PLR1730 - a comparison, not a call per point
                slow = deadline
        elif deadline < fast:
            fast = deadline
    return fast, slow


@dataclass(frozen=True, slots=True)
class Late:
    """A point found more than one interval late: reported once per device."""

    point: str
    lag_s: float
    interval_s: float


class Schedule:
    """The deadlines of every device of one line."""

    def __init__(self, devices: Mapping[str, DeviceState]) -> None:
        """Schedule ``devices`` (the worker's states, shared)."""
        self.devices = devices
        # Per class (slow: diagnostics): (deadline, address, index, device); the key last
        # pushed for each device index, older entries of a device being stale.
        self._index = {state.target.name: n for n, state in enumerate(devices.values())}
        self._next_index = len(self._index)  # a device a reload adds: an index never used
        self._heaps: dict[bool, list[tuple[float, int, int, DeviceState]]] = {False: [], True: []}
        self._keys: dict[bool, dict[int, float]] = {False: {}, True: {}}
        for state in devices.values():
            self.touch(state)

    def add(self, state: DeviceState, now: float) -> None:
        """A device a reload added (already among the devices): all of it due now."""
        self._index[state.target.name] = self._next_index
        self._next_index += 1
        self.restart_device(state, now)

    def remove(self, state: DeviceState) -> None:
        """A device a reload removed: its heap entries are stale from now on."""
        index = self._index.pop(state.target.name)
        for keys in self._keys.values():
            keys.pop(index, None)

    def touch(self, state: DeviceState) -> None:
        """Put the device in the heaps with its deadlines as they are now.

        Needed where a deadline may move earlier than the one the heap holds (a restart,
        the device going offline); a deadline that grows is found out when it is popped.
        """
        for slow in (False, True):
            self._push(state, self.next_deadline(state, slow=slow), slow=slow)

    def _push(self, state: DeviceState, deadline: float, *, slow: bool) -> None:
        index = self._index[state.target.name]
        if self._keys[slow].get(index) == deadline:
            return  # already there with this key
        self._keys[slow][index] = deadline
        heapq.heappush(self._heaps[slow], (deadline, state.target.address, index, state))

    def restart(self, now: float) -> None:
        """Everything due now, identity again, on every device (start or reconnection)."""
        for state in self.devices.values():
            self.restart_device(state, now)

    def restart_device(self, state: DeviceState, now: float) -> None:
        """Everything due now, identity again (start, reconnection, back online)."""
        deadlines = state.deadlines
        deadlines.next_due.clear()
        deadlines.identity_pending.clear()
        deadlines.cache.clear()
        # Only points with a deadline: :meth:`advance` empties the set as they are read, and
        # identity points, never advanced, kept it (and its table) full for good.
        deadlines.fresh = {n for n, i in state.target.intervals.items() if i is not None}
        profile = state.profile
        # One float per distinct deadline, not one per point: a device's points share a few.
        delayed: dict[float, float] = {}
        for name, interval in state.target.intervals.items():
            if interval is None:
                deadlines.identity_pending.add(name)
            elif profile.point(name).group in SLOW_GROUPS:
                # Process values first: slow groups follow once the first values are out.
                deadline = now + min(interval, SLOW_GROUP_DELAY_S)
                deadlines.next_due[name] = delayed.setdefault(interval, deadline)
            else:
                deadlines.next_due[name] = now
        # Registers other values depend on: units and the float format.
        for name in state.target.intervals:
            unit_from = profile.point(name).unit_from
            if unit_from is not None:
                deadlines.identity_pending.add(unit_from)
        if profile.float_order_register is not None and state.target.float_order is None:
            deadlines.identity_pending.add(profile.float_order_register.point)
        # The device's own minimum response time: its timeouts follow it once read.
        if profile.timing.min_response_time_point is not None:
            deadlines.identity_pending.add(profile.timing.min_response_time_point)
        state.holds.restarted()
        self.touch(state)

    def reread(self, state: DeviceState, address: int, count: int, now: float) -> None:
        """Read the polled points within written registers again, at once.

        Another master wrote them: what the gateway holds may be old. A register other
        values depend on (a unit, the float format) or an identity point is read before
        the values, as at a start.
        """
        last = address + count - 1
        deadlines = state.deadlines
        profile = state.profile
        depended_on = set(state.target.unit_tables)  # the unit registers, by name
        if profile.float_order_register is not None:
            depended_on.add(profile.float_order_register.point)
        for point in profile.points:
            if point.last < address or point.address > last:
                continue
            name = point.name
            if name in depended_on or state.target.intervals.get(name, 0.0) is None:
                deadlines.identity_pending.add(name)
            elif name in state.target.intervals:
                deadlines.next_due[name] = now
        deadlines.cache.clear()
        self.touch(state)

    @staticmethod
    def is_slow(state: DeviceState, name: str) -> bool:
        """Whether a point belongs to the slow class (identity never does)."""
        return name in state.target.slow_points and name not in state.deadlines.identity_pending

    def due_points(self, state: DeviceState, now: float, *, slow: bool) -> list[str]:
        """The device's points of the class due at ``now``, pending identity included."""
        deadlines = state.deadlines
        due = [name for name, deadline in deadlines.next_due.items() if deadline <= now]
        pending = deadlines.identity_pending
        if pending:
            due.extend(pending - set(due))
        unreadable, slow_points = state.holds.unreadable, state.target.slow_points
        # is_slow() written out: a call per due point on every poll's path.
        return [
            n
            for n in due
            if n not in unreadable and (n in slow_points and n not in pending) == slow
        ]

    @staticmethod
    def in_order(state: DeviceState, blocks: Sequence[ReadBlock]) -> Sequence[ReadBlock]:
        """A device's planned reads, oldest deadline first (identity, with none, first).

        So a poll cut short (values due elsewhere, a failure's wait) resumes where it left.
        """
        if len(blocks) <= 1:  # nearly every poll: nothing to order
            return blocks
        earliest = state.deadlines.earliest
        keyed = []  # (deadline, place, block): the planner's order among equal deadlines
        for place, block in enumerate(blocks):
            keyed.append((earliest(block.points), place, block))
        keyed.sort()
        return [block for _, _, block in keyed]

    def next_deadline(self, state: DeviceState, *, slow: bool) -> float:
        """When the device next has work of the class: values (fast) or diagnostics (slow)."""
        if state.presence.online is False:
            return state.presence.probe_at if not slow else math.inf
        deadlines = state.deadlines
        pending = deadlines.identity_pending
        if not slow and pending and any(n not in state.holds.unreadable for n in pending):
            return 0.0
        cache = deadlines.cache
        cached = cache.get(slow)
        if cached is None:
            cache[False], cache[True] = _earliest_by_class(state)
            cached = cache[slow]
        return cached

    def pick(self, now: float, *, slow: bool) -> DeviceState | None:
        """The device with the earliest due work of the class (ties: lower address).

        O(log n) per device looked at: the heap's top, past stale entries and devices
        inside a wait, which go back for the next pick.
        """
        heap, keys = self._heaps[slow], self._keys[slow]
        waiting: list[tuple[float, int, int, DeviceState]] = []
        chosen: DeviceState | None = None
        while heap and heap[0][0] <= now:
            entry = heapq.heappop(heap)
            deadline, _, index, state = entry
            if keys.get(index) != deadline:
                continue  # the device was pushed again since: this entry is stale
            current = self.next_deadline(state, slow=slow)
            if current != deadline:  # its deadline grew (points read): where it is now
                keys[index] = current
                heapq.heappush(heap, (current, entry[1], index, state))
                continue
            waiting.append(entry)  # stays scheduled: picking is not serving
            if state.holds.not_before <= now:
                chosen = state
                break
        for entry in waiting:
            heapq.heappush(heap, entry)
        return chosen

    def wake_at(self, now: float) -> float:
        """When the next device has work it may do (its waits kept); ``now + 1`` without devices."""
        return min(
            (
                max(
                    min(self.next_deadline(s, slow=False), self.next_deadline(s, slow=True)),
                    s.holds.not_before,
                )
                for s in self.devices.values()
            ),
            default=now + 1.0,
        )

    def advance(self, state: DeviceState, names: Sequence[str], now: float) -> Late | None:
        """Move the deadlines of the points just handled; count and skip missed ones.

        Returns the first point found more than an interval late, once per device (not
        while any device of the line still reads its identity), for the caller to report.
        """
        deadlines = state.deadlines
        deadlines.cache.clear()
        late: Late | None = None
        starting = False  # whether any device still reads its identity: found out once
        phase_s = state.target.phase_s
        slow_points = state.target.slow_points
        intervals = state.target.intervals
        next_due = deadlines.next_due
        early: dict[float, float] = {}  # interval -> now + interval
        # The points read together mostly share their deadline, interval and phase: the
        # deadline after is computed once for a run of them, and the one float shared (one
        # per point held some 22,000 copies of a few hundred values at 16 x 16). Each point
        # still counts the deadlines it missed.
        group: tuple[float, float, float | None, bool] | None = None
        following = 0.0
        skipped = 0
        for name in set(names):
            interval = intervals.get(name)
            if interval is None or name not in next_due:
                continue
            deadline = next_due[name]
            first = name in deadlines.fresh
            if first:  # the first cycle after a (re)start reads everything
                deadlines.fresh.discard(name)
                if not deadlines.fresh:  # an emptied set keeps its table: 8 KiB for an H10
                    deadlines.fresh = set()
                deadline = now
            offset_s = None if name in slow_points else phase_s  # None: no phase
            if deadline > now:  # read early, along with due diagnostics: take their phase
                if offset_s is None:  # a phased value keeps its slot
                    next_due[name] = early.setdefault(interval, now + interval)
                continue
            lag = now - deadline
            key = (deadline, interval, offset_s, first)
            if key != group:
                missed = deadlines.missed_deadlines
                following = self._following(state, deadline, interval, now, offset_s, first=first)
                group, skipped = key, deadlines.missed_deadlines - missed
            else:
                deadlines.missed_deadlines += skipped
            next_due[name] = following
            deadlines.lag_s = max(0.0, lag)
            if lag <= interval or deadlines.lag_reported:
                continue
            # Once at most: found false, the device's lateness is reported and no point of
            # this read comes here again; found true, it is not looked for again.
            starting = starting or any(s.deadlines.identity_pending for s in self.devices.values())
            if not starting:
                deadlines.lag_reported = True
                late = Late(point=name, lag_s=lag, interval_s=interval)
        self.touch(state)  # a point read early takes a new phase, which may come sooner
        return late

    @staticmethod
    def _following(
        state: DeviceState,
        deadline: float,
        interval: float,
        now: float,
        offset_s: float | None,
        *,
        first: bool,
    ) -> float:
        """The deadline after ``deadline`` (a point read at ``now``); missed ones counted.

        With a phase (``offset_s``), the point's next slot, also after a reread, whose
        deadline was the moment it came, not a slot. After the first cycle of a (re)start,
        the first slot a whole interval after it: that cycle's ``now`` is when it began,
        and it may have read the device's identity for a second and more, with the other
        devices' first cycles still to come; a slot sooner would be missed before it is
        served (a start at 9600 baud counted missed deadlines). So the second cycle comes
        one to two intervals after the first, never sooner than before phases.
        """
        nxt = deadline + interval
        if nxt <= now:
            skipped = math.floor((now - nxt) / interval) + 1
            nxt += skipped * interval
            state.deadlines.missed_deadlines += skipped
        if offset_s is not None:
            after = now + interval if first else now
            nxt = next_slot(after, interval_s=interval, offset_s=offset_s)
        return nxt
