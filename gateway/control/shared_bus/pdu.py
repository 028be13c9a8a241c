"""Other masters' requests as Modbus PDUs: checked, turned into line requests, answered.

Pure: no I/O. A request a client sends is checked as a Modbus server checks it (function,
length, quantity, address range) before anything is framed for the line; the answer it
gets is the device's answer PDU as the device sent it, or an exception PDU.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from typing import TYPE_CHECKING, Final

from gateway.wire import frames

if TYPE_CHECKING:
    from gateway.errors import DeviceExceptionError

# Modbus application protocol 7: the exception codes the gateway itself answers.
ILLEGAL_FUNCTION: Final = 0x01
ILLEGAL_ADDRESS: Final = 0x02
ILLEGAL_VALUE: Final = 0x03
DEVICE_FAILURE: Final = 0x04  # the gateway cannot do it (the flash ledger cannot count a write)
DEVICE_BUSY: Final = 0x06  # no bus time for the request now
PATH_UNAVAILABLE: Final = 0x0A  # no device answers to that unit id, or its bus is down
TARGET_FAILED: Final = 0x0B  # the device did not answer (timeout, CRC, offline)

# The function codes every family documents (03 and 04 read the same map, 06 and 16
# write); no family documents 08 (diagnostics), so it is refused like any other.
READ_FUNCTIONS: Final = frames.READ_FUNCTIONS
WRITE_FUNCTIONS: Final = frozenset({frames.WRITE_SINGLE, frames.WRITE_MULTIPLE})


class RequestRefusedError(Exception):
    """A client's request the gateway answers itself, with a Modbus exception code."""

    def __init__(self, code: int, reason: str, *, label: str = "invalid_request") -> None:
        """Keep the code for the answer, the reason for the log, a label for the metrics."""
        self.code = code
        self.reason = reason
        self.label = label
        super().__init__(f"exception {code:02X}: {reason}")


@dataclass(frozen=True, slots=True, kw_only=True)
class ClientRequest:
    """What a client asks: a read or a write of registers."""

    function: int
    address: int
    count: int
    values: tuple[int, ...] = ()

    @property
    def is_write(self) -> bool:
        """Whether it writes registers."""
        return self.function in WRITE_FUNCTIONS

    @property
    def last(self) -> int:
        """The last register it touches."""
        return self.address + self.count - 1


def parse_request(pdu: bytes) -> ClientRequest:
    """The request a PDU holds, or :class:`RequestRefusedError` with the code to answer."""
    if not pdu:
        raise RequestRefusedError(ILLEGAL_FUNCTION, "empty request")
    function = pdu[0]
    if function in READ_FUNCTIONS:
        return _read(function, pdu)
    if function == frames.WRITE_SINGLE:
        if len(pdu) != 5:  # noqa: PLR2004 - function, address, value
            raise RequestRefusedError(ILLEGAL_VALUE, f"{len(pdu)} bytes for a one-register write")
        address, value = struct.unpack(">HH", pdu[1:5])
        return ClientRequest(function=function, address=address, count=1, values=(value,))
    if function == frames.WRITE_MULTIPLE:
        return _write_multiple(pdu)
    raise RequestRefusedError(ILLEGAL_FUNCTION, f"function {function:#04x} is not served")


def _read(function: int, pdu: bytes) -> ClientRequest:
    if len(pdu) != 5:  # noqa: PLR2004 - function, address, quantity
        raise RequestRefusedError(ILLEGAL_VALUE, f"{len(pdu)} bytes for a read")
    address, count = struct.unpack(">HH", pdu[1:5])
    if not 1 <= count <= frames.MAX_READ_REGISTERS:
        raise RequestRefusedError(ILLEGAL_VALUE, f"read of {count} registers")
    _check_range(address, count)
    return ClientRequest(function=function, address=address, count=count)


def _write_multiple(pdu: bytes) -> ClientRequest:
    if len(pdu) < 6:  # noqa: PLR2004 - function, address, quantity, byte count
        raise RequestRefusedError(ILLEGAL_VALUE, f"{len(pdu)} bytes for a write")
    address, count = struct.unpack(">HH", pdu[1:5])
    byte_count = pdu[5]
    if not 1 <= count <= frames.MAX_WRITE_REGISTERS or byte_count != 2 * count:
        raise RequestRefusedError(
            ILLEGAL_VALUE, f"write of {count} registers with byte count {byte_count}"
        )
    if len(pdu) != 6 + byte_count:
        raise RequestRefusedError(ILLEGAL_VALUE, f"{len(pdu)} bytes for {count} registers")
    _check_range(address, count)
    values = struct.unpack(f">{count}H", pdu[6:])
    return ClientRequest(
        function=frames.WRITE_MULTIPLE, address=address, count=count, values=values
    )


def _check_range(address: int, count: int) -> None:
    if address + count - 1 > frames.MAX_ADDRESS:
        raise RequestRefusedError(
            ILLEGAL_ADDRESS, f"{count} registers from {address:#06x} pass the end of the map"
        )


def line_request(request: ClientRequest, device_address: int) -> frames.Request:
    """The request as it goes on the line to the device (a well-formed frame by construction)."""
    if request.function in READ_FUNCTIONS:
        return frames.read_request(
            device_address, request.address, request.count, function=request.function
        )
    if request.function == frames.WRITE_SINGLE:
        return frames.write_single_request(device_address, request.address, request.values[0])
    return frames.write_multiple_request(device_address, request.address, request.values)


def answer_pdu(request: ClientRequest, response: frames.Response) -> bytes:
    """The device's answer PDU, byte for byte as it sent it.

    The line parsed and checked the answer against the request (CRC, length, echo), and
    an answer is determined by what was parsed: a read's registers, in the form the
    device sent them (the digiLine two-byte byte count included), or a write's echo.
    """
    if request.function in READ_FUNCTIONS:
        frame = frames.read_response(
            response.device,
            request.function,
            response.registers,
            byte_count_16bit=response.tolerated == frames.QUIRK_STRING_BYTE_COUNT,
        )
    elif request.function == frames.WRITE_SINGLE:
        frame = frames.write_single_response(response.device, request.address, request.values[0])
    else:
        frame = frames.write_multiple_response(response.device, request.address, request.count)
    return frame[1:-2]


def cached_read_pdu(request: ClientRequest, registers: tuple[int, ...]) -> bytes:
    """A read answered with registers the device sent earlier (standard form)."""
    return frames.read_response(1, request.function, registers)[1:-2]


def device_exception_pdu(error: DeviceExceptionError) -> bytes:
    """The device's exception answer, as it sent it."""
    return bytes((error.function | frames.EXCEPTION_FLAG, error.code & 0xFF))


def exception_pdu(function: int, code: int) -> bytes:
    """An exception the gateway answers itself."""
    return bytes(((function & 0x7F) | frames.EXCEPTION_FLAG, code))
