"""A device's health as its bus task sees it: the value the metrics and ``/healthz`` read."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True, slots=True, kw_only=True)
class DeviceHealth:
    """A device as its bus task sees it: availability, poll lag, missed deadlines."""

    bus: str
    device: str
    address: int
    online: bool | None
    failures_in_a_row: int
    lag_s: float
    missed_deadlines: int
    unreadable_points: int
