"""``set_clock``: the sensor's date and time from the gateway's clock, read before and after.

The point is the profile's writable date-and-time block
(:func:`~gateway.control.operations.catalogue.clock_point`): the S10 clock, which runs, or
the H10/H20 calibration date, which the sensor copies into the logbook entries that
follow and which does not run. The write goes through
:class:`~gateway.control.writes.SafeWriter` as an explicit operator action, and only
while the host clock is trusted (:mod:`gateway.control.clock_trust`): a Raspberry Pi
boots with the time it last saved, and NTP steps it later, by hours or days.
"""

from __future__ import annotations

import asyncio
import time
from dataclasses import dataclass, field
from datetime import UTC, datetime, timedelta
from typing import TYPE_CHECKING

from gateway.control.clock_trust import require_trusted_clock
from gateway.control.operations.catalogue import SET_CLOCK, clock_point, require_operation
from gateway.errors import CommandRejectedError
from gateway.line.samples import json_value

if TYPE_CHECKING:
    from gateway.control.writes import SafeWriter
    from gateway.wire import codec


@dataclass(frozen=True, slots=True)
class _GatewayClock:
    """The caller's wall clock, advanced by the monotonic clock (immune to clock steps)."""

    start: datetime
    start_monotonic: float = field(default_factory=time.monotonic)

    def now(self) -> datetime:
        return self.start + timedelta(seconds=time.monotonic() - self.start_monotonic)


@dataclass(frozen=True, slots=True, kw_only=True)
class ClockSetting:
    """What ``set_clock`` found, wrote and read back.

    Offsets are sensor minus gateway in seconds (the sensor's resolution is one second),
    ``None`` where the sensor held no date. A non-running point (the H10/H20 calibration
    date) keeps the written time, so its offset grows from then on.
    """

    device: str
    point: str
    running: bool
    meaning: str
    before: datetime | None
    gateway_before: datetime
    written: datetime
    registers: tuple[int, ...]
    after: datetime | None
    gateway_after: datetime
    note: str = ""

    @property
    def offset_before_s(self) -> float | None:
        """How far the sensor was from the gateway before the write."""
        return _offset(self.before, self.gateway_before)

    @property
    def offset_after_s(self) -> float | None:
        """How far the sensor is from the gateway after the write (read back)."""
        return _offset(self.after, self.gateway_after)

    def as_dict(self) -> dict[str, object]:
        """The setting as JSON-ready data."""
        data: dict[str, object] = {
            "point": self.point,
            "running": self.running,
            "meaning": self.meaning,
            "before": json_value(self.before),
            "gateway_before": self.gateway_before.isoformat(),
            "offset_before_s": self.offset_before_s,
            "written": self.written.isoformat(),
            "registers": list(self.registers),
            "after": json_value(self.after),
            "gateway_after": self.gateway_after.isoformat(),
            "offset_after_s": self.offset_after_s,
        }
        if self.note:
            data["note"] = self.note
        return data


def _offset(sensor: datetime | None, gateway: datetime) -> float | None:
    if sensor is None:
        return None
    return round((sensor - gateway).total_seconds(), 3)


def _as_datetime(value: codec.Decoded) -> datetime | None:
    return value if isinstance(value, datetime) else None


async def set_clock(writer: SafeWriter, *, now: datetime, local: bool = False) -> ClockSetting:
    """Set the sensor's date and time from the gateway's clock ``now``; read before and after.

    The time written is UTC (offset 0), or with ``local`` the gateway host's local time
    and offset. The write waits for the gateway clock's next whole second, so the
    sensor, which keeps whole seconds, starts within the frame's travel time of it.
    Refused before anything is read while the host clock is not trusted
    (``writer.clock``).
    """
    link = writer.link
    require_operation(SET_CLOCK, link.profile)
    target = clock_point(link.profile)
    assert target is not None  # noqa: S101 - require_operation checked it
    if now.tzinfo is None or now.utcoffset() is None:
        raise CommandRejectedError("the gateway's clock must carry a time zone")
    require_trusted_clock(
        writer.clock, f"set-clock of {link.device}", link.profile.point(target.point)
    )
    gateway = _GatewayClock(now)
    before = _as_datetime(await link.read_value(target.point))
    gateway_before = gateway.now()
    second = gateway.now().replace(microsecond=0) + timedelta(seconds=1)
    await asyncio.sleep(max(0.0, (second - gateway.now()).total_seconds()))
    written = second.astimezone() if local else second.astimezone(UTC)
    outcome = await writer.set(writer.point(target.point), written, explicit=True)
    return ClockSetting(
        device=link.device,
        point=target.point,
        running=target.running,
        meaning=target.meaning,
        before=before,
        gateway_before=gateway_before,
        written=written,
        registers=outcome.registers,
        after=_as_datetime(outcome.value),
        gateway_after=gateway.now(),
        note=outcome.note,
    )
