"""The manuals' access rules: what a read may span, what a write may target, which values pass.

Each rule raises :class:`SlaveExceptionError` with the code the sensor answers; the device
(:mod:`gateway.simulator.device`) applies what passes.
"""

from __future__ import annotations

import struct
from typing import TYPE_CHECKING, Final

from gateway.errors import CodecError
from gateway.wire import codec, frames
from gateway.wire.codec import DataType, Decoded

if TYPE_CHECKING:
    from collections.abc import Collection, Iterator

    from gateway.profiles import Point
    from gateway.simulator.registers import RegisterImage

ILLEGAL_VALUE: Final = 3  # digiLine: value out of range; tecLine/Reiss: data format
WRITE_PROTECTED: Final = 8  # digiLine only
MAX_READ: Final = 125


class SlaveExceptionError(Exception):
    """A request the simulated sensor answers with a Modbus exception code."""

    def __init__(self, code: int, reason: str) -> None:
        """Keep the code for the answer and the reason for the stats."""
        self.code = code
        self.reason = reason
        super().__init__(f"exception {code:02d}: {reason}")


def read_registers(
    image: RegisterImage,
    address: int,
    count: int,
    *,
    raw: Collection[int],
    unmapped: Collection[int],
) -> tuple[int, ...]:
    """Registers as the sensor sends them, or a :class:`SlaveExceptionError`.

    ``raw``: words held from start, maybe outside the map; ``unmapped``: registers this
    unit does not implement.
    """
    if not 1 <= count <= min(MAX_READ, image.profile.limits.max_read):
        raise SlaveExceptionError(frames.ILLEGAL_ADDRESS, f"read of {count} registers")
    span = range(address, address + count)
    # Raw words outside the map: a unit that answers more than its manual documents.
    answered = _in_readable_runs(image, address, count) or all(a in raw for a in span)
    if not answered or any(a in unmapped for a in span):
        raise SlaveExceptionError(
            frames.ILLEGAL_ADDRESS, f"read {address:#06x}+{count} crosses unmapped registers"
        )
    registers = image.registers
    words = {a: registers[a] for a in range(address - 1, address + count + 1) if a in registers}
    order, canonical = image.float_order, image.profile.float_order
    if order is not canonical:
        for point in _floats_overlapping(image, address, count):
            pair = (registers[point.address], registers[point.address + 1])
            words[point.address], words[point.address + 1] = codec.reorder_float(
                pair, canonical, order
            )
    return tuple(words[a] for a in span)


def _in_readable_runs(image: RegisterImage, address: int, count: int) -> bool:
    run = image.profile.readable_run(address)
    return run is not None and address + count - 1 <= run[1]


def _floats_overlapping(image: RegisterImage, address: int, count: int) -> Iterator[Point]:
    for start in range(address - 1, address + count):
        point = image.float_at(start)
        if point is not None:
            yield point


def write_targets(image: RegisterImage, address: int, count: int) -> list[tuple[Point, int]]:
    """Split a write into whole writable points (string prefixes allowed), with their lengths."""
    targets: list[tuple[Point, int]] = []
    position, end = address, address + count
    while position < end:
        for point in image.writable_at(position):
            if point.last < end:
                targets.append((point, point.count))
                break
            if point.dtype is DataType.STRING:
                targets.append((point, end - position))
                break
        else:
            if (owner := image.point_at(position)) is not None and not owner.writable:
                code = (
                    WRITE_PROTECTED
                    if WRITE_PROTECTED in image.profile.exceptions
                    else frames.ILLEGAL_ADDRESS
                )
                raise SlaveExceptionError(code, f"{owner.name} is read-only")
            raise SlaveExceptionError(
                frames.ILLEGAL_ADDRESS, f"no writable point starts at {position:#06x}"
            )
        position += targets[-1][1]
    return targets


def written_value_problem(image: RegisterImage, point: Point, chunk: tuple[int, ...]) -> str | None:
    """Why the words written to ``point`` (canonical order) are refused with 03, if they are."""
    fmt = point.format
    if point.dtype is DataType.STRING:
        fmt = codec.Format(dtype=DataType.STRING, count=len(chunk), encoding=fmt.encoding)
    try:
        value = codec.decode(fmt, chunk, float_order=image.profile.float_order)
    except CodecError as exc:
        return str(exc)
    return _value_problem(point, value)


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
