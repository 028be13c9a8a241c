"""One simulated sensor: its register image, the manual's access rules and its behaviour.

The register image holds floats in the profile's default word order; reads and writes
convert to the order the device's float-format register selects (digiLine 0x0307), so
switching the order on the simulated sensor behaves as on the real one.
"""

from __future__ import annotations

import logging
import struct
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Final, Protocol

from gateway.errors import CodecError
from gateway.wire import codec, frames
from gateway.wire.codec import DataType, Decoded, WordOrder

if TYPE_CHECKING:
    from collections.abc import Iterator, Mapping, Sequence

    from gateway.profiles import Point, Profile
    from gateway.wire.timing import LineFormat

_LOGGER = logging.getLogger(__name__)

ILLEGAL_VALUE: Final = 3  # digiLine: value out of range; tecLine/Reiss: data format
WRITE_PROTECTED: Final = 8  # digiLine only
MAX_READ: Final = 125

# The interface registers, by the names every profile gives them (digiLine 0x0300-0x0302,
# S10 6.4 and H10 6.1.4; tecLine and Reiss 0x0400-0x0402, "Device data Modbus"), and what
# of the line each holds. Their enum labels say the line in one form across the families
# (``baud_19200``, ``8e1``), so the line's own labels find the codes.
_ADDRESS: Final = ("device_address", "modbus_address")
_BAUD_RATE: Final = ("baud_rate",)
_FRAMING: Final = ("data_format", "parity_stop_bits")


class SlaveExceptionError(Exception):
    """A request the simulated sensor answers with a Modbus exception code."""

    def __init__(self, code: int, reason: str) -> None:
        """Keep the code for the answer and the reason for the stats."""
        self.code = code
        self.reason = reason
        super().__init__(f"exception {code:02d}: {reason}")


@dataclass(frozen=True, slots=True)
class WriteRecord:
    """One write the simulated sensor accepted (or, with a reason, refused)."""

    time: float
    device: int
    function: int
    address: int
    values: tuple[int, ...]
    points: tuple[str, ...]
    exception: int | None = None


class Behaviour(Protocol):
    """The family-specific part of a simulated sensor (:mod:`gateway.simulator.behaviour`)."""

    def start(self, device: SimulatedDevice, now: float) -> None:
        """Fill nameplate, configuration and first values."""

    def tick(self, device: SimulatedDevice, now: float) -> None:
        """Move values up to ``now``."""

    def filter_write(self, device: SimulatedDevice, points: list[Point]) -> list[Point]:
        """The points of an accepted write that the sensor really stores."""

    def on_write(self, device: SimulatedDevice, points: list[Point], now: float) -> None:
        """React to stored points (triggers, calibration)."""


@dataclass(slots=True)
class SimulatedDevice:
    """A sensor on the simulated bus, driven by its profile plus a family behaviour."""

    profile: Profile
    address: int
    behaviour: Behaviour
    processing_s: float = 0.005  # t1, S10 manual 5.1: typically 5 ms
    animate: bool = True
    registers: dict[int, int] = field(default_factory=dict)
    initial: dict[str, object] = field(default_factory=dict)  # held from start (config)
    held: dict[str, Decoded] = field(default_factory=dict)  # values pinned by tests or config
    write_log: list[WriteRecord] = field(default_factory=list)
    unmapped: set[int] = field(default_factory=set)  # registers this unit does not implement
    raw: dict[int, int] = field(default_factory=dict)  # words held from start, maybe unmapped
    silent_until: float = 0.0
    last_write_end: float = float("-inf")
    last_write_wait_s: float = 0.0
    _floats: dict[int, Point] = field(default_factory=dict)
    _writable_at: dict[int, list[Point]] = field(default_factory=dict)
    _point_at: dict[int, Point] = field(default_factory=dict)

    def __post_init__(self) -> None:
        """Index the map and give every documented register a value."""
        for first, last in self.profile.readable:
            for address in range(first, last + 1):
                self.registers.setdefault(address, 0)
        for point in self.profile.points:
            if point.dtype is DataType.FLOAT32 and not point.view:
                self._floats[point.address] = point
            if point.writable:
                self._writable_at.setdefault(point.address, []).append(point)
            if not point.view:
                for address in range(point.address, point.last + 1):
                    self._point_at[address] = point
        for candidates in self._writable_at.values():
            candidates.sort(key=lambda p: (p.view, -p.count))

    # --- values by point name ----------------------------------------------------------

    @property
    def float_order(self) -> WordOrder:
        """The float word order currently selected on the sensor."""
        selector = self.profile.float_order_register
        if selector is None:
            return self.profile.float_order
        code = self.registers[self.profile.point(selector.point).address]
        return selector.orders.get(code, self.profile.float_order)

    def _raw(self, point: Point) -> tuple[int, ...]:
        return tuple(self.registers[a] for a in range(point.address, point.last + 1))

    def get(self, name: str) -> Decoded:
        """A point's current value, decoded as a master would (faults included)."""
        point = self.profile.point(name)
        return codec.decode(point.format, self._raw(point), float_order=self.profile.float_order)

    def put(self, name: str, value: object) -> None:
        """Store a value unless a test holds the point (behaviours use this)."""
        if name in self.held:
            return
        self._store(self.profile.point(name), value)

    def hold(self, name: str, value: object) -> None:
        """Pin a point to a value (or a :class:`codec.Fault`); animation leaves it alone."""
        point = self.profile.point(name)
        self._store(point, value)
        self.held[name] = self.get(name)

    def release(self, name: str) -> None:
        """Let animation move a held point again."""
        self.held.pop(name, None)

    def set_fault(self, name: str, fault: str) -> None:
        """Make a float point carry one of the manuals' error values (1.0e37 ... 9.0e37)."""
        codes = {v: k for k, v in codec.FLOAT_FAULTS.items()}
        if fault not in codes:
            raise CodecError(f"unknown fault {fault!r}; known: {sorted(codes)}")
        point = self.profile.point(name)
        raw = codes[fault].to_bytes(4, "big")
        ieee_registers = (int.from_bytes(raw[:2], "big"), int.from_bytes(raw[2:], "big"))
        canonical = codec.reorder_float(ieee_registers, WordOrder.ABCD, self.profile.float_order)
        self._write_registers(point.address, canonical)
        self.held[name] = self.get(name)

    def set_flags(self, name: str, **flags: bool) -> None:
        """Set or clear named bits of a bit field and hold it."""
        point = self.profile.point(name)
        current = self.get(name)
        assert isinstance(current, codec.BitfieldValue)  # noqa: S101 - profile guarantees it
        names = {bit_name: bit for bit, bit_name in point.format.bits.items()}
        raw = current.raw
        for flag, state in flags.items():
            if flag not in names:
                raise CodecError(f"{name} has no bit {flag!r}; bits: {sorted(names)}")
            raw = raw | (1 << names[flag]) if state else raw & ~(1 << names[flag])
        self.hold(name, raw)

    def _store(self, point: Point, value: object) -> None:
        if isinstance(value, codec.Fault):
            self.set_fault(point.name, value.name)
            return
        registers = codec.encode(point.format, value, float_order=self.profile.float_order)
        if point.dtype is DataType.STRING:
            registers = (*registers, *([0] * (point.count - len(registers))))
        self._write_registers(point.address, registers)

    def _write_registers(self, address: int, registers: Sequence[int]) -> None:
        for offset, value in enumerate(registers):
            self.registers[address + offset] = value

    # --- Modbus access -------------------------------------------------------------------

    def _in_readable_runs(self, address: int, count: int) -> bool:
        run = self.profile.readable_run(address)
        return run is not None and address + count - 1 <= run[1]

    def _floats_overlapping(self, address: int, count: int) -> Iterator[Point]:
        for start in range(address - 1, address + count):
            point = self._floats.get(start)
            if point is not None:
                yield point

    def read(self, address: int, count: int) -> tuple[int, ...]:
        """Registers as the sensor sends them, or a :class:`SlaveExceptionError`."""
        if not 1 <= count <= min(MAX_READ, self.profile.limits.max_read):
            raise SlaveExceptionError(frames.ILLEGAL_ADDRESS, f"read of {count} registers")
        span = range(address, address + count)
        # Raw words outside the map: a unit that answers more than its manual documents.
        answered = self._in_readable_runs(address, count) or all(a in self.raw for a in span)
        if not answered or self.unmapped.intersection(span):
            raise SlaveExceptionError(
                frames.ILLEGAL_ADDRESS, f"read {address:#06x}+{count} crosses unmapped registers"
            )
        image = {
            a: self.registers[a]
            for a in range(address - 1, address + count + 1)
            if a in self.registers
        }
        order = self.float_order
        if order is not self.profile.float_order:
            for point in self._floats_overlapping(address, count):
                pair = (self.registers[point.address], self.registers[point.address + 1])
                converted = codec.reorder_float(pair, self.profile.float_order, order)
                image[point.address], image[point.address + 1] = converted
        return tuple(image[a] for a in range(address, address + count))

    def _write_targets(self, address: int, count: int) -> list[tuple[Point, int]]:
        """Split a write into whole writable points (string prefixes allowed)."""
        targets: list[tuple[Point, int]] = []
        position, end = address, address + count
        while position < end:
            for point in self._writable_at.get(position, []):
                if point.last < end:
                    targets.append((point, point.count))
                    break
                if point.dtype is DataType.STRING:
                    targets.append((point, end - position))
                    break
            else:
                if (owner := self._point_at.get(position)) is not None and not owner.writable:
                    code = (
                        WRITE_PROTECTED
                        if WRITE_PROTECTED in self.profile.exceptions
                        else frames.ILLEGAL_ADDRESS
                    )
                    raise SlaveExceptionError(code, f"{owner.name} is read-only")
                raise SlaveExceptionError(
                    frames.ILLEGAL_ADDRESS, f"no writable point starts at {position:#06x}"
                )
            position += targets[-1][1]
        return targets

    def write(
        self, address: int, values: Sequence[int], *, function: int, now: float
    ) -> list[Point]:
        """Apply a write as the sensor would: checked whole, then applied, then acted on."""
        max_write = self.profile.limits.max_write
        if not 1 <= len(values) <= max_write:
            raise SlaveExceptionError(frames.ILLEGAL_ADDRESS, f"write of {len(values)} registers")
        try:
            targets = self._write_targets(address, len(values))
        except SlaveExceptionError as exc:
            self._log(
                now,
                function=function,
                address=address,
                values=values,
                points=(),
                exception=exc.code,
            )
            raise
        order = self.float_order
        staged: list[tuple[Point, tuple[int, ...]]] = []
        offset = 0
        for point, length in targets:
            chunk = tuple(values[offset : offset + length])
            offset += length
            if point.dtype is DataType.FLOAT32:
                chunk = codec.reorder_float(chunk, order, self.profile.float_order)
            self._check_value(
                point, chunk, now=now, function=function, address=address, values=values
            )
            staged.append((point, chunk))
        accepted = self.behaviour.filter_write(self, [p for p, _ in staged])
        for point, chunk in staged:
            if point in accepted:
                self._write_registers(point.address, chunk)
                self.held.pop(point.name, None)
        self._log(
            now,
            function=function,
            address=address,
            values=values,
            points=tuple(p.name for p in accepted),
            exception=None,
        )
        self.behaviour.on_write(self, accepted, now)
        return accepted

    def _check_value(
        self,
        point: Point,
        chunk: tuple[int, ...],
        *,
        now: float,
        function: int,
        address: int,
        values: Sequence[int],
    ) -> None:
        fmt = point.format
        if point.dtype is DataType.STRING:
            fmt = codec.Format(dtype=DataType.STRING, count=len(chunk), encoding=fmt.encoding)
        try:
            value = codec.decode(fmt, chunk, float_order=self.profile.float_order)
            problem = _value_problem(point, value)
        except CodecError as exc:
            problem = str(exc)
        if problem is not None:
            self._log(
                now,
                function=function,
                address=address,
                values=values,
                points=(point.name,),
                exception=ILLEGAL_VALUE,
            )
            raise SlaveExceptionError(ILLEGAL_VALUE, f"{point.name}: {problem}")

    def _log(
        self,
        now: float,
        /,
        *,
        function: int,
        address: int,
        values: Sequence[int],
        points: tuple[str, ...],
        exception: int | None,
    ) -> None:
        self.write_log.append(
            WriteRecord(
                time=now,
                device=self.address,
                function=function,
                address=address,
                values=tuple(values),
                points=points,
                exception=exception,
            )
        )

    def start(self, now: float, *, line: LineFormat | None = None) -> None:
        """Power up: the behaviour's nameplate and values, the line, then the configured values.

        A sensor answers only on the line its interface registers are set to, so they say
        ``line`` (the simulated line, or the format given for RTU over TCP); a configured
        value still wins, to simulate a sensor that reports something else.
        """
        self.behaviour.start(self, now)
        if line is not None:
            self._report_line(line)
        for name, value in self.initial.items():
            self.hold(name, value)
        self.hold_registers(self.raw)

    def hold_registers(self, words: Mapping[int, int]) -> None:
        """Pin raw words (by address) and the points they touch; animation leaves them alone.

        For what a value cannot say: words that do not decode (an S10 clock with month
        13) or registers the profile does not map.
        """
        for address, word in words.items():
            self.registers[address] = word
            point = self._point_at.get(address)
            if point is not None:
                self.held[point.name] = None  # held as raw words: they may not decode

    def _report_line(self, line: LineFormat) -> None:
        framing = f"8{line.parity}{line.stopbits}".lower()
        settings: Mapping[tuple[str, ...], object] = {
            _ADDRESS: self.address,
            _BAUD_RATE: f"baud_{line.baudrate}",
            _FRAMING: framing,
        }
        for names, value in settings.items():
            for point in (self.profile.point(n) for n in names if self.profile.has_point(n)):
                if point.format.enum and value not in point.format.enum.values():
                    # A real sensor cannot be set to this line (tests run faster ones): say
                    # so, and leave the register as the behaviour set it.
                    _LOGGER.warning(
                        "%s at %d: %s has no code for %s (codes: %s)",
                        self.profile.id,
                        self.address,
                        point.name,
                        value,
                        ", ".join(point.format.enum.values()),
                    )
                    continue
                self.put(point.name, value)

    def tick(self, now: float) -> None:
        """Let the behaviour move values up to ``now`` (called before every request)."""
        self.behaviour.tick(self, now)


def _value_problem(point: Point, value: Decoded) -> str | None:
    """Why a written value is refused with exception 03 (range and enum checks), if it is."""
    fmt = point.format
    if isinstance(value, codec.Fault):
        return f"{value.name} is not a value"
    if isinstance(value, codec.EnumValue) and not value.known:
        return f"{value.code} is not one of {sorted(fmt.enum)}"
    if isinstance(value, int | float) and not isinstance(value, bool):
        # Bounds compared as the sensor holds them: floats in float32.
        low, high = fmt.minimum, fmt.maximum
        if point.dtype is DataType.FLOAT32:
            low = None if low is None else _f32(low)
            high = None if high is None else _f32(high)
        if low is not None and value < low:
            return f"{value} below {fmt.minimum}"
        if high is not None and value > high:
            return f"{value} above {fmt.maximum}"
    return None


def _f32(value: float) -> float:
    result: float = struct.unpack(">f", struct.pack(">f", value))[0]
    return result
