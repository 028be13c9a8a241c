"""The recent values of each sensor's process value: what it read when a grab sample was taken.

An operator takes a sample at the basin, analyses it, and enters the result twenty minutes
later: the comparison is with the value the sensor read at the sample's time, not at the
entry's. :class:`RecentValues` is a sink that keeps, for each device, its verifiable
point's good values over a window, one per resolution step, in two fixed arrays (bounded
memory: 361 slots of 16 bytes for an hour at 10 s, whatever the poll rate). An entry later
than the window is refused with a message that says so.
"""

from __future__ import annotations

import math
from array import array
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import TYPE_CHECKING, Final

from gateway.errors import CommandRejectedError
from gateway.line.samples import Quality

if TYPE_CHECKING:
    from collections.abc import Mapping, Sequence

    from gateway.line.samples import DeviceEvent, Sample


MIN_TOLERANCE_S: Final = 5.0  # a grab sample's time is not known closer than this


@dataclass(frozen=True, slots=True, kw_only=True)
class ValueAt:
    """A sensor's value at a moment: when it was read, what, in which unit."""

    at: datetime
    value: float
    unit: str | None


class _Ring:
    """One point's values, one per resolution step, the oldest overwritten."""

    __slots__ = ("next", "times", "unit", "values")

    def __init__(self, slots: int) -> None:
        self.times = array("d", [math.nan] * slots)  # UTC seconds since the epoch
        self.values = array("d", [math.nan] * slots)
        self.next = 0
        self.unit: str | None = None

    def newest_time(self) -> float:
        return self.times[self.next - 1]

    def add(self, at: float, value: float) -> None:
        self.times[self.next] = at
        self.values[self.next] = value
        self.next = (self.next + 1) % len(self.times)

    def nearest(self, at: float) -> tuple[float, float] | None:
        best: tuple[float, float] | None = None
        for when, value in zip(self.times, self.values, strict=True):
            if math.isnan(when):
                continue
            if best is None or abs(when - at) < abs(best[0] - at):
                best = (when, value)
        return best


class RecentValues:
    """A sink: each device's verifiable point over the last ``window_s``."""

    def __init__(self, points: Mapping[str, str], *, window_s: float, resolution_s: float) -> None:
        """Keep ``points`` (device → its verifiable point) over ``window_s``."""
        self.window_s = window_s
        self.resolution_s = resolution_s
        self._slots = math.ceil(window_s / resolution_s) + 1
        self._points = dict(points)
        self._rings: dict[tuple[str, str], _Ring] = {}
        self._latest: dict[tuple[str, str], tuple[float, float]] = {}  # each poll's, kept

    @property
    def tolerance_s(self) -> float:
        """How far from the sample's time the value compared may be.

        Kept values are a resolution step apart or more (and a poll later than that): the
        nearest is within two steps; a grab sample is not timed closer than a few seconds.
        """
        return max(2 * self.resolution_s, MIN_TOLERANCE_S)

    @property
    def capacity(self) -> int:
        """The values kept per device: the window in resolution steps, and one more."""
        return self._slots

    def watch(self, device: str, point: str) -> None:
        """Keep ``device``'s ``point`` (a device added at a reload)."""
        self._points[device] = point

    async def publish(self, samples: Sequence[Sample]) -> None:
        """Keep the good value of each device's verifiable point, once per resolution step."""
        for sample in samples:
            if self._points.get(sample.device) != sample.point:
                continue
            value = sample.value
            if sample.quality is not Quality.GOOD or not isinstance(value, int | float):
                continue
            key = (sample.device, sample.point)
            ring = self._rings.get(key)
            if ring is None:
                ring = self._rings[key] = _Ring(self._slots)
            if sample.unit is not None:  # known once the sensor's unit register was read
                ring.unit = sample.unit
            at = sample.time.timestamp()
            self._latest[key] = (at, float(value))  # an entry "now" compares the newest
            newest = ring.newest_time()
            if not math.isnan(newest) and at - newest < self.resolution_s:
                continue
            ring.add(at, float(value))

    async def device_event(self, event: DeviceEvent) -> None:
        """Availability changes nothing here: a value is kept with its time."""

    def value_at(self, device: str, point: str, at: datetime, *, now: datetime) -> ValueAt:
        """The value ``device`` read nearest to ``at``; refused if ``at`` is out of reach.

        A :class:`CommandRejectedError` when ``at`` is older than the window, in the future,
        or no good value was read within one resolution step of it.
        """
        late_s = (now - at).total_seconds()
        if late_s > self.window_s:
            raise CommandRejectedError(
                f"the sample was taken {late_s / 60:.0f} min ago, more than the "
                f"{self.window_s / 60:g} min of values the gateway keeps "
                "(verification.window_minutes): enter it sooner, or take a new sample"
            )
        if late_s < -self.resolution_s:
            raise CommandRejectedError(
                f"the sample's time {at.isoformat(timespec='seconds')} is in the future "
                "(check sampled_at, and the host clock)"
            )
        ring = self._rings.get((device, point))
        wanted = at.timestamp()
        found = ring.nearest(wanted) if ring is not None else None
        latest = self._latest.get((device, point))
        if latest is not None and (
            found is None or abs(latest[0] - wanted) < abs(found[0] - wanted)
        ):
            found = latest
        if ring is None or found is None or abs(found[0] - wanted) > self.tolerance_s:
            raise CommandRejectedError(
                f"{device} sent no good {point} value within {self.tolerance_s:g} s of "
                f"{at.isoformat(timespec='seconds')}: it was offline or faulty then"
            )
        return ValueAt(at=datetime.fromtimestamp(found[0], tz=UTC), value=found[1], unit=ring.unit)
