"""Write commands: a set payload parsed, typed by its point and encoded, or rejected.

This module is pure. It turns what a user sends (``20.5``, ``wet``, or
``{"value": 20.5, "id": "abc"}``) into the registers to write, and refuses with a
:class:`CommandRejectedError` whose reason says what is wrong before anything reaches the
bus. Whether a flash-backed point may be written at all is :mod:`gateway.control.flash`'s job.

Text is typed by the point it is meant for:

- numbers (``float32`` and the integer types): ``"20.5"``, ``"3"``; ``"3.5"`` is not an integer;
- ``bool``: ``true``/``false``, ``1``/``0``, ``on``/``off`` (any case);
- enums: the label (``"wet"``) or the code (``"1"``);
- bit fields: a JSON object of bit names to ``true``/``false``, or the raw integer. Here an
  object encodes as if every bit it does not name were 0; the write path
  (:mod:`gateway.control.writes`) reads the word first and changes only the bits named. A raw
  integer is the whole word;
- ``datetime`` (digiLine clock): ISO 8601 with an offset, ``2024-05-01T12:00:00+02:00``;
- ``yymmddhhmm`` (calibration stamp): ISO 8601 to the minute; the stamp has no time zone, so
  an offset, if given, is dropped and the wall-clock time written as given;
- strings: the text as it is.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from dataclasses import dataclass
from datetime import datetime
from typing import TYPE_CHECKING

from gateway.errors import CommandRejectedError, EncodeError
from gateway.wire.codec import (
    BITFIELD_TYPES,
    ENUM_TYPES,
    NUMERIC_TYPES,
    DataType,
    Format,
    WordOrder,
)
from gateway.wire.encoding import encode

if TYPE_CHECKING:
    from gateway.profiles.model import Point, Profile

WRITE_SINGLE_REGISTER = 0x06  # Modbus Application Protocol V1.1b3, 6.6
WRITE_MULTIPLE_REGISTERS = 0x10  # Modbus Application Protocol V1.1b3, 6.12

_TRUE_WORDS = frozenset({"true", "1", "on"})
_FALSE_WORDS = frozenset({"false", "0", "off"})
_JSON_KEYS = frozenset({"value", "id", "reason"})
# A value is a scalar or an object of bits, arguments an object of scalars: 8 levels is
# plenty, and keeps the repr() in a rejection reason far from the recursion limit.
MAX_JSON_DEPTH = 8


@dataclass(frozen=True, slots=True)
class SetCommand:
    """One parsed set request: the value as sent (text stays text), the caller's id and reason.

    The reason goes into the write's record (why it was changed). Example::

        SetCommand(value="20.5", id=None)
        SetCommand(value={"temperature_from_ram": True}, id="42", reason="new probe")
    """

    value: object
    id: str | None = None
    reason: str = ""


def parse_set_payload(payload: bytes) -> SetCommand:
    """Parse a set payload: plain text, or a JSON object of ``value``, ``id`` and ``reason``.

    Surrounding whitespace of plain text is dropped (``echo`` adds a newline); a text whose
    spaces matter goes in JSON. A payload that starts with ``{`` is JSON and must be valid.
    """
    try:
        text = payload.decode("utf-8").strip()
    except UnicodeDecodeError as exc:
        raise CommandRejectedError(f"the payload is not UTF-8 text: {exc}") from exc
    if not text:
        raise CommandRejectedError("the payload is empty")
    if not text.startswith("{"):
        return SetCommand(value=text)
    data = parse_json(text)
    if not isinstance(data, dict):  # "{" can only start an object; kept for the type checker
        raise CommandRejectedError("malformed JSON: expected an object")
    if "value" not in data:
        raise CommandRejectedError('the JSON object needs a "value"')
    unknown = sorted(set(data) - _JSON_KEYS)
    if unknown:
        raise CommandRejectedError(
            f"unknown keys {unknown} in the JSON object; allowed: value, id, reason"
        )
    reason = data.get("reason", "")
    if not isinstance(reason, str):
        raise CommandRejectedError(f"the reason must be a JSON string, got {reason!r}")
    return SetCommand(value=data["value"], id=_command_id(data.get("id")), reason=reason.strip())


def parse_json(text: str) -> object:
    """A command's JSON document, or a :class:`CommandRejectedError` saying what is wrong.

    Beyond malformed JSON, three things ``json.loads`` lets through or raises in its own
    way are refused here, at the boundary, because later steps would fail on them
    outside the gateway's errors: an integer of more than 4300 digits (``ValueError``),
    nesting deep enough to exhaust the recursion limit (``RecursionError`` here, or
    later in the ``repr`` of a rejection reason), and a lone UTF-16 surrogate escape
    (U+D800 to U+DFFF on its own), which is no text and cannot be encoded into the
    UTF-8 result.
    """
    try:
        data = json.loads(text)
    except (ValueError, RecursionError) as exc:
        raise CommandRejectedError(f"malformed JSON: {exc}") from exc
    pending: list[tuple[object, int]] = [(data, 1)]
    while pending:  # iterative: the document may be as deep as the recursion limit
        item, depth = pending.pop()
        if depth > MAX_JSON_DEPTH:
            raise CommandRejectedError(f"the JSON nests deeper than {MAX_JSON_DEPTH} levels")
        if isinstance(item, dict):
            pending.extend((key, depth + 1) for key in item)
            pending.extend((value, depth + 1) for value in item.values())
        elif isinstance(item, list):
            pending.extend((value, depth + 1) for value in item)
        elif isinstance(item, str) and not _is_text(item):
            raise CommandRejectedError("the JSON holds a lone surrogate escape, which is no text")
    return data


def _is_text(text: str) -> bool:
    try:
        text.encode("utf-8")
    except UnicodeEncodeError:
        return False
    return True


def _command_id(raw: object) -> str | None:
    if raw is None:
        return None
    if isinstance(raw, str):
        return raw
    if isinstance(raw, bool | int | float):
        return json.dumps(raw)  # 42 -> "42", true -> "true", as the sender wrote it
    raise CommandRejectedError(f"the id must be a JSON string or number, got {raw!r}")


def writable_point(profile: Profile, point_name: str) -> Point:
    """The point of that name if it may be written, else a :class:`CommandRejectedError`.

    This is where a name that comes in (a set command, the command line, a feed, an
    operation, a calibration step) becomes a :class:`Point`, once; everything below takes
    the point.
    """
    if not profile.has_point(point_name):
        raise CommandRejectedError(
            f"no point {point_name!r} in profile {profile.id}", point=point_name
        )
    return require_writable(profile.point(point_name))


def require_writable(point: Point) -> Point:
    """The point if it may be written, else a :class:`CommandRejectedError`."""
    if not point.writable:
        raise CommandRejectedError("the point is read-only", point=point.name)
    return point


def validate_write(
    profile: Profile, point: Point, value: object, *, float_order: WordOrder
) -> tuple[int, ...]:
    """The registers that write ``value`` to the point, or a :class:`CommandRejectedError`.

    ``point`` is one of ``profile``'s (resolved by :func:`writable_point`); ``float_order``
    is the device's word order (the profile default, or what the device reports). Range,
    type and length checks are the codec's; its reason is kept.
    """
    require_writable(point)
    fmt = point.format
    coerce = _COERCERS.get(fmt.dtype, _as_is)
    try:
        registers = encode(fmt, coerce(fmt, value), float_order=float_order)
    except _CoercionError as exc:
        raise CommandRejectedError(str(exc), point=point.name) from exc
    except EncodeError as exc:
        raise CommandRejectedError(_with_range(fmt, str(exc)), point=point.name) from exc
    if len(registers) > profile.limits.max_write:
        raise CommandRejectedError(
            f"{len(registers)} registers exceed the {profile.limits.max_write} registers "
            f"profile {profile.id} accepts per write",
            point=point.name,
        )
    return registers


def function_for(registers: tuple[int, ...]) -> int:
    """The Modbus function that writes these registers: 6 for one, 16 for more."""
    if not registers:
        raise ValueError("there are no registers to write")
    return WRITE_SINGLE_REGISTER if len(registers) == 1 else WRITE_MULTIPLE_REGISTERS


# --- coercion of text by the point's type ----------------------------------------------


class _CoercionError(Exception):
    """Text that cannot be a value of the point's type; becomes the rejection reason."""


def _with_range(fmt: Format, message: str) -> str:
    """Add the allowed range to a numeric point's codec message."""
    if fmt.dtype not in NUMERIC_TYPES or (fmt.minimum is None and fmt.maximum is None):
        return message
    if fmt.minimum is None:
        return f"{message}; allowed: at most {fmt.maximum:g}"
    if fmt.maximum is None:
        return f"{message}; allowed: at least {fmt.minimum:g}"
    return f"{message}; allowed range {fmt.minimum:g} to {fmt.maximum:g}"


def _as_is(_fmt: Format, value: object) -> object:
    return value


def _to_float(fmt: Format, value: object) -> object:
    if not isinstance(value, str):
        return value  # the codec rejects what is not a number
    try:
        number = float(value)
    except ValueError:
        raise _CoercionError(f"{fmt.dtype} needs a number, got {value!r}") from None
    if not math.isfinite(number):
        raise _CoercionError(f"{value!r} is not a finite number")
    return number


def _to_int(fmt: Format, value: object) -> object:
    if not isinstance(value, str):
        return value
    try:
        return int(value)
    except ValueError:
        raise _CoercionError(f"{fmt.dtype} needs an integer, got {value!r}") from None


def _to_bool(_fmt: Format, value: object) -> object:
    if isinstance(value, bool):
        return value
    word = str(value).lower() if isinstance(value, str | int) else None
    if word in _TRUE_WORDS:
        return True
    if word in _FALSE_WORDS:
        return False
    raise _CoercionError(f"bool needs true/false, 1/0 or on/off, got {value!r}")


def _to_enum(fmt: Format, value: object) -> object:
    if not isinstance(value, str) or value in fmt.enum.values():
        return value
    try:
        return int(value)
    except ValueError:
        labels = ", ".join(fmt.enum[code] for code in sorted(fmt.enum))
        raise _CoercionError(f"unknown label {value!r}; allowed: {labels}") from None


def _to_bitfield(fmt: Format, value: object) -> object:
    if not isinstance(value, str):
        return value
    try:
        return int(value)
    except ValueError:
        names = ", ".join(fmt.bits[bit] for bit in sorted(fmt.bits))
        raise _CoercionError(
            f"a bit field needs a JSON object of bit names ({names}) to true/false, "
            f"or the raw integer; got {value!r}"
        ) from None


def _parse_iso(value: str) -> datetime:
    try:
        return datetime.fromisoformat(value)
    except ValueError:
        raise _CoercionError(f"needs an ISO 8601 date and time, got {value!r}") from None


def _to_datetime(_fmt: Format, value: object) -> object:
    if not isinstance(value, str):
        return value
    moment = _parse_iso(value)
    if moment.tzinfo is None:
        raise _CoercionError(
            f"needs a time-zone offset (the sensor stores it), e.g. "
            f"{moment:%Y-%m-%dT%H:%M:%S}+00:00; got {value!r}"
        )
    return moment


def _to_stamp(_fmt: Format, value: object) -> object:
    if not isinstance(value, str):
        return value
    moment = _parse_iso(value)
    if moment.second or moment.microsecond:
        raise _CoercionError(f"the stamp holds minutes, not seconds; got {value!r}")
    return moment


_Coercer = Callable[[Format, object], object]

_COERCERS: dict[DataType, _Coercer] = {
    DataType.FLOAT32: _to_float,
    **dict.fromkeys(NUMERIC_TYPES - {DataType.FLOAT32}, _to_int),
    DataType.BOOL: _to_bool,
    **dict.fromkeys(ENUM_TYPES, _to_enum),
    **dict.fromkeys(BITFIELD_TYPES, _to_bitfield),
    DataType.DATETIME: _to_datetime,
    DataType.YYMMDDHHMM: _to_stamp,
    DataType.STRING: _as_is,
}
