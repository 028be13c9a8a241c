"""Sparkplug B payloads, without I/O: metrics built from values, and commands read back.

The schema is Eclipse Tahu's ``sparkplug_b.proto`` (Sparkplug 3.0.0), compiled with protoc
into :mod:`~gateway.publish.sparkplug.sparkplug_b_pb2` beside this module. Everything else
of the package goes through here, so the generated code has one user.

``seq`` is not part of a payload as it is built: messages wait (in memory, or on disk
while the host is away) without it, and the sender appends it as they go out in order
(:func:`with_seq`): protobuf merges a field appended to an encoded message, and the last
value of a scalar field wins.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from datetime import UTC, datetime
from enum import IntEnum
from typing import Final

from google.protobuf.message import DecodeError

from gateway.errors import CommandRejectedError
from gateway.publish.sparkplug import sparkplug_b_pb2 as pb
from gateway.wire import codec

Payload = pb.Payload
Metric = pb.Payload.Metric


class SpType(IntEnum):
    """The Sparkplug data types the gateway uses (the schema's ``DataType``)."""

    INT8 = pb.Int8
    INT16 = pb.Int16
    INT32 = pb.Int32
    INT64 = pb.Int64
    UINT8 = pb.UInt8
    UINT16 = pb.UInt16
    UINT32 = pb.UInt32
    UINT64 = pb.UInt64
    FLOAT = pb.Float
    DOUBLE = pb.Double
    BOOLEAN = pb.Boolean
    STRING = pb.String
    DATETIME = pb.DateTime


# A register type's Sparkplug type: Float for process values, Int/UInt for registers,
# Boolean for status bits, String for identity; enums go as their code, bit fields as
# their word (and each named bit as a Boolean metric of its own), dates as DateTime.
DATATYPE_OF: Final[dict[codec.DataType, SpType]] = {
    codec.DataType.FLOAT32: SpType.FLOAT,
    codec.DataType.UINT8: SpType.UINT8,
    codec.DataType.INT8: SpType.INT8,
    codec.DataType.BOOL: SpType.BOOLEAN,
    codec.DataType.UINT16: SpType.UINT16,
    codec.DataType.INT16: SpType.INT16,
    codec.DataType.UINT32: SpType.UINT32,
    codec.DataType.INT32: SpType.INT32,
    codec.DataType.ENUM: SpType.UINT16,
    codec.DataType.ENUM32: SpType.UINT32,
    codec.DataType.BITFIELD: SpType.UINT16,
    codec.DataType.BITFIELD32: SpType.UINT32,
    codec.DataType.STRING: SpType.STRING,
    codec.DataType.YYMMDDHHMM: SpType.DATETIME,
    codec.DataType.DATETIME: SpType.DATETIME,
}

# Which field of the value oneof carries each type (Sparkplug 3.0, 6.4.16).
_INT_TYPES: Final = frozenset(
    {SpType.INT8, SpType.INT16, SpType.INT32, SpType.UINT8, SpType.UINT16, SpType.UINT32}
)
_LONG_TYPES: Final = frozenset({SpType.INT64, SpType.UINT64, SpType.DATETIME})
_SIGNED_BITS: Final = {SpType.INT8: 8, SpType.INT16: 16, SpType.INT32: 32, SpType.INT64: 64}
FIELD_OF: Final[dict[SpType, str]] = {
    **dict.fromkeys(_INT_TYPES, "int_value"),
    **dict.fromkeys(_LONG_TYPES, "long_value"),
    SpType.FLOAT: "float_value",
    SpType.DOUBLE: "double_value",
    SpType.BOOLEAN: "boolean_value",
    SpType.STRING: "string_value",
}

# The "Quality" property's codes, as Sparkplug hosts (Ignition, Tahu) read them.
QUALITY_GOOD: Final = 192
QUALITY_BAD: Final = 0
QUALITY_STALE: Final = 500
QUALITY: Final = "Quality"
ENG_UNIT: Final = "engUnit"
DESCRIPTION: Final = "description"
READ_ONLY: Final = "readOnly"
FAULT: Final = "fault"

# Payload field 3 (seq), wire type 0 (varint): (3 << 3) | 0.
_SEQ_TAG: Final = b"\x18"
SEQ_MODULUS: Final = 256  # seq runs 0..255 and wraps (Sparkplug 3.0, 6.4.1)

Scalar = float | int | bool | str


def epoch_ms(moment: datetime) -> int:
    """Milliseconds since the epoch (UTC), as Sparkplug timestamps are; naive is UTC."""
    if moment.tzinfo is None:
        moment = moment.replace(tzinfo=UTC)
    return int(moment.timestamp() * 1000)


def with_seq(payload: bytes, seq: int) -> bytes:
    """The encoded payload with its ``seq`` (0..255) appended."""
    return payload + _SEQ_TAG + _varint(seq % SEQ_MODULUS)


def _varint(value: int) -> bytes:
    out = bytearray()
    while True:
        low = value & 0x7F
        value >>= 7
        if value:
            out.append(low | 0x80)
        else:
            out.append(low)
            return bytes(out)


def set_value(metric: Metric, datatype: SpType, value: Scalar) -> None:
    """Put ``value`` in the field of the value oneof that ``datatype`` uses.

    Signed integers travel as their two's complement in the unsigned field (as Tahu does).
    """
    field = FIELD_OF[datatype]
    if field == "int_value":
        metric.int_value = int(value) & 0xFFFFFFFF
    elif field == "long_value":
        metric.long_value = int(value) & 0xFFFFFFFFFFFFFFFF
    elif field in {"float_value", "double_value"}:
        setattr(metric, field, float(value))
    elif field == "boolean_value":
        metric.boolean_value = bool(value)
    else:
        metric.string_value = str(value)


def set_property(metric: Metric, key: str, datatype: SpType, value: Scalar) -> None:
    """Add one property to the metric's property set."""
    properties = metric.properties
    properties.keys.append(key)
    prop = properties.values.add()
    prop.type = datatype
    field = FIELD_OF[datatype]
    if field == "int_value":
        prop.int_value = int(value) & 0xFFFFFFFF
    elif field == "long_value":
        prop.long_value = int(value)
    elif field == "float_value":
        prop.float_value = float(value)
    elif field == "boolean_value":
        prop.boolean_value = bool(value)
    else:
        prop.string_value = str(value)


def scalar_of(value: codec.Value, datatype: SpType) -> Scalar | None:
    """A decoded value as the scalar of its Sparkplug type; ``None`` if it is none."""
    result: Scalar | None
    if isinstance(value, codec.EnumValue):
        result = value.code
    elif isinstance(value, codec.BitfieldValue):
        result = value.raw
    elif isinstance(value, datetime):
        result = epoch_ms(value)
    else:
        result = value
    if result is None:
        return None
    if datatype is SpType.FLOAT and isinstance(result, int | float) and not math.isfinite(result):
        return None
    if datatype is SpType.STRING and not isinstance(result, str):
        return None
    return result


def new_payload(timestamp_ms: int) -> pb.Payload:
    """An empty payload stamped with the time it was built."""
    payload = pb.Payload()
    payload.timestamp = timestamp_ms
    return payload


@dataclass(frozen=True, slots=True)
class CommandMetric:
    """One metric of an NCMD or DCMD as it arrived: its name or alias, type and value."""

    name: str | None
    alias: int | None
    datatype: int | None
    value: Scalar | None  # None: no value given, or is_null
    value_field: str | None

    @property
    def label(self) -> str:
        """How a log line names it."""
        if self.name is not None:
            return repr(self.name)
        return f"alias {self.alias}"


def decode_command(payload: bytes) -> list[CommandMetric]:
    """The metrics of a command payload; malformed protobuf is a :class:`CommandRejectedError`."""
    message = pb.Payload()
    try:
        message.ParseFromString(payload)
    except DecodeError as exc:
        raise CommandRejectedError(f"the payload is not a Sparkplug B payload: {exc}") from exc
    if not message.metrics:
        raise CommandRejectedError("the payload carries no metric")
    result = []
    for metric in message.metrics:
        field = metric.WhichOneof("value")
        value: Scalar | None = None
        if field in FIELD_OF.values() and not metric.is_null:
            value = getattr(metric, field)
        elif field is not None and field not in FIELD_OF.values():
            label = metric.name or metric.alias
            raise CommandRejectedError(f"metric {label}: a {field} is refused")
        result.append(
            CommandMetric(
                name=metric.name if metric.HasField("name") else None,
                alias=metric.alias if metric.HasField("alias") else None,
                datatype=metric.datatype if metric.HasField("datatype") else None,
                value=value,
                value_field=None if metric.is_null else field,
            )
        )
    return result


def command_value(metric: CommandMetric, datatype: SpType) -> Scalar:
    """The value of a command metric for a metric of ``datatype``, or the reason it is wrong.

    The datatype, if the command gives one, must be the birth's, and the value must be in
    the field that type uses (a Float in ``float_value``, a Boolean in ``boolean_value``).
    """
    if metric.datatype is not None and metric.datatype != datatype:
        given = _type_name(metric.datatype)
        raise CommandRejectedError(
            f"metric {metric.label} is a {datatype.name.title()}, the command says {given}"
        )
    if metric.value is None:
        raise CommandRejectedError(f"metric {metric.label} carries no value")
    field = FIELD_OF[datatype]
    if metric.value_field != field:
        raise CommandRejectedError(
            f"metric {metric.label} is a {datatype.name.title()} ({field}); "
            f"the command carries a {metric.value_field}"
        )
    value = metric.value
    if isinstance(value, int) and not isinstance(value, bool) and datatype in _SIGNED_BITS:
        value = codec_signed(value, _SIGNED_BITS[datatype])
    return value


def codec_signed(value: int, bits: int) -> int:
    """A two's complement in an unsigned field as the signed integer it carries."""
    value &= (1 << bits) - 1
    return value - (1 << bits) if value & (1 << (bits - 1)) else value


def _type_name(code: int) -> str:
    try:
        return str(pb.DataType.Name(code))
    except ValueError:
        return f"type {code}"


def encode(payload: pb.Payload) -> bytes:
    """The payload's bytes."""
    return bytes(payload.SerializeToString())
