"""A simulated sensor's register image: values by point name, and the points held still.

The image holds floats in the profile's default word order; :mod:`gateway.simulator.access`
converts to the order the sensor's float-format register selects when a master reads or
writes them.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from gateway.errors import CodecError
from gateway.wire import codec, encoding
from gateway.wire.codec import DataType, Decoded, WordOrder

if TYPE_CHECKING:
    from collections.abc import Mapping, Sequence

    from gateway.profiles import Point, Profile


@dataclass(slots=True)
class RegisterImage:
    """Every documented register of one profile, with the points pinned by tests or config."""

    profile: Profile
    registers: dict[int, int] = field(default_factory=dict)
    held: dict[str, Decoded] = field(default_factory=dict)  # values pinned by tests or config
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

    # --- the map, indexed ----------------------------------------------------------------

    def float_at(self, address: int) -> Point | None:
        """The float point that starts at ``address``, if one does."""
        return self._floats.get(address)

    def writable_at(self, address: int) -> list[Point]:
        """The writable points that start at ``address``, whole ones and longest first."""
        return self._writable_at.get(address, [])

    def point_at(self, address: int) -> Point | None:
        """The point (not a view) that ``address`` belongs to, if any."""
        return self._point_at.get(address)

    @property
    def float_order(self) -> WordOrder:
        """The float word order currently selected on the sensor."""
        selector = self.profile.float_order_register
        if selector is None:
            return self.profile.float_order
        code = self.registers[self.profile.point(selector.point).address]
        return selector.orders.get(code, self.profile.float_order)

    # --- values by point name ----------------------------------------------------------

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

    def _store(self, point: Point, value: object) -> None:
        if isinstance(value, codec.Fault):
            self.set_fault(point.name, value.name)
            return
        registers = encoding.encode(point.format, value, float_order=self.profile.float_order)
        if point.dtype is DataType.STRING:
            registers = (*registers, *([0] * (point.count - len(registers))))
        self._write_registers(point.address, registers)

    def _write_registers(self, address: int, registers: Sequence[int]) -> None:
        for offset, value in enumerate(registers):
            self.registers[address + offset] = value
