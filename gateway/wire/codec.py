"""Registers to values and back, exactly as the sensor manuals define each data type.

The codec is pure: it knows data types, word orders and the float fault values, not
devices or buses. A point's :class:`Format` is resolved once from its profile; decoding
(here) and encoding (:mod:`gateway.wire.encoding`) then dispatch through a table keyed by
:class:`DataType`, never an ``if`` chain over vendors.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from datetime import datetime, timedelta, timezone
from enum import StrEnum
from typing import Final

from gateway.errors import DecodeError


class DataType(StrEnum):
    """Every register data type used by the four sensor families."""

    FLOAT32 = "float32"
    UINT8 = "uint8"  # low byte of a word, high byte unused (digiLine "char")
    INT8 = "int8"
    BOOL = "bool"  # least significant bit of a word
    UINT16 = "uint16"
    INT16 = "int16"
    UINT32 = "uint32"  # high word first (ABCD) in all four families
    INT32 = "int32"
    ENUM = "enum"  # 16-bit code with labels
    ENUM32 = "enum32"  # 32-bit code with labels (H10/H20 configuration registers)
    BITFIELD = "bitfield"  # 16 named bits
    BITFIELD32 = "bitfield32"
    STRING = "string"  # NUL-terminated, 2 bytes per register, first byte in the MSB
    YYMMDDHHMM = "yymmddhhmm"  # tecLine/Reiss calibration stamp as a decimal uint32
    DATETIME = "datetime"  # digiLine block: year, month, day, hour, min, sec, tz offset


class WordOrder(StrEnum):
    """Byte order of a 32-bit float on the wire; letters are IEEE 754 bytes, A = sign."""

    ABCD = "ABCD"  # IEEE 754 big endian
    CDAB = "CDAB"  # "standard Modbus format": words swapped (default of all families)
    BADC = "BADC"  # bytes swapped within each word
    DCBA = "DCBA"  # IEEE 754 little endian


DEFAULT_FLOAT_ORDER = WordOrder.CDAB  # S10 manual 2.6.2, H10/H20 2.6.2, tecLine 2.6.3

# Position in the IEEE 754 big-endian byte string of each byte as it arrives on the wire.
_WIRE_TO_IEEE: dict[WordOrder, tuple[int, int, int, int]] = {
    WordOrder.ABCD: (0, 1, 2, 3),
    WordOrder.CDAB: (2, 3, 0, 1),
    WordOrder.BADC: (1, 0, 3, 2),
    WordOrder.DCBA: (3, 2, 1, 0),
}

# Fixed register counts; strings take theirs from the profile (n bytes -> n/2 registers).
REGISTER_COUNT: dict[DataType, int] = {
    DataType.FLOAT32: 2,
    DataType.UINT8: 1,
    DataType.INT8: 1,
    DataType.BOOL: 1,
    DataType.UINT16: 1,
    DataType.INT16: 1,
    DataType.UINT32: 2,
    DataType.INT32: 2,
    DataType.ENUM: 1,
    DataType.ENUM32: 2,
    DataType.BITFIELD: 1,
    DataType.BITFIELD32: 2,
    DataType.YYMMDDHHMM: 2,
    DataType.DATETIME: 7,
}

NUMERIC_TYPES = frozenset(
    {
        DataType.FLOAT32,
        DataType.UINT8,
        DataType.INT8,
        DataType.UINT16,
        DataType.INT16,
        DataType.UINT32,
        DataType.INT32,
    }
)
ENUM_TYPES = frozenset({DataType.ENUM, DataType.ENUM32})
BITFIELD_TYPES = frozenset({DataType.BITFIELD, DataType.BITFIELD32})

# Float error values, S10 manual 2.8.2 and H10/H20 manual 2.8.2: a fault, never a value.
FLOAT_FAULTS: dict[int, str] = {
    struct.unpack(">I", struct.pack(">f", k * 1.0e37))[0]: name
    for k, name in enumerate(
        (
            "underrange",
            "overrange",
            "no_valid_input",
            "division_by_zero",
            "math_error",
            "invalid_compensation_temperature",
            "probe_short_circuit",
            "probe_break",
            "timeout",
        ),
        start=1,
    )
}

STRING_ENCODINGS = {"ascii": "ascii", "utf-8": "utf-8", "iso-8859-1": "iso-8859-1"}


UNDECODABLE: Final = "undecodable"  # the fault name of registers that are not a value


@dataclass(frozen=True, slots=True)
class Fault:
    """A value the sensor sent that is not a measurement, by name.

    Either a float register that carries one of the documented error values (``raw`` the
    float, e.g. 2.0e37 ``overrange``), or registers that cannot be a value of the point's
    type (:data:`UNDECODABLE`: an S10 clock dated month 13), with the ``registers`` as
    read and the ``reason``. The line worked either way: these are faults of the value.
    """

    name: str
    raw: float | None = None
    registers: tuple[int, ...] = ()
    reason: str = ""

    @classmethod
    def undecodable(cls, registers: Sequence[int], exc: DecodeError) -> Fault:
        """The fault of registers that :func:`decode` refused, with its reason."""
        return cls(name=UNDECODABLE, registers=tuple(registers), reason=str(exc))


@dataclass(frozen=True, slots=True)
class EnumValue:
    """A decoded enumeration: the code on the wire and the profile's label for it."""

    code: int
    label: str
    known: bool = True

    def __str__(self) -> str:
        """Show the label, which is what users see in topics and tables."""
        return self.label


@dataclass(frozen=True, slots=True)
class BitfieldValue:
    """A decoded bit field: the raw word and every named bit's state, in bit order."""

    raw: int
    flags: tuple[tuple[str, bool], ...]

    @property
    def active(self) -> tuple[str, ...]:
        """Names of the bits that are set."""
        return tuple(name for name, state in self.flags if state)

    def __str__(self) -> str:
        """Show the set bits, or ``-`` when none is set."""
        return ",".join(self.active) or "-"


Value = float | int | bool | str | datetime | EnumValue | BitfieldValue | None
Decoded = Value | Fault


@dataclass(frozen=True, slots=True, kw_only=True)
class Format:
    """What the codec needs to know about one point, resolved once from its profile.

    Example::

        Format(dtype=DataType.FLOAT32, count=2, minimum=0.0, maximum=99.99)
    """

    dtype: DataType
    count: int
    encoding: str = "ascii"
    enum: Mapping[int, str] = field(default_factory=dict)
    bits: Mapping[int, str] = field(default_factory=dict)
    minimum: float | None = None
    maximum: float | None = None
    tz_signed_byte: bool = False  # S10 stores some time-zone offsets as a "char"
    float_faults: bool = False  # digiLine floats may carry 1.0e37 ... 9.0e37

    @property
    def byte_capacity(self) -> int:
        """Bytes a string point holds, terminating NUL included."""
        return 2 * self.count


# --- helpers ---------------------------------------------------------------------------


def _u32(registers: Sequence[int]) -> int:
    return (registers[0] << 16) | registers[1]


def _signed(value: int, bits: int) -> int:
    return value - (1 << bits) if value & (1 << (bits - 1)) else value


def registers_to_bytes(registers: Sequence[int]) -> bytes:
    """Registers as they travel on the wire, high byte first."""
    return b"".join(r.to_bytes(2, "big") for r in registers)


def bytes_to_registers(data: bytes) -> tuple[int, ...]:
    """Big-endian byte pairs as register values; ``data`` must have an even length."""
    return tuple(int.from_bytes(data[i : i + 2], "big") for i in range(0, len(data), 2))


def float_to_registers(value: float, order: WordOrder) -> tuple[int, int]:
    """Encode a float32 in the given wire order."""
    ieee = struct.pack(">f", value)
    wire = bytearray(4)
    for wire_index, ieee_index in enumerate(_WIRE_TO_IEEE[order]):
        wire[wire_index] = ieee[ieee_index]
    regs = bytes_to_registers(bytes(wire))
    return regs[0], regs[1]


def reorder_float(
    registers: Sequence[int], source: WordOrder, target: WordOrder
) -> tuple[int, int]:
    """The same float32 bit pattern moved from one wire order to another (faults included)."""
    ieee = _float_bits(registers, source).to_bytes(4, "big")
    wire = bytearray(4)
    for wire_index, ieee_index in enumerate(_WIRE_TO_IEEE[target]):
        wire[wire_index] = ieee[ieee_index]
    regs = bytes_to_registers(bytes(wire))
    return regs[0], regs[1]


# For each order, the wire byte that lands at each IEEE position (the inverse of the above):
# a float is decoded on every poll, so the bytes are picked, not shuffled in a loop.
_IEEE_FROM_WIRE: dict[WordOrder, tuple[int, int, int, int]] = {
    order: (wire.index(0), wire.index(1), wire.index(2), wire.index(3))
    for order, wire in _WIRE_TO_IEEE.items()
}


def _swap(word: int) -> int:
    """A register's two bytes exchanged."""
    return ((word & 0xFF) << 8) | (word >> 8)


# The IEEE bit pattern of two registers in each wire order, with shifts: a float is decoded
# on every poll, and packing the registers into bytes to pick them took several times as long.
_FLOAT_BITS: Final[dict[WordOrder, Callable[[Sequence[int]], int]]] = {
    WordOrder.ABCD: lambda r: (r[0] << 16) | r[1],
    WordOrder.CDAB: lambda r: (r[1] << 16) | r[0],
    WordOrder.BADC: lambda r: (_swap(r[0]) << 16) | _swap(r[1]),
    WordOrder.DCBA: lambda r: (_swap(r[1]) << 16) | _swap(r[0]),
}


def _float_bits(registers: Sequence[int], order: WordOrder) -> int:
    """The IEEE 754 bits of a float32 in two registers (16-bit values, as read)."""
    return _FLOAT_BITS[order](registers)


# --- decoders --------------------------------------------------------------------------

_Decoder = Callable[[Format, Sequence[int], WordOrder], Decoded]


def shortest_float32(value: float) -> float:
    """The shortest decimal that is the same float32: 24.091, not 24.090909957885742.

    Sensors compute in float32; the extra binary digits of a double are not information,
    and they would reach dashboards and MQTT payloads as noise.
    """
    if not math.isfinite(value):
        return value
    return _shortest(value, _F32.pack(value))


_F32: Final = struct.Struct(">f")
_U32: Final = struct.Struct(">I")
_SHORTEST_FORMATS: Final = ("%.6g", "%.7g", "%.8g", "%.9g")  # 9 digits always round-trip
_EXPONENT_BITS: Final = 0x7F800000  # all set: an infinity or a NaN


def _shortest(value: float, packed: bytes) -> float:
    """:func:`shortest_float32` of a finite ``value`` whose float32 bytes are ``packed``."""
    pack = _F32.pack
    for text in _SHORTEST_FORMATS:
        candidate = float(text % value)
        if pack(candidate) == packed:
            return candidate
    return value


def _decode_float(fmt: Format, regs: Sequence[int], order: WordOrder) -> Decoded:
    bits = _FLOAT_BITS[order](regs)  # _float_bits() without its call: every float of a poll
    packed = _U32.pack(bits)
    value: float = _F32.unpack(packed)[0]
    if fmt.float_faults and (name := FLOAT_FAULTS.get(bits)) is not None:
        return Fault(name=name, raw=value)
    if bits & _EXPONENT_BITS == _EXPONENT_BITS:
        return value  # not finite: as it is
    return _shortest(value, packed)


def _decode_uint8(_fmt: Format, regs: Sequence[int], _order: WordOrder) -> Decoded:
    return regs[0] & 0xFF


def _decode_int8(_fmt: Format, regs: Sequence[int], _order: WordOrder) -> Decoded:
    return _signed(regs[0] & 0xFF, 8)


def _decode_bool(_fmt: Format, regs: Sequence[int], _order: WordOrder) -> Decoded:
    return bool(regs[0] & 0x0001)


def _decode_uint16(_fmt: Format, regs: Sequence[int], _order: WordOrder) -> Decoded:
    return regs[0]


def _decode_int16(_fmt: Format, regs: Sequence[int], _order: WordOrder) -> Decoded:
    return _signed(regs[0], 16)


def _decode_uint32(_fmt: Format, regs: Sequence[int], _order: WordOrder) -> Decoded:
    return _u32(regs)


def _decode_int32(_fmt: Format, regs: Sequence[int], _order: WordOrder) -> Decoded:
    return _signed(_u32(regs), 32)


def _enum_value(fmt: Format, code: int) -> EnumValue:
    label = fmt.enum.get(code)
    if label is None:
        return EnumValue(code=code, label=f"unknown_{code}", known=False)
    return EnumValue(code=code, label=label)


def _decode_enum(fmt: Format, regs: Sequence[int], _order: WordOrder) -> Decoded:
    return _enum_value(fmt, regs[0])


def _decode_enum32(fmt: Format, regs: Sequence[int], _order: WordOrder) -> Decoded:
    return _enum_value(fmt, _u32(regs))


# Each bit field's named bits in bit order, by the mapping (kept with it, so that a reused id
# is told apart): a status word is decoded on every poll, and sorting its bits every time
# was most of the work.
_BITS_IN_ORDER: dict[int, tuple[Mapping[int, str], tuple[tuple[int, str], ...]]] = {}
_BITS_IN_ORDER_MAX: Final = 1024  # bit fields kept; past this many they are sorted anew


def _bits_in_order(bits: Mapping[int, str]) -> tuple[tuple[int, str], ...]:
    known = _BITS_IN_ORDER.get(id(bits))
    if known is not None and known[0] is bits:
        return known[1]
    ordered = tuple(sorted(bits.items()))
    if len(_BITS_IN_ORDER) >= _BITS_IN_ORDER_MAX:
        _BITS_IN_ORDER.clear()
    _BITS_IN_ORDER[id(bits)] = (bits, ordered)
    return ordered


def _bitfield_value(fmt: Format, raw: int) -> BitfieldValue:
    flags = tuple([(name, bool(raw >> bit & 1)) for bit, name in _bits_in_order(fmt.bits)])
    return BitfieldValue(raw=raw, flags=flags)


def _decode_bitfield(fmt: Format, regs: Sequence[int], _order: WordOrder) -> Decoded:
    return _bitfield_value(fmt, regs[0])


def _decode_bitfield32(fmt: Format, regs: Sequence[int], _order: WordOrder) -> Decoded:
    return _bitfield_value(fmt, _u32(regs))


def _decode_string(fmt: Format, regs: Sequence[int], _order: WordOrder) -> Decoded:
    raw = registers_to_bytes(regs)
    text, _nul, _garbage = raw.partition(b"\x00")  # bytes after the first NUL mean nothing
    try:
        return text.decode(STRING_ENCODINGS[fmt.encoding])
    except UnicodeDecodeError as exc:
        raise DecodeError(f"string bytes {text!r} are not valid {fmt.encoding}") from exc


def _decode_yymmddhhmm(_fmt: Format, regs: Sequence[int], _order: WordOrder) -> Decoded:
    stamp = _u32(regs)
    if stamp == 0:  # the documented initial value: never calibrated
        return None
    minute, hour = stamp % 100, stamp // 100 % 100
    day, month, year = stamp // 10**4 % 100, stamp // 10**6 % 100, stamp // 10**8
    try:
        return datetime(2000 + year, month, day, hour, minute)  # noqa: DTZ001 - zone-less stamp
    except ValueError as exc:
        raise DecodeError(f"{stamp} is not a YYMMDDHHMM date: {exc}") from exc


def _decode_datetime(fmt: Format, regs: Sequence[int], _order: WordOrder) -> Decoded:
    if not any(regs):  # never set
        return None
    year = regs[0]
    month, day, hour, minute, second = (r & 0xFF for r in regs[1:6])
    offset = _signed(regs[6] & 0xFF, 8) if fmt.tz_signed_byte else _signed(regs[6], 16)
    try:
        zone = timezone(timedelta(minutes=offset))
        return datetime(year, month, day, hour, minute, second, tzinfo=zone)
    except ValueError as exc:
        raise DecodeError(f"registers {list(regs)} are not a date and time: {exc}") from exc


_DECODERS: dict[DataType, _Decoder] = {
    DataType.FLOAT32: _decode_float,
    DataType.UINT8: _decode_uint8,
    DataType.INT8: _decode_int8,
    DataType.BOOL: _decode_bool,
    DataType.UINT16: _decode_uint16,
    DataType.INT16: _decode_int16,
    DataType.UINT32: _decode_uint32,
    DataType.INT32: _decode_int32,
    DataType.ENUM: _decode_enum,
    DataType.ENUM32: _decode_enum32,
    DataType.BITFIELD: _decode_bitfield,
    DataType.BITFIELD32: _decode_bitfield32,
    DataType.STRING: _decode_string,
    DataType.YYMMDDHHMM: _decode_yymmddhhmm,
    DataType.DATETIME: _decode_datetime,
}


def decoder_of(dtype: DataType) -> Callable[[Format, Sequence[int], WordOrder], Decoded]:
    """The decoder of a type, to resolve once per point; its registers must be ``count`` long.

    :func:`decode` checks the count and looks the decoder up on every call; a poll loop
    that decodes the same points again and again resolves them once (Telegraf's way).
    """
    return _DECODERS[dtype]


def decode(
    fmt: Format, registers: Sequence[int], *, float_order: WordOrder = DEFAULT_FLOAT_ORDER
) -> Decoded:
    """Decode a point's registers; a float error value comes back as a :class:`Fault`."""
    if len(registers) != fmt.count:
        raise DecodeError(f"{fmt.dtype} needs {fmt.count} registers, got {len(registers)}")
    return _DECODERS[fmt.dtype](fmt, registers, float_order)
