"""A sink that prints each poll cycle on one line, for ``gateway run`` in a terminal."""

from __future__ import annotations

import sys
from datetime import datetime
from typing import TYPE_CHECKING, TextIO

from gateway.line.samples import Quality, json_value

if TYPE_CHECKING:
    from collections.abc import Sequence

    from gateway.line.samples import DeviceEvent, Sample


def format_sample(sample: Sample) -> str:
    """``name=value unit``, ``name=!overrange`` for faults, ``name=?timeout`` for errors."""
    if sample.quality is Quality.GOOD:
        value = sample.value
        text = json_value(value) if isinstance(value, datetime) else str(value)
        unit = f" {sample.unit}" if sample.unit else ""
        return f"{sample.point}={text}{unit}"
    marker = "!" if sample.quality is Quality.FAULT else "?"
    return f"{sample.point}={marker}{sample.fault}"


class ConsoleSink:
    """Writes one line per device and poll cycle, and one per availability change."""

    def __init__(self, stream: TextIO | None = None) -> None:
        """Print to ``stream`` (standard output by default)."""
        self._stream = stream or sys.stdout

    async def publish(self, samples: Sequence[Sample]) -> None:
        """Print the cycle's samples of one device."""
        if not samples:
            return
        first = samples[0]
        stamp = first.time.astimezone().strftime("%H:%M:%S")
        body = " ".join(format_sample(s) for s in samples)
        self._stream.write(f"{stamp} {first.bus}/{first.device} {body}\n")
        self._stream.flush()

    async def device_event(self, event: DeviceEvent) -> None:
        """Print that a device came online or went offline."""
        state = "online" if event.online else "OFFLINE"
        stamp = event.time.astimezone().strftime("%H:%M:%S")
        self._stream.write(f"{stamp} {event.bus}/{event.device} {state}: {event.reason}\n")
        self._stream.flush()
