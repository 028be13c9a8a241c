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
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import TYPE_CHECKING, Final

from gateway.errors import DecodeError
from gateway.line.engine.devices import SLOW_GROUPS
from gateway.line.samples import Quality, Sample, hex_registers
from gateway.wire import codec

if TYPE_CHECKING:
    from collections.abc import Callable, Sequence

    from gateway.line.engine.devices import DeviceState
    from gateway.line.engine.plan import ReadBlock
    from gateway.profiles import Point

_LOGGER = logging.getLogger(__name__)


# Layouts kept per line; past this many (plans made and dropped again) they are made anew.
LAYOUTS_MAX: Final = 4096


@dataclass(frozen=True, slots=True)
class _Slot:
    """One point of a block as its decoding needs it, resolved once per block."""

    point: Point
    name: str
    start: int  # its first register within the block
    end: int
    decode: Callable[[codec.Format, Sequence[int], codec.WordOrder], codec.Decoded]
    format: codec.Format
    group: str
    unit: str | None  # its unit, unless a unit register selects it (``point.unit_from``)


class Decoder:
    """The samples of one line's reads; keeps each device's last values."""

    def __init__(self, bus: str) -> None:
        """Decode for the line named ``bus``."""
        self.bus = bus
        # Each planned block's points resolved for decoding, by the block (its id, and the
        # block kept to tell a reused id apart): plans are made once and read again and
        # again, and looking each point's offset, decoder and group up on every read was
        # a good part of a transaction's CPU.
        self._layouts: dict[int, tuple[ReadBlock, tuple[_Slot, ...], bool]] = {}

    def _layout(self, block: ReadBlock) -> tuple[tuple[_Slot, ...], bool]:
        """The block's slots, and whether any is a float (whose word order is then needed)."""
        known = self._layouts.get(id(block))
        if known is not None and known[0] is block:
            return known[1], known[2]
        if len(self._layouts) >= LAYOUTS_MAX:
            self._layouts.clear()
        layout = tuple(
            _Slot(
                point=p,
                name=p.name,
                start=p.address - block.address,
                end=p.address - block.address + p.format.count,
                decode=codec.decoder_of(p.format.dtype),
                format=p.format,
                group=p.group.value,
                unit=p.unit,
            )
            for p in block.points
        )
        floats = any(p.format.dtype is codec.DataType.FLOAT32 for p in block.points)
        if block.points and block.points[0].group not in SLOW_GROUPS:
            # Kept for the values polled every interval; a diagnostics block, read now and
            # then, is resolved for its read only: hundreds of points per family (some
            # 26,000 at 16 x 16) would otherwise each keep a slot for little gain.
            self._layouts[id(block)] = (block, layout, floats)
        return layout, floats

    def decode(
        self, state: DeviceState, block: ReadBlock, registers: tuple[int, ...]
    ) -> list[Sample]:
        """The samples of a block read; the device's values and pending identity updated."""
        monotonic, now = time.monotonic(), datetime.now(tz=UTC)
        layout, floats = self._layout(block)
        # Only a float's decoder reads the word order, which takes some looking up.
        order = state.float_order if floats else codec.DEFAULT_FLOAT_ORDER
        values = state.values
        deadlines = state.deadlines
        pending = deadlines.identity_pending
        bus, device, profile = self.bus, state.target.name, state.target.profile.id
        samples = []
        for slot in layout:
            chunk = registers[slot.start : slot.end]
            fmt = slot.format
            try:
                if len(chunk) == fmt.count:
                    value: codec.Decoded = slot.decode(fmt, chunk, order)
                else:  # registers short of the block: decode() says what is wrong
                    value = codec.decode(fmt, chunk, float_order=order)
            except DecodeError as exc:
                value = codec.Fault.undecodable(chunk, exc)
            if isinstance(value, codec.Fault):
                fault, good = value, None
            else:
                fault, good = None, value
            if fault is not None or state.undecodable:
                self._note_undecodable(state, slot.point, value)
            name = slot.name
            values[name] = value
            if pending and name in pending:
                deadlines.identity_read(name)
            # The sample as _sample() makes it, built here with what the slot resolved.
            samples.append(
                Sample(
                    bus=bus,
                    device=device,
                    profile=profile,
                    point=name,
                    value=good,
                    fault=fault.name if fault is not None else None,
                    unit=slot.unit if slot.point.unit_from is None else state.unit_of(slot.point),
                    quality=Quality.FAULT if fault is not None else Quality.GOOD,
                    monotonic=monotonic,
                    time=now,
                    group=slot.group,
                    raw=fault.registers if fault is not None else (),
                )
            )
        return samples

    def failed(self, state: DeviceState, block: ReadBlock, reason: str) -> list[Sample]:
        """A ``comms_error`` sample for every point of a block that could not be read."""
        at = (time.monotonic(), datetime.now(tz=UTC))
        state.deadlines.identity_failed(p.name for p in block.points)
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
