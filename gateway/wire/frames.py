"""Modbus RTU frames: requests built and responses parsed for a strict master, and a slave's.

What a strict master needs and a general client does not give: a response matched against
the request in flight (device, function, byte count, length), every failure classified as
its own error, the frame length expected from the first bytes, and the digiLine string
quirk as an explicit, reported tolerance. The server-side helpers serve the simulator.

The four functions the sensors speak (03, 04, 06, 16) and their exception answers are
framed and read here with :mod:`struct`, the CRC from our own table (:func:`crc_value`),
a read's answer by a struct per register count (:func:`read_answer`). They were
pymodbus's framer and PDUs once; its decoder took a third of a transaction's CPU, and a
gateway that only polls held all of pymodbus (its framers, PDUs, datastore and simulator:
some 1 MiB, ``bench/memory.py --reference``) for frames it builds with a few bytes. What
is read here is read as pymodbus read it, the same verdicts and messages (the fuzzing
tests hold both to an oracle of the manuals). Only a function code outside the four, which
no poll asks for, still goes to pymodbus's decoder, imported then, to tell a PDU of
another function from garbage as before.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Final

from gateway.errors import (
    CrcError,
    DeviceExceptionError,
    EncodeError,
    GatewayError,
    MalformedFrameError,
    UnexpectedDeviceError,
)

if TYPE_CHECKING:
    from collections.abc import Mapping, Sequence

READ_HOLDING: Final = 0x03
READ_INPUT: Final = 0x04
WRITE_SINGLE: Final = 0x06
WRITE_MULTIPLE: Final = 0x10
READ_FUNCTIONS: Final = frozenset({READ_HOLDING, READ_INPUT})
BROADCAST: Final = 0
MAX_ADDRESS: Final = 0xFFFF
MAX_REGISTER_VALUE: Final = 0xFFFF
MAX_READ_REGISTERS: Final = 125  # Modbus application protocol 6.3; all four manuals
MAX_WRITE_REGISTERS: Final = 123  # Modbus application protocol 6.12
EXCEPTION_FLAG: Final = 0x80
ILLEGAL_FUNCTION: Final = 1  # exception 01 in all four manuals
ILLEGAL_ADDRESS: Final = 2  # exception 02 in all four manuals: unmapped address, too many words
EXCEPTION_FRAME_LENGTH: Final = 5  # device, function | 0x80, code, CRC
WRITE_RESPONSE_LENGTH: Final = 8  # device, function, address, value or count, CRC
READ_REQUEST_LENGTH: Final = 8  # device, function, address, count, CRC
QUIRK_STRING_BYTE_COUNT: Final = "string_byte_count_16bit"

# Standard Modbus meanings; each profile supplies its family's own.
STANDARD_EXCEPTIONS: Final[Mapping[int, str]] = {
    1: "illegal_function",
    2: "illegal_address",
    3: "illegal_value",
    4: "device_failure",
}

_ADDRESS_COUNT: Final = struct.Struct(">HH")  # address and count, or address and value
_WRITE_HEAD: Final = struct.Struct(">HHB")  # function 16: address, count, byte count


def _crc_table() -> tuple[int, ...]:
    """CRC-16/MODBUS (polynomial 0xA001 reflected) of every byte value, for a byte at a time."""
    table = []
    for byte in range(256):
        crc = byte
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
        table.append(crc)
    return tuple(table)


_CRC_TABLE: Final = _crc_table()


def crc_value(data: bytes | bytearray | memoryview) -> int:
    """The Modbus CRC of ``data`` as a number (Modbus over serial line 2.5.1.2).

    Our own table, not pymodbus's ``FramerRTU.compute_CRC``: every answer is checked
    with it, and this loop is the same table walk without a class attribute lookup and
    a byte swap per call. The low byte goes first on the wire.
    """
    crc = 0xFFFF
    table = _CRC_TABLE
    for byte in data:
        crc = (crc >> 8) ^ table[(crc ^ byte) & 0xFF]
    return crc


def crc16(data: bytes) -> bytes:
    """The Modbus CRC of ``data`` in wire order (low byte first)."""
    return crc_value(data).to_bytes(2, "little")


def crc_ok(frame: bytes | bytearray | memoryview) -> bool:
    """Whether the last two bytes of ``frame`` are the CRC of the rest."""
    if len(frame) < 4:  # noqa: PLR2004 - device, function, CRC
        return False
    return crc_value(frame[:-2]) == frame[-2] | (frame[-1] << 8)


@dataclass(frozen=True, slots=True, kw_only=True)
class Request:
    """A request as sent: what it asks, and its bytes with CRC."""

    device: int
    function: int
    address: int
    count: int
    values: tuple[int, ...] = ()
    frame: bytes
    # Said once, at the build, not worked out at every look: a transaction looks three
    # times, and a request is built once and sent again and again.
    is_broadcast: bool = field(init=False, repr=False, compare=False)
    """Broadcast requests (address 0) get no answer."""
    is_write: bool = field(init=False, repr=False, compare=False)
    """Whether the request writes registers."""

    def __post_init__(self) -> None:
        """Its kinds, from its device and function."""
        object.__setattr__(self, "is_broadcast", self.device == BROADCAST)
        object.__setattr__(self, "is_write", self.function in {WRITE_SINGLE, WRITE_MULTIPLE})


@dataclass(frozen=True, slots=True, kw_only=True)
class Response:
    """A response that matched its request."""

    device: int
    function: int
    address: int = 0
    count: int = 0
    registers: tuple[int, ...] = ()
    tolerated: str | None = None  # name of the documented quirk the frame needed


def _frame(device: int, function: int, payload: bytes) -> bytes:
    """An RTU frame: device, function, payload, CRC (Modbus over serial line 2.5.1)."""
    body = bytes((device, function)) + payload
    return body + crc16(body)


def _decodes(pdu: bytes, *, is_server: bool) -> bool:
    """Whether pymodbus reads ``pdu``, of a function code outside the four, as a PDU.

    Only a frame no poll asks for reaches this (another function from a confused
    converter, another master's request to the simulator), so pymodbus is imported here,
    the first time one comes: the verdict stays the one it gave, and a gateway that only
    polls does not hold it.
    """
    from pymodbus.pdu import DecodePDU  # noqa: PLC0415

    return DecodePDU(is_server=is_server).decode(pdu) is not None


def _check_device(device: int, *, broadcast_ok: bool) -> None:
    low = BROADCAST if broadcast_ok else 1
    if not low <= device <= 247:  # noqa: PLR2004 - Modbus unicast range
        raise EncodeError(f"device address {device} outside {low}..247")


def _check_register(value: int) -> None:
    if not 0 <= value <= MAX_REGISTER_VALUE:
        raise EncodeError(f"register value {value} outside 0..65535")


def read_request(device: int, address: int, count: int, *, function: int = READ_HOLDING) -> Request:
    """Build a read of ``count`` registers (function 03, or 04 which reads the same map)."""
    _check_device(device, broadcast_ok=False)
    if function not in READ_FUNCTIONS:
        raise EncodeError(f"function {function} does not read registers")
    if not 1 <= count <= MAX_READ_REGISTERS:
        raise EncodeError(f"cannot read {count} registers (1..{MAX_READ_REGISTERS})")
    if not 0 <= address <= MAX_ADDRESS - count + 1:
        raise EncodeError(f"address {address} with {count} registers is outside the map")
    frame = _frame(device, function, _ADDRESS_COUNT.pack(address, count))
    return Request(device=device, function=function, address=address, count=count, frame=frame)


def write_single_request(device: int, address: int, value: int) -> Request:
    """Build a function 06 write of one register (device 0 broadcasts)."""
    _check_device(device, broadcast_ok=True)
    _check_register(value)
    frame = _frame(device, WRITE_SINGLE, _ADDRESS_COUNT.pack(address, value))
    return Request(
        device=device, function=WRITE_SINGLE, address=address, count=1, values=(value,), frame=frame
    )


def write_multiple_request(device: int, address: int, values: Sequence[int]) -> Request:
    """Build a function 16 write of consecutive registers (device 0 broadcasts)."""
    _check_device(device, broadcast_ok=True)
    if not 1 <= len(values) <= MAX_WRITE_REGISTERS:
        raise EncodeError(f"cannot write {len(values)} registers (1..{MAX_WRITE_REGISTERS})")
    for value in values:
        _check_register(value)
    count = len(values)
    payload = _WRITE_HEAD.pack(address, count, 2 * count) + _WORDS[count].pack(*values)
    return Request(
        device=device,
        function=WRITE_MULTIPLE,
        address=address,
        count=count,
        values=tuple(values),
        frame=_frame(device, WRITE_MULTIPLE, payload),
    )


def write_request(device: int, address: int, values: Sequence[int]) -> Request:
    """Function 06 for one register, 16 for more: what the manuals use for each type."""
    if len(values) == 1:
        return write_single_request(device, address, values[0])
    return write_multiple_request(device, address, values)


# --- master side: lengths and parsing --------------------------------------------------


def response_length(request: Request, head: bytes, *, byte_count_16bit: bool = False) -> int:
    """Total length of the response that starts with ``head``; 0 while more bytes are needed.

    Raises :class:`MalformedFrameError` when the function code can answer neither the
    request nor an exception to it, so the caller can resynchronise at once.
    """
    if len(head) < 2:  # noqa: PLR2004
        return 0
    function = head[1]
    if function == request.function | EXCEPTION_FLAG:
        return EXCEPTION_FRAME_LENGTH
    if function != request.function:
        raise MalformedFrameError(
            f"function {function:#04x} does not answer function {request.function:#04x}"
        )
    if function not in READ_FUNCTIONS:
        return WRITE_RESPONSE_LENGTH
    if len(head) < 3:  # noqa: PLR2004
        return 0
    if byte_count_16bit and head[2] == 0:
        return 6 + 2 * request.count  # device, function, 2-byte count, data, CRC
    return 5 + head[2]


def parse_response(
    request: Request,
    frame: bytes,
    *,
    exceptions: Mapping[int, str] = STANDARD_EXCEPTIONS,
    byte_count_16bit: bool = False,
) -> Response:
    """Check ``frame`` against ``request`` and decode it.

    Raises :class:`CrcError`, :class:`UnexpectedDeviceError`, :class:`MalformedFrameError`
    or, for an exception response, :class:`DeviceExceptionError` with the family's meaning.
    With ``byte_count_16bit`` a read response with a two-byte byte count (documented in
    both digiLine manuals for strings) is accepted when unambiguous, and marked.
    """
    if len(frame) < EXCEPTION_FRAME_LENGTH:
        raise MalformedFrameError(f"{len(frame)} bytes cannot be a response")
    if not crc_ok(frame):
        raise CrcError(f"CRC {frame[-2:].hex()} does not match {crc16(frame[:-2]).hex()}")
    if frame[0] != request.device:
        raise UnexpectedDeviceError(
            f"answer from device {frame[0]} to a request for device {request.device}",
            expected=request.device,
            received=frame[0],
        )
    count = request.count
    if (
        request.function in READ_FUNCTIONS
        and frame[1] == request.function
        and frame[2] == 2 * count
        and len(frame) == 5 + 2 * count
    ):
        # The answer to nearly every request: big-endian words read straight from the
        # frame; everything else is read below.
        return read_answer(request, frame)
    return _other_answer(request, frame, exceptions=exceptions, byte_count_16bit=byte_count_16bit)


def _other_answer(
    request: Request, frame: bytes, *, exceptions: Mapping[int, str], byte_count_16bit: bool
) -> Response:
    """Any answer but a plain read's, its CRC and device already checked.

    An exception, a write's echo, the digiLine two-byte byte count, or a malformed frame.
    """
    tolerated = None
    if (
        byte_count_16bit
        and request.function in READ_FUNCTIONS
        and frame[1] == request.function
        and len(frame) == 6 + 2 * request.count
        and frame[2] == 0
        and frame[3] == 2 * request.count
    ):
        frame = frame[:2] + frame[3:]  # the standard form; the CRC was checked above
        tolerated = QUIRK_STRING_BYTE_COUNT
    function = frame[1]
    if function > EXCEPTION_FLAG:  # an exception to some function (0x80 itself is none)
        raise _exception_error(request, frame, function & ~EXCEPTION_FLAG, exceptions)
    undecodable = MalformedFrameError(f"cannot decode response {frame.hex(' ')}")
    if function != request.function:
        if not _decodes(frame[1:-2], is_server=False):
            raise undecodable
        raise MalformedFrameError(
            f"function {function:#04x} does not answer {request.function:#04x}"
        )
    data = frame[2:-2]  # what follows the function code; at least one byte
    if function in READ_FUNCTIONS:
        if data[0] >= len(data):  # the byte count announces more than there is
            raise undecodable
        return _read_response(request, frame, tolerated)
    if len(data) < _ADDRESS_COUNT.size:
        raise undecodable
    return _write_response(request, frame)


# A struct per register count a byte count can announce (255 bytes: 127 registers).
_WORDS: Final = tuple(struct.Struct(f">{n}H") for n in range(128))


def read_answer(request: Request, frame: bytes | bytearray | memoryview) -> Response:
    """The registers of a read's answer already checked: device, function, byte count, CRC.

    The answer to nearly every request: big-endian words (as pymodbus would decode them)
    read straight from the frame by a struct made once per count. pymodbus's decoder took
    a third of a transaction's CPU.
    """
    count = request.count
    return Response(
        device=request.device,
        function=request.function,
        address=request.address,
        count=count,
        registers=_WORDS[count].unpack_from(frame, 3),
    )


def _exception_error(
    request: Request, frame: bytes, function: int, exceptions: Mapping[int, str]
) -> GatewayError:
    """The error an exception response stands for: the device's, or a malformed frame."""
    if function != request.function:
        return MalformedFrameError(
            f"exception for function {function:#04x} while {request.function:#04x} was asked"
        )
    if len(frame) != EXCEPTION_FRAME_LENGTH:
        # A frame followed by 0x00 passes the CRC again shifted by one byte: so the
        # length is checked, not only the code read.
        return MalformedFrameError(f"{len(frame)} bytes for an exception response")
    code = frame[2]
    return DeviceExceptionError(
        device=request.device,
        function=function,
        code=code,
        meaning=exceptions.get(code, f"exception_{code}"),
    )


def _read_response(request: Request, frame: bytes, tolerated: str | None) -> Response:
    count = request.count
    if frame[2] != 2 * count or len(frame) != 5 + 2 * count:
        raise MalformedFrameError(
            f"{len(frame)} bytes with byte count {frame[2]} for {count} registers"
        )
    return Response(
        device=request.device,
        function=request.function,
        address=request.address,
        count=count,
        registers=_WORDS[count].unpack_from(frame, 3),
        tolerated=tolerated,
    )


def _write_response(request: Request, frame: bytes) -> Response:
    if len(frame) != WRITE_RESPONSE_LENGTH:  # an echo is exactly 8 bytes, nothing after it
        raise MalformedFrameError(f"{len(frame)} bytes for a write confirmation")
    address, value = _ADDRESS_COUNT.unpack_from(frame, 2)  # a value, or a count for 16
    if request.function == WRITE_SINGLE:
        echoed = (address, (value,))
        if echoed != (request.address, request.values):
            raise MalformedFrameError(f"write echo {echoed} differs from the request")
        return Response(device=request.device, function=WRITE_SINGLE, address=address, count=1)
    if (address, value) != (request.address, request.count):
        raise MalformedFrameError(
            f"write confirmation {address:#06x}/{value} differs from the request"
        )
    return Response(
        device=request.device, function=WRITE_MULTIPLE, address=address, count=request.count
    )


# --- slave side: the simulator ---------------------------------------------------------


def request_length(head: bytes) -> int:
    """Total length of a request starting with ``head``; 0 while more bytes are needed.

    Unknown function codes are assumed to be 8 bytes long, the length of every fixed-size
    request, so a slave can check their CRC and answer exception 01 as the manuals say.
    """
    if len(head) < 2:  # noqa: PLR2004
        return 0
    if head[1] != WRITE_MULTIPLE:
        return 8
    if len(head) < 7:  # noqa: PLR2004
        return 0
    return 9 + head[6]


def parse_request(frame: bytes) -> Request:
    """Decode a request frame received by a slave; CRC and structure are checked."""
    if len(frame) < 4:  # noqa: PLR2004
        raise MalformedFrameError(f"{len(frame)} bytes cannot be a request")
    if not crc_ok(frame):
        raise CrcError(f"CRC {frame[-2:].hex()} does not match {crc16(frame[:-2]).hex()}")
    device, function = frame[0], frame[1]
    known = function in READ_FUNCTIONS or function in {WRITE_SINGLE, WRITE_MULTIPLE}
    if known and len(frame) != request_length(frame):
        # Bytes after what the function needs: a slave must not act on them.
        raise MalformedFrameError(f"{len(frame)} bytes for a function {function:#04x} request")
    if function in READ_FUNCTIONS:
        # Counts outside 1..125 are read too: a slave answers them with exception 02.
        address, count = _ADDRESS_COUNT.unpack_from(frame, 2)
        return Request(device=device, function=function, address=address, count=count, frame=frame)
    if function == WRITE_SINGLE:
        address, value = _ADDRESS_COUNT.unpack_from(frame, 2)
        return Request(
            device=device, function=function, address=address, count=1, values=(value,), frame=frame
        )
    if function == WRITE_MULTIPLE:
        address, count, byte_count = _WRITE_HEAD.unpack_from(frame, 2)
        # The words the byte count covers (its length checked above): half of it, rounded down.
        values = _WORDS[byte_count // 2].unpack_from(frame, 7)
        if byte_count != 2 * count or len(values) != count:
            raise MalformedFrameError(f"write of {count} registers with byte count {byte_count}")
        return Request(
            device=device,
            function=function,
            address=address,
            count=count,
            values=values,
            frame=frame,
        )
    if not _decodes(frame[1:-2], is_server=True):
        raise MalformedFrameError(f"cannot decode request {frame.hex(' ')}")
    raise MalformedFrameError(f"function {function:#04x} is not supported")


def read_response(
    device: int, function: int, registers: Sequence[int], *, byte_count_16bit: bool = False
) -> bytes:
    """A slave's answer to a read; optionally with the digiLine two-byte byte count."""
    function = READ_HOLDING if function == READ_HOLDING else READ_INPUT
    count = len(registers)
    frame = _frame(device, function, bytes((2 * count,)) + _WORDS[count].pack(*registers))
    if not byte_count_16bit:
        return frame
    body = frame[:2] + b"\x00" + frame[2:-2]
    return body + crc16(body)


def write_single_response(device: int, address: int, value: int) -> bytes:
    """A slave's echo of a function 06 write."""
    return _frame(device, WRITE_SINGLE, _ADDRESS_COUNT.pack(address, value))


def write_multiple_response(device: int, address: int, count: int) -> bytes:
    """A slave's confirmation of a function 16 write."""
    return _frame(device, WRITE_MULTIPLE, _ADDRESS_COUNT.pack(address, count))


def exception_response(device: int, function: int, code: int) -> bytes:
    """A slave's exception answer."""
    return _frame(device, function | EXCEPTION_FLAG, bytes((code,)))
