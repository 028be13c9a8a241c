"""Values to registers, exactly as the sensor manuals define each data type.

The write side of :mod:`gateway.wire.codec`: the same :class:`~gateway.wire.codec.Format`,
one encoder per :class:`~gateway.wire.codec.DataType` in a table. A value that does not fit
the point (its type's range, the profile's bounds, an enum's labels, a string's length)
raises :class:`~gateway.errors.EncodeError` before anything reaches the bus.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Callable, Mapping
from datetime import datetime

from gateway.errors import EncodeError
from gateway.wire.codec import (
    DEFAULT_FLOAT_ORDER,
    STRING_ENCODINGS,
    BitfieldValue,
    DataType,
    EnumValue,
    Format,
    WordOrder,
    bytes_to_registers,
    float_to_registers,
)

_INT_BOUNDS: dict[DataType, tuple[int, int]] = {
    DataType.UINT8: (0, 0xFF),
    DataType.INT8: (-0x80, 0x7F),
    DataType.UINT16: (0, 0xFFFF),
    DataType.INT16: (-0x8000, 0x7FFF),
    DataType.UINT32: (0, 0xFFFF_FFFF),
    DataType.INT32: (-0x8000_0000, 0x7FFF_FFFF),
    DataType.ENUM: (0, 0xFFFF),
    DataType.ENUM32: (0, 0xFFFF_FFFF),
    DataType.BITFIELD: (0, 0xFFFF),
    DataType.BITFIELD32: (0, 0xFFFF_FFFF),
}

# YYMMDDHHMM must fit a uint32: tecLine manual 7.1, last date 2042-12-31 23:59.
_YYMMDDHHMM_LAST = datetime(2042, 12, 31, 23, 59)  # noqa: DTZ001 - the stamp has no zone


_Encoder = Callable[[Format, object, WordOrder], tuple[int, ...]]


def _check_range(fmt: Format, number: float) -> None:
    if fmt.minimum is not None and number < fmt.minimum:
        raise EncodeError(f"{number} is below the minimum {fmt.minimum}")
    if fmt.maximum is not None and number > fmt.maximum:
        raise EncodeError(f"{number} is above the maximum {fmt.maximum}")


def _as_int(value: object, dtype: DataType) -> int:
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise EncodeError(f"{dtype} needs an integer, got {value!r}")
    if isinstance(value, float) and not value.is_integer():
        raise EncodeError(f"{dtype} needs an integer, got {value!r}")
    number = int(value)
    low, high = _INT_BOUNDS[dtype]
    if not low <= number <= high:
        raise EncodeError(f"{number} does not fit {dtype} ({low} to {high})")
    return number


def _split32(number: int) -> tuple[int, int]:
    number &= 0xFFFF_FFFF
    return number >> 16, number & 0xFFFF


def _encode_float(fmt: Format, value: object, order: WordOrder) -> tuple[int, ...]:
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise EncodeError(f"float32 needs a number, got {value!r}")
    try:
        number = float(value)
    except OverflowError:  # an integer beyond any float (JSON allows 4300 digits)
        raise EncodeError(f"{value!r} does not fit a float32") from None
    if not math.isfinite(number):
        raise EncodeError(f"{value!r} is not a finite number")
    if abs(number) > struct.unpack(">f", b"\x7f\x7f\xff\xff")[0]:
        raise EncodeError(f"{value!r} does not fit a float32")
    _check_range(fmt, number)
    return float_to_registers(number, order)


def _encode_small_int(fmt: Format, value: object, _order: WordOrder) -> tuple[int, ...]:
    number = _as_int(value, fmt.dtype)
    _check_range(fmt, number)
    return (number & 0xFF if fmt.dtype in {DataType.UINT8, DataType.INT8} else number & 0xFFFF,)


def _encode_int32(fmt: Format, value: object, _order: WordOrder) -> tuple[int, ...]:
    number = _as_int(value, fmt.dtype)
    _check_range(fmt, number)
    return _split32(number)


def _encode_bool(_fmt: Format, value: object, _order: WordOrder) -> tuple[int, ...]:
    if not isinstance(value, bool):
        raise EncodeError(f"bool needs true or false, got {value!r}")
    return (int(value),)


def _enum_code(fmt: Format, value: object) -> int:
    if isinstance(value, EnumValue):
        value = value.code
    if isinstance(value, str):
        for code, label in fmt.enum.items():
            if label == value:
                return code
        raise EncodeError(f"{value!r} is not one of {sorted(fmt.enum.values())}")
    code = _as_int(value, fmt.dtype)
    if code not in fmt.enum:
        raise EncodeError(f"{code} is not one of the codes {sorted(fmt.enum)}")
    return code


def _encode_enum(fmt: Format, value: object, _order: WordOrder) -> tuple[int, ...]:
    code = _enum_code(fmt, value)
    return _split32(code) if fmt.dtype is DataType.ENUM32 else (code,)


def with_bits(fmt: Format, raw: int, bits: Mapping[object, object]) -> int:
    """``raw`` with the named ``bits`` set (``True``) or cleared (``False``), the rest kept.

    >>> flags = Format(dtype=DataType.BITFIELD, count=1, bits={0: "a", 2: "c"})
    >>> bin(with_bits(flags, 0b1_0001, {"a": False, "c": True}))
    '0b10100'
    """
    names = {name: bit for bit, name in fmt.bits.items()}
    for name, state in bits.items():
        if name not in names:
            raise EncodeError(f"{name!r} is not a bit of this field: {sorted(names)}")
        if not isinstance(state, bool):
            raise EncodeError(f"bit {name!r} needs true or false, got {state!r}")
        mask = 1 << names[name]
        raw = raw | mask if state else raw & ~mask
    return raw


def _encode_bitfield(fmt: Format, value: object, _order: WordOrder) -> tuple[int, ...]:
    if isinstance(value, BitfieldValue):
        value = value.raw
    raw = with_bits(fmt, 0, value) if isinstance(value, Mapping) else _as_int(value, fmt.dtype)
    return _split32(raw) if fmt.dtype is DataType.BITFIELD32 else (raw,)


def _encode_string(fmt: Format, value: object, _order: WordOrder) -> tuple[int, ...]:
    if not isinstance(value, str):
        raise EncodeError(f"string needs text, got {value!r}")
    try:
        raw = value.encode(STRING_ENCODINGS[fmt.encoding])
    except UnicodeEncodeError as exc:
        raise EncodeError(f"{value!r} cannot be written as {fmt.encoding}") from exc
    if b"\x00" in raw:
        raise EncodeError("text must not contain NUL characters")
    raw += b"\x00"  # the terminator is part of the capacity (S10 manual 2.6.3)
    if len(raw) > fmt.byte_capacity:
        raise EncodeError(
            f"{len(raw)} bytes with the terminating NUL exceed the {fmt.byte_capacity} bytes "
            "of this field"
        )
    if len(raw) % 2:
        raw += b"\x00"  # whole registers only: pad to an even length
    return bytes_to_registers(raw)


def _encode_yymmddhhmm(_fmt: Format, value: object, _order: WordOrder) -> tuple[int, ...]:
    if not isinstance(value, datetime):
        raise EncodeError(f"a calibration stamp needs a date and time, got {value!r}")
    if not datetime(2000, 1, 1) <= value.replace(tzinfo=None) <= _YYMMDDHHMM_LAST:  # noqa: DTZ001
        raise EncodeError(f"{value:%Y-%m-%d %H:%M} is outside 2000-01-01 to 2042-12-31 23:59")
    stamp = int(f"{value.year % 100:02d}{value:%m%d%H%M}")
    return _split32(stamp)


def _encode_datetime(fmt: Format, value: object, _order: WordOrder) -> tuple[int, ...]:
    if not isinstance(value, datetime):
        raise EncodeError(f"a date and time is needed, got {value!r}")
    offset = value.utcoffset() if value.tzinfo is not None else None
    if offset is None:
        raise EncodeError("the date and time needs a time zone (the sensor stores the offset)")
    minutes = int(offset.total_seconds() // 60)
    low, high = (-0x80, 0x7F) if fmt.tz_signed_byte else (-0x8000, 0x7FFF)
    if not low <= minutes <= high:
        raise EncodeError(f"a time-zone offset of {minutes} minutes does not fit this field")
    return (
        value.year,
        value.month,
        value.day,
        value.hour,
        value.minute,
        value.second,
        minutes & (0xFF if fmt.tz_signed_byte else 0xFFFF),
    )


_ENCODERS: dict[DataType, _Encoder] = {
    DataType.FLOAT32: _encode_float,
    DataType.UINT8: _encode_small_int,
    DataType.INT8: _encode_small_int,
    DataType.BOOL: _encode_bool,
    DataType.UINT16: _encode_small_int,
    DataType.INT16: _encode_small_int,
    DataType.UINT32: _encode_int32,
    DataType.INT32: _encode_int32,
    DataType.ENUM: _encode_enum,
    DataType.ENUM32: _encode_enum,
    DataType.BITFIELD: _encode_bitfield,
    DataType.BITFIELD32: _encode_bitfield,
    DataType.STRING: _encode_string,
    DataType.YYMMDDHHMM: _encode_yymmddhhmm,
    DataType.DATETIME: _encode_datetime,
}


def encode(
    fmt: Format, value: object, *, float_order: WordOrder = DEFAULT_FLOAT_ORDER
) -> tuple[int, ...]:
    """Encode a value for writing; anything that does not fit raises :class:`EncodeError`.

    Strings yield only the registers the text needs (terminator and padding included),
    so a short text is written with a short frame, as the manuals' examples do.
    """
    return _ENCODERS[fmt.dtype](fmt, value, float_order)
