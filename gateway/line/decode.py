"""Registers to samples: each point of a block decoded as its manual says, or a fault.

A sensor's fault value (``2.0e37``...) is a :class:`~gateway.wire.codec.Fault`, a sample of
quality ``fault``. Registers that are no value of the point's type (an S10 clock dated month
13) are a fault of that value too, ``undecodable`` with the registers sent: the line and the
device worked, so it is never a comms error that would blame the line. A read that failed
gives every point of its block a ``comms_error`` sample.
"""

from __future__ import annotations

import logging
import time
from datetime import UTC, datetime
from typing import TYPE_CHECKING

from gateway.errors import DecodeError
from gateway.line.samples import Quality, Sample, hex_registers
from gateway.wire import codec

if TYPE_CHECKING:
    from gateway.line.devices import DeviceState
    from gateway.line.plan import ReadBlock
    from gateway.profiles import Point

_LOGGER = logging.getLogger(__name__)


class Decoder:
    """The samples of one line's reads; keeps each device's last values."""

    def __init__(self, bus: str) -> None:
        """Decode for the line named ``bus``."""
        self.bus = bus

    def decode(
        self, state: DeviceState, block: ReadBlock, registers: tuple[int, ...]
    ) -> list[Sample]:
        """The samples of a block read; the device's values and pending identity updated."""
        at = (time.monotonic(), datetime.now(tz=UTC))
        order = state.float_order
        base = block.address
        values = state.values
        pending = state.identity_pending
        samples = []
        for point in block.points:
            offset = point.address - base
            chunk = registers[offset : offset + point.count]
            try:
                value: codec.Decoded = codec.decode(point.format, chunk, float_order=order)
            except DecodeError as exc:
                value = codec.Fault.undecodable(chunk, exc)
            if isinstance(value, codec.Fault) or state.undecodable:
                self._note_undecodable(state, point, value)
            values[point.name] = value
            if pending and point.name in pending:
                pending.discard(point.name)
                state.deadline_cache.clear()
            if isinstance(value, codec.Fault):
                fault = self._sample(state, point, fault=value.name, raw=value.registers, at=at)
                samples.append(fault)
            else:
                samples.append(self._sample(state, point, value=value, at=at))
        return samples

    def failed(self, state: DeviceState, block: ReadBlock, reason: str) -> list[Sample]:
        """A ``comms_error`` sample for every point of a block that could not be read."""
        at = (time.monotonic(), datetime.now(tz=UTC))
        for point in block.points:
            state.identity_pending.discard(point.name)
        state.deadline_cache.clear()
        return [self._sample(state, p, fault=reason, comms_error=True, at=at) for p in block.points]

    def _note_undecodable(self, state: DeviceState, point: Point, value: codec.Decoded) -> None:
        """Log why a point's registers do not decode: the first time loudly, then quietly."""
        if not (isinstance(value, codec.Fault) and value.name == codec.UNDECODABLE):
            if point.name in state.undecodable:
                state.undecodable.discard(point.name)
                _LOGGER.info("%s/%s: %s decodes again", self.bus, state.target.name, point.name)
            return
        log = _LOGGER.debug if point.name in state.undecodable else _LOGGER.warning
        state.undecodable.add(point.name)
        log(
            "%s/%s: %s cannot be decoded (%s): %s",
            self.bus,
            state.target.name,
            point.name,
            " ".join(hex_registers(value.registers)),
            value.reason,
        )

    def _sample(
        self,
        state: DeviceState,
        point: Point,
        *,
        value: codec.Value = None,
        fault: str | None = None,
        raw: tuple[int, ...] = (),
        comms_error: bool = False,
        at: tuple[float, datetime],
    ) -> Sample:
        """A good value, a sensor fault, or (``comms_error``) no value at all.

        ``raw`` carries the registers of a value that could not be decoded.
        """
        if comms_error:
            quality = Quality.COMMS_ERROR
        elif fault is not None:
            quality = Quality.FAULT
        else:
            quality = Quality.GOOD
        return Sample(
            bus=self.bus,
            device=state.target.name,
            profile=state.profile.id,
            point=point.name,
            value=value,
            fault=fault,
            unit=state.unit_of(point),
            quality=quality,
            monotonic=at[0],
            time=at[1],
            group=point.group.value,
            raw=raw,
        )
