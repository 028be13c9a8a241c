"""Compensation feeds counted per device and day, not recorded one by one.

A feed writes a temperature or a salinity into a sensor's volatile registers every few
seconds: tens of thousands of writes a day that change no setting of the sensor. Recording
each would bury the changes that matter. So they are counted in memory per device, point
and UTC day, and each day's counts become one record per device when the day changes and
when the gateway stops (:meth:`FeedCounts.flush`). A feed to a flash-backed register is a
setting and is recorded as any other write.
"""

from __future__ import annotations

from collections import Counter
from datetime import UTC, date, datetime
from typing import TYPE_CHECKING

from gateway.records.actor import Actor, Via
from gateway.records.model import DeviceRef, Entry, Kind, Result

if TYPE_CHECKING:
    from collections.abc import Callable

    from gateway.records.store import RecordStore

FEEDS_ACTOR = Actor(user="feeds", via=Via.GATEWAY, detail="the config's feeds")


class FeedCounts:
    """Feed writes of the current UTC day, per device and point, until flushed."""

    def __init__(
        self,
        store: RecordStore,
        *,
        profiles: Callable[[str], str] = lambda _device: "",
        today: Callable[[], date] = lambda: datetime.now(UTC).date(),
    ) -> None:
        """Count into ``store``; ``profiles`` names a device's profile for its record."""
        self.store = store
        self._profiles = profiles
        self._today = today
        self._day: date | None = None
        self._counts: dict[str, Counter[str]] = {}

    def count(self, device: str, point: str) -> None:
        """One feed write, counted (a new day first records the last one's counts)."""
        day = self._today()
        if self._day is not None and day != self._day:
            self.flush()
        self._day = day
        self._counts.setdefault(device, Counter())[point] += 1

    def pending(self) -> dict[str, dict[str, int]]:
        """The counts not yet recorded, by device and point."""
        return {device: dict(points) for device, points in self._counts.items()}

    def flush(self) -> None:
        """One record per device with its counts of the day so far; then start again."""
        if self._day is None:
            return
        for device, points in sorted(self._counts.items()):
            self.store.append(
                Entry(
                    kind=Kind.FEEDS,
                    actor=FEEDS_ACTOR,
                    device=DeviceRef(name=device, profile=self._profiles(device)),
                    action="compensation feeds",
                    result=Result.NOTED,
                    note=f"writes to volatile registers on {self._day.isoformat()} (UTC)",
                    data={"day": self._day.isoformat(), "writes": dict(sorted(points.items()))},
                )
            )
        self._counts = {}
        self._day = None
