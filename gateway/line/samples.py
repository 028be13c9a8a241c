"""What the bus engine produces, and the small interface sinks implement to receive it."""

from __future__ import annotations

from dataclasses import dataclass
from datetime import datetime
from enum import StrEnum
from typing import TYPE_CHECKING, Protocol

from gateway.wire.codec import BitfieldValue, EnumValue

if TYPE_CHECKING:
    from collections.abc import Sequence

    from gateway.wire.codec import Value


class Quality(StrEnum):
    """How far a sample can be trusted."""

    GOOD = "good"  # the value the sensor sent, decoded as its manual says
    # The sensor answered with a fault instead of a value: a named error value (overrange)
    # or registers that are not a value of the point's type (undecodable).
    FAULT = "fault"
    STALE = "stale"  # the last good value is older than its interval allows
    COMMS_ERROR = "comms_error"  # the value could not be read: the line or the device failed


@dataclass(slots=True, kw_only=True)
class Sample:
    """One point of one device at one moment; made once, never changed (sinks share it).

    ``raw`` holds the registers of a value that could not be decoded (fault
    ``undecodable``), so what the sensor sent can be shown; it is empty otherwise.

    Not a frozen dataclass, though nothing changes one: a frozen one is built through
    ``object.__setattr__`` field by field, 2.5 times as long, and every answer makes two.
    """

    bus: str
    device: str
    profile: str
    point: str
    value: Value
    fault: str | None
    unit: str | None
    quality: Quality
    monotonic: float
    time: datetime
    group: str
    raw: tuple[int, ...] = ()

    @property
    def good(self) -> bool:
        """Whether ``value`` is a measurement to use."""
        return self.quality is Quality.GOOD


@dataclass(frozen=True, slots=True, kw_only=True)
class DeviceEvent:
    """A device came online, went offline, or its identity was read."""

    bus: str
    device: str
    profile: str
    online: bool
    reason: str
    time: datetime


def hex_registers(registers: Sequence[int]) -> list[str]:
    """Registers as the manuals print them (``0x07E9``), for JSON and logs."""
    return [f"0x{word:04X}" for word in registers]


def json_value(value: Value) -> object:
    """A value as JSON-ready data: enum labels, bit mappings, ISO 8601 date-times."""
    if isinstance(value, EnumValue):
        return value.label
    if isinstance(value, BitfieldValue):
        return dict(value.flags)
    if isinstance(value, datetime):
        return value.isoformat()
    return value


class Sink(Protocol):
    """Where samples go: console, MQTT, Prometheus. Calls must not block the bus task."""

    async def publish(self, samples: Sequence[Sample]) -> None:
        """Take the samples of one device's poll cycle."""

    async def device_event(self, event: DeviceEvent) -> None:
        """Take a change of a device's availability."""
