"""Modbus TCP framing: the 7-byte MBAP header around a PDU, built and checked here.

Modbus Messaging on TCP/IP Implementation Guide V1.0b, 3.1.3: transaction id (2 bytes),
protocol id (2 bytes, 0 = Modbus), length (2 bytes: the unit id and the PDU), unit id
(1 byte); then the PDU, without address or CRC (TCP checks the bytes).

Built and checked with :mod:`struct` rather than pymodbus's ``FramerSocket``: on a wrong
protocol id or a length beyond any PDU that framer waits for more bytes instead of
refusing (the shared bus checks the header before calling it for that reason), it decodes
the PDU through its own decoder where the gateway's answers go through
:func:`gateway.wire.frames.parse_response` with every check of the RTU path, and a master
must match the transaction id against its own request, which the framer leaves to its
client. The header is seven bytes of fixed layout; the PDUs stay pymodbus's
(:mod:`gateway.wire.frames` builds and decodes them).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from typing import TYPE_CHECKING, Final

from gateway.errors import (
    ConverterError,
    ConverterNoAnswerError,
    ConverterPathError,
    MalformedFrameError,
    UnexpectedDeviceError,
)
from gateway.wire import frames

if TYPE_CHECKING:
    from collections.abc import Mapping

MBAP_HEADER_LENGTH: Final = 7  # Implementation Guide V1.0b 3.1.3
MBAP_PROTOCOL_MODBUS: Final = 0  # Implementation Guide V1.0b 3.1.3: protocol identifier
MAX_PDU_LENGTH: Final = 253  # Modbus application protocol V1.1b3 4.1
MAX_TRANSACTION_ID: Final = 0xFFFF
DEFAULT_PORT: Final = 502  # Implementation Guide V1.0b 4.2.1: the registered Modbus port
GATEWAY_PATH_UNAVAILABLE: Final = 0x0A  # Modbus application protocol V1.1b3 7: exception 0A
GATEWAY_TARGET_FAILED: Final = 0x0B  # exception 0B: the target device failed to respond
_HEADER: Final = struct.Struct(">HHHB")

_CONVERTER_ERRORS: Final[dict[int, type[ConverterError]]] = {
    GATEWAY_PATH_UNAVAILABLE: ConverterPathError,
    GATEWAY_TARGET_FAILED: ConverterNoAnswerError,
}
_CONVERTER_MEANINGS: Final[dict[int, str]] = {
    GATEWAY_PATH_UNAVAILABLE: (
        "gateway path unavailable: the converter has no path to its serial side "
        "(check its serial port and Modbus settings)"
    ),
    GATEWAY_TARGET_FAILED: (
        "gateway target device failed to respond: the device did not answer the "
        "converter within the converter's response timeout"
    ),
}


@dataclass(frozen=True, slots=True, kw_only=True)
class MbapFrame:
    """One Modbus TCP frame cut from a stream: its header's fields and its PDU."""

    transaction: int
    unit: int
    pdu: bytes


def encode(transaction: int, unit: int, pdu: bytes) -> bytes:
    """``pdu`` behind an MBAP header (transaction id, protocol 0, length, unit id)."""
    return (
        _HEADER.pack(transaction & MAX_TRANSACTION_ID, MBAP_PROTOCOL_MODBUS, len(pdu) + 1, unit)
        + pdu
    )


def from_rtu(transaction: int, rtu_frame: bytes) -> bytes:
    """An RTU frame (address, PDU, CRC) as a Modbus TCP frame: the address is the unit id."""
    return encode(transaction, rtu_frame[0], rtu_frame[1:-2])


def to_rtu(unit: int, pdu: bytes) -> bytes:
    """A unit id and PDU as the RTU frame a converter puts on its serial side."""
    body = bytes((unit,)) + pdu
    return body + frames.crc16(body)


def decode(data: bytes | bytearray) -> tuple[MbapFrame, int] | None:
    """The first frame in ``data`` and the bytes it took; ``None`` while more are needed.

    A header that cannot start a Modbus frame (another protocol id, a length outside
    2..254) raises :class:`MalformedFrameError`: a byte stream has no silence to
    resynchronise on, so the caller drops what it holds.
    """
    if len(data) < MBAP_HEADER_LENGTH:
        return None
    transaction, protocol, length, unit = _HEADER.unpack_from(data)
    if protocol != MBAP_PROTOCOL_MODBUS:
        raise MalformedFrameError(f"MBAP protocol id {protocol}, not 0 (Modbus)")
    if not 2 <= length <= MAX_PDU_LENGTH + 1:  # noqa: PLR2004 - the unit id and a function code
        raise MalformedFrameError(f"MBAP length {length} outside 2..{MAX_PDU_LENGTH + 1}")
    end = 6 + length  # the length counts from the unit id, the header's seventh byte
    if len(data) < end:
        return None
    pdu = bytes(data[MBAP_HEADER_LENGTH:end])
    return MbapFrame(transaction=transaction, unit=unit, pdu=pdu), end


def parse_answer(
    request: frames.Request,
    frame: MbapFrame,
    *,
    where: str,
    exceptions: Mapping[int, str] = frames.STANDARD_EXCEPTIONS,
    byte_count_16bit: bool = False,
) -> frames.Response:
    """The answer to ``request`` in ``frame`` (its transaction id already matched).

    The converter's own exceptions 0A and 0B raise a :class:`ConverterError`; an answer of
    another unit :class:`UnexpectedDeviceError`; the rest is framed again as RTU (unit,
    PDU, CRC) so that one parser, :func:`frames.parse_response` with every check of the
    serial path (function, byte count, length, the exception's meaning in the family's
    words, the digiLine string quirk), judges answers on both kinds of bus. ``where``
    names the bus in the messages.
    """
    pdu = frame.pdu
    what = f"device {request.device} function {request.function:#04x} at {request.address:#06x}"
    if (
        len(pdu) == 2  # noqa: PLR2004 - function | 0x80, exception code
        and pdu[0] == request.function | frames.EXCEPTION_FLAG
        and pdu[1] in _CONVERTER_ERRORS
    ):
        code = pdu[1]
        raise _CONVERTER_ERRORS[code](
            f"{where}: the converter answered exception {code:02X} for {what}: "
            f"{_CONVERTER_MEANINGS[code]}",
            device=request.device,
            code=code,
        )
    if frame.unit != request.device:
        raise UnexpectedDeviceError(
            f"{where}: unit {frame.unit} answered a request for {what}",
            expected=request.device,
            received=frame.unit,
        )
    return frames.parse_response(
        request, to_rtu(frame.unit, pdu), exceptions=exceptions, byte_count_16bit=byte_count_16bit
    )
