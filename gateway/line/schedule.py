"""What is due next on one line: the points' deadlines and the device to serve.

Pure: every answer is computed from the device states and ``now``; nothing here waits,
sends or logs. Every point has a monotonic deadline (``next += interval``); missed
deadlines are counted and skipped, never piled up. Values (process values and status)
come first; diagnostics and configuration (the slow class) fill the time values leave
free. Between devices the earliest deadline wins, ties to the lower address.

The earliest deadline of a device is cached per class, so the next device is found in one
pass over the line's devices (247 at most) rather than kept in a heap, which would have to
follow every quarantine, post-write wait and probe as well.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Final

from gateway.line.devices import SLOW_GROUPS

if TYPE_CHECKING:
    from collections.abc import Mapping, Sequence

    from gateway.line.devices import DeviceState

SLOW_GROUP_DELAY_S: Final = 2.0  # after a (re)start, the slow class waits for the values


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

    def restart(self, now: float) -> None:
        """Everything due now, identity again, on every device (start or reconnection)."""
        for state in self.devices.values():
            self.restart_device(state, now)

    @staticmethod
    def restart_device(state: DeviceState, now: float) -> None:
        """Everything due now, identity again (start, reconnection, back online)."""
        state.next_due.clear()
        state.identity_pending.clear()
        state.deadline_cache.clear()
        state.fresh = set(state.target.intervals)
        profile = state.profile
        for name, interval in state.target.intervals.items():
            if interval is None:
                state.identity_pending.add(name)
            elif profile.point(name).group in SLOW_GROUPS:
                # Process values first: slow groups follow once the first values are out.
                state.next_due[name] = now + min(interval, SLOW_GROUP_DELAY_S)
            else:
                state.next_due[name] = now
        # Registers other values depend on: units and the float format.
        for name in state.target.intervals:
            unit_from = profile.point(name).unit_from
            if unit_from is not None:
                state.identity_pending.add(unit_from)
        if profile.float_order_register is not None and state.target.float_order is None:
            state.identity_pending.add(profile.float_order_register.point)
        state.attempts.clear()

    @staticmethod
    def is_slow(state: DeviceState, name: str) -> bool:
        """Whether a point belongs to the slow class (identity never does)."""
        return name in state.target.slow_points and name not in state.identity_pending

    def due_points(self, state: DeviceState, now: float, *, slow: bool) -> list[str]:
        """The device's points of the class due at ``now``, pending identity included."""
        due = [name for name, deadline in state.next_due.items() if deadline <= now]
        due.extend(state.identity_pending - set(due))
        return [n for n in due if n not in state.unreadable and self.is_slow(state, n) == slow]

    def next_deadline(self, state: DeviceState, *, slow: bool) -> float:
        """When the device next has work of the class: values (fast) or diagnostics (slow)."""
        if state.online is False:
            return state.probe_at if not slow else math.inf
        if not slow and any(n not in state.unreadable for n in state.identity_pending):
            return 0.0
        cached = state.deadline_cache.get(slow)
        if cached is None:
            cached = min(
                (
                    t
                    for n, t in state.next_due.items()
                    if n not in state.unreadable and self.is_slow(state, n) == slow
                ),
                default=math.inf,
            )
            state.deadline_cache[slow] = cached
        return cached

    def pick(self, now: float, *, slow: bool) -> DeviceState | None:
        """The device with the earliest due work of the class (ties: lower address)."""
        due = [
            (deadline, s.target.address, s)
            for s in self.devices.values()
            if s.not_before <= now and (deadline := self.next_deadline(s, slow=slow)) <= now
        ]
        return min(due, key=lambda item: (item[0], item[1]))[2] if due else None

    def wake_at(self, now: float) -> float:
        """When the next device has work it may do (its waits kept); ``now + 1`` without devices."""
        return min(
            (
                max(
                    min(self.next_deadline(s, slow=False), self.next_deadline(s, slow=True)),
                    s.not_before,
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
        state.deadline_cache.clear()
        late: Late | None = None
        starting: bool | None = None  # whether any device still reads its identity, once
        for name in set(names):
            interval = state.target.intervals.get(name)
            if interval is None or name not in state.next_due:
                continue
            deadline = state.next_due[name]
            if name in state.fresh:  # the first cycle after a (re)start reads everything
                state.fresh.discard(name)
                deadline = now
            if deadline > now:  # read early, along with due diagnostics: take their phase
                state.next_due[name] = now + interval
                continue
            lag = now - deadline
            nxt = deadline + interval
            if nxt <= now:
                skipped = math.floor((now - nxt) / interval) + 1
                nxt += skipped * interval
                state.missed_deadlines += skipped
            state.next_due[name] = nxt
            state.lag_s = max(0.0, lag)
            if lag <= interval or state.lag_reported:
                continue
            if starting is None:
                starting = any(s.identity_pending for s in self.devices.values())
            if not starting:
                state.lag_reported = True
                late = Late(point=name, lag_s=lag, interval_s=interval)
        return late
