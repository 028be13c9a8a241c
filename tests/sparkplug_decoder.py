"""An independent Sparkplug B decoder for the tests: the protobuf wire format read by hand.

It shares nothing with the product's encoder (neither the protobuf library nor the code
protoc generated): it reads varints, fixed 32/64-bit fields and length-delimited fields by
the field numbers of Eclipse Tahu's ``sparkplug_b.proto``, so a wrong field number, type
or encoding in the product shows here as a wrong value.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field
from typing import Any

# The DataType enum of sparkplug_b.proto, by code.
TYPE_NAMES = {
    1: "Int8",
    2: "Int16",
    3: "Int32",
    4: "Int64",
    5: "UInt8",
    6: "UInt16",
    7: "UInt32",
    8: "UInt64",
    9: "Float",
    10: "Double",
    11: "Boolean",
    12: "String",
    13: "DateTime",
    14: "Text",
}
_SIGNED_BITS = {"Int8": 8, "Int16": 16, "Int32": 32, "Int64": 64}


class WireError(ValueError):
    """Bytes that are not a protobuf message."""


def _varint(data: bytes, pos: int) -> tuple[int, int]:
    result = shift = 0
    while True:
        if pos >= len(data):
            raise WireError("truncated varint")
        byte = data[pos]
        pos += 1
        result |= (byte & 0x7F) << shift
        if not byte & 0x80:
            return result, pos
        shift += 7


def fields(data: bytes) -> list[tuple[int, int, int | bytes]]:
    """``(field number, wire type, value)`` in order; value is an int or the raw bytes."""
    out: list[tuple[int, int, int | bytes]] = []
    pos = 0
    while pos < len(data):
        key, pos = _varint(data, pos)
        number, wire = key >> 3, key & 7
        value: int | bytes
        if wire == 0:
            value, pos = _varint(data, pos)
        elif wire == 1:
            value, pos = data[pos : pos + 8], pos + 8
        elif wire == 2:
            length, pos = _varint(data, pos)
            value, pos = data[pos : pos + length], pos + length
        elif wire == 5:
            value, pos = data[pos : pos + 4], pos + 4
        else:
            raise WireError(f"wire type {wire}")
        if pos > len(data):
            raise WireError("truncated field")
        out.append((number, wire, value))
    return out


def _signed(value: int, bits: int) -> int:
    value &= (1 << bits) - 1
    return value - (1 << bits) if value & (1 << (bits - 1)) else value


_DECODERS: dict[int, Any] = {
    1: lambda raw: raw,  # uint64
    2: lambda raw: struct.unpack("<f", raw)[0],  # float
    3: lambda raw: struct.unpack("<d", raw)[0],  # double
    4: bool,  # bool
    5: lambda raw: raw.decode("utf-8"),  # string
}


def _value(number: int, raw: int | bytes, datatype: str | None, base: int) -> object:
    """A value field (metric: int 10 … string 15; property: int 3 … string 8)."""
    offset = number - base
    if offset == 0:  # uint32, signed types as their two's complement
        assert isinstance(raw, int)
        bits = _SIGNED_BITS.get(datatype or "")
        return _signed(raw, bits) if bits else raw
    decoder = _DECODERS.get(offset)
    return raw if decoder is None else decoder(raw)


def _properties(data: bytes) -> dict[str, object]:
    keys: list[str] = []
    values: list[object] = []
    for number, _, raw in fields(data):
        assert isinstance(raw, bytes)
        if number == 1:
            keys.append(raw.decode("utf-8"))
        elif number == 2:
            ptype: str | None = None
            value: object = None
            for n, _, r in fields(raw):
                if n == 1:
                    assert isinstance(r, int)
                    ptype = TYPE_NAMES.get(r)
                elif 3 <= n <= 8:
                    value = _value(n, r, ptype, 3)
            values.append(value)
    return dict(zip(keys, values, strict=True))


@dataclass
class DecodedMetric:
    name: str | None = None
    alias: int | None = None
    timestamp: int | None = None
    datatype: str | None = None
    is_historical: bool = False
    is_null: bool = False
    properties: dict[str, object] = field(default_factory=dict)
    value: object = None


@dataclass
class DecodedPayload:
    timestamp: int | None = None
    metrics: list[DecodedMetric] = field(default_factory=list)
    seq: int | None = None

    def by_name(self) -> dict[str, DecodedMetric]:
        return {m.name: m for m in self.metrics if m.name is not None}

    def by_alias(self) -> dict[int, DecodedMetric]:
        return {m.alias: m for m in self.metrics if m.alias is not None}


_METRIC_FIELDS: dict[int, tuple[str, Any]] = {
    1: ("name", lambda raw: raw.decode("utf-8")),
    2: ("alias", int),
    3: ("timestamp", int),
    4: ("datatype", lambda raw: TYPE_NAMES.get(raw, f"type {raw}")),
    5: ("is_historical", bool),
    7: ("is_null", bool),
    9: ("properties", _properties),
}


def _metric(data: bytes) -> DecodedMetric:
    metric = DecodedMetric()
    values: list[tuple[int, int | bytes]] = []
    for number, _, raw in fields(data):
        if number in _METRIC_FIELDS:
            name, convert = _METRIC_FIELDS[number]
            setattr(metric, name, convert(raw))
        elif 10 <= number <= 15:
            values.append((number, raw))
    for number, raw in values:  # after the datatype, wherever it stood
        metric.value = _value(number, raw, metric.datatype, 10)
    return metric


def decode(data: bytes) -> DecodedPayload:
    """A Sparkplug B ``Payload``: its timestamp, metrics and seq."""
    payload = DecodedPayload()
    for number, _, raw in fields(data):
        if number == 1:
            assert isinstance(raw, int)
            payload.timestamp = raw
        elif number == 2:
            assert isinstance(raw, bytes)
            payload.metrics.append(_metric(raw))
        elif number == 3:
            assert isinstance(raw, int)
            payload.seq = raw
    return payload


def _key(number: int, wire: int) -> bytes:
    return encode_varint((number << 3) | wire)


def encode_varint(value: int) -> bytes:
    """Base-128, least significant group first: protobuf's varint, and MQTT's remaining length."""
    out = bytearray()
    while True:
        low = value & 0x7F
        value >>= 7
        out.append(low | (0x80 if value else 0))
        if not value:
            return bytes(out)


def _length_delimited(number: int, data: bytes) -> bytes:
    return _key(number, 2) + encode_varint(len(data)) + data


def command(
    *metrics: tuple[str | int, str, object], timestamp: int = 1, datatype_given: bool = True
) -> bytes:
    """A command payload, hand-encoded: ``(name or alias, Sparkplug type name, value)``.

    The value goes in the field the type name says (an honest host), so a test can put a
    Float's value in ``boolean_value`` by naming the type ``Boolean``.
    """
    codes = {name: code for code, name in TYPE_NAMES.items()}
    out = _key(1, 0) + encode_varint(timestamp)
    for who, type_name, value in metrics:
        body = b""
        if isinstance(who, str):
            body += _length_delimited(1, who.encode())
        else:
            body += _key(2, 0) + encode_varint(who)
        if datatype_given:
            body += _key(4, 0) + encode_varint(codes[type_name])
        if type_name == "Float":
            body += _key(12, 5) + struct.pack("<f", float(value))  # type: ignore[arg-type]
        elif type_name == "Double":
            body += _key(13, 1) + struct.pack("<d", float(value))  # type: ignore[arg-type]
        elif type_name == "Boolean":
            body += _key(14, 0) + encode_varint(int(bool(value)))
        elif type_name in {"String", "Text"}:
            body += _length_delimited(15, str(value).encode())
        elif type_name in {"Int64", "UInt64", "DateTime"}:
            body += _key(11, 0) + encode_varint(int(value) & 0xFFFFFFFFFFFFFFFF)  # type: ignore[call-overload]
        else:
            body += _key(10, 0) + encode_varint(int(value) & 0xFFFFFFFF)  # type: ignore[call-overload]
        out += _length_delimited(2, body)
    return out
