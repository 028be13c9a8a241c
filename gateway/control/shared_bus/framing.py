"""Requests on a client's socket: Modbus TCP (MBAP) or RTU frames, cut from the byte stream.

Modbus TCP is decoded and encoded with pymodbus's ``FramerSocket``; its header is checked
here first, because that framer waits for more bytes on a wrong protocol id or a length
beyond any PDU (a client that sends such a header would hold its connection for ever).
RTU frames are cut by the lengths the Modbus application protocol gives each public
function, checked by their CRC: pymodbus's RTU framer skips a request of an unknown
function code as garbage, where a Modbus server must answer it with exception 01. Where
the length is unknown (a private function, a sub-function of 0x2B other than 0x0E) or the
bytes at the function's length fail the CRC (a frame of another length), the frame ends
where a serial line ends it: at a silence (``RTU_SILENCE_S`` without a byte).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Final, Protocol

from pymodbus.framer import FramerRTU, FramerSocket
from pymodbus.pdu import DecodePDU

from gateway.errors import FrameError
from gateway.wire import frames

if TYPE_CHECKING:
    from gateway.config.shared_bus import Framing

MBAP_HEADER: Final = 7  # transaction id, protocol id, length, unit id
MAX_PDU: Final = 253  # Modbus application protocol 4.1
MAX_RTU_FRAME: Final = 256  # Modbus over serial line 2.5.1
# Bytes held without a frame before the stream is given up: a frame ended by a silence
# may be longer than RTU allows (it gets its exception), two such are not one.
MAX_RTU_HELD: Final = 2 * MAX_RTU_FRAME
# No byte for this long ends a frame whose length is unknown. A client (or a converter)
# sends a frame in one go: a LAN splits none of it this long; its next request follows
# our answer, so the silence costs nothing to a client that waits for its answers.
RTU_SILENCE_S: Final = 0.05
MIN_RTU_FRAME: Final = 4  # unit, function, CRC

# Modbus application protocol 6: the request of each public function, as an RTU frame
# (unit, PDU, CRC). Fixed lengths, or where a byte counts the data that follows.
_FIXED_LENGTH: Final = {
    0x01: 8, 0x02: 8, 0x03: 8, 0x04: 8, 0x05: 8, 0x06: 8,  # address, quantity or value
    0x07: 4, 0x0B: 4, 0x0C: 4, 0x11: 4,  # no data: exception status, event counter and
    #                                      log, report server id
    0x08: 8,  # diagnostics: sub-function and one word of data
    0x16: 10,  # mask write: address, AND mask, OR mask
    0x18: 6,  # read FIFO queue: address
}  # fmt: skip
_BYTE_COUNT_AT: Final = {0x0F: 6, 0x10: 6, 0x14: 2, 0x15: 2, 0x17: 10}
MEI: Final = 0x2B
READ_DEVICE_ID: Final = 0x0E  # MEI type of 0x2B: unit, 2B, 0E, read code, object id, CRC
READ_DEVICE_ID_LENGTH: Final = 7


class FramingError(FrameError):
    """Bytes on a client's socket that no framing can resynchronise on: close it."""


@dataclass(frozen=True, slots=True, kw_only=True)
class ClientFrame:
    """One request cut from the stream: how many bytes it took, its unit, its PDU."""

    used: int
    unit: int
    transaction: int
    pdu: bytes


class Framer(Protocol):
    """Cuts requests from a socket's bytes and frames answers for it."""

    # How long a silence ends a frame whose length is unknown; None: lengths are known.
    silence_s: float | None
    min_frame: int  # the bytes of the shortest request: a read of N times it holds N at most

    def decode(self, data: bytes, *, silent: bool = False) -> ClientFrame | None:
        """The first request in ``data``; ``None`` while more bytes (or a silence) are needed.

        ``silent``: no byte came for ``silence_s`` after ``data``: its end ends a frame.
        """

    def encode(self, pdu: bytes, unit: int, transaction: int) -> bytes:
        """An answer PDU framed for the client."""


class TcpFramer:
    """Modbus TCP: the MBAP header, then the PDU; no CRC (TCP checks the bytes)."""

    silence_s: float | None = None  # the header gives every frame's length
    min_frame: int = MBAP_HEADER + 1  # the header and a function code

    def __init__(self) -> None:
        """One pymodbus framer per connection (it keeps nothing between frames)."""
        self._framer = FramerSocket(DecodePDU(is_server=True))

    def decode(self, data: bytes, *, silent: bool = False) -> ClientFrame | None:  # noqa: ARG002
        """The first request in ``data``; a header that cannot be one raises FramingError."""
        if len(data) < MBAP_HEADER:
            return None
        protocol = int.from_bytes(data[2:4], "big")
        length = int.from_bytes(data[4:6], "big")
        if protocol != 0:
            raise FramingError(f"MBAP protocol id {protocol}, not 0 (Modbus)")
        if not 2 <= length <= MAX_PDU + 1:  # noqa: PLR2004 - the unit id and a function code
            raise FramingError(f"MBAP length {length} outside 2..{MAX_PDU + 1}")
        if len(data) < 6 + length:
            return None
        # pymodbus takes one byte more after a two-byte length when exactly one follows;
        # the frame ends where its length says, so the framer sees just the frame.
        used, unit, transaction, pdu = self._framer.decode(data[: 6 + length])
        return ClientFrame(used=used, unit=unit, transaction=transaction, pdu=bytes(pdu))

    def encode(self, pdu: bytes, unit: int, transaction: int) -> bytes:
        """The answer with the request's transaction id and unit id."""
        return bytes(self._framer.encode(pdu, unit, transaction))


class RtuFramer:
    """RTU frames over TCP: unit id, PDU, CRC, as a serial converter passes them."""

    silence_s: float | None = RTU_SILENCE_S
    min_frame: int = MIN_RTU_FRAME

    def __init__(self) -> None:
        """Answers get their unit id and CRC from pymodbus's RTU framer."""
        self._framer = FramerRTU(DecodePDU(is_server=True))

    def decode(self, data: bytes, *, silent: bool = False) -> ClientFrame | None:
        """The first request in ``data``; bytes that cannot hold one raise FramingError.

        A frame of a known length that passes its CRC is cut at once (a client may send the
        next without waiting); any other ends at the silence after it, and is then the
        whole of ``data``.
        """
        need = request_length(data)
        if need and len(data) >= need and frames.crc_ok(data[:need]):
            return _frame(data[:need])
        if silent:
            if len(data) < MIN_RTU_FRAME or not frames.crc_ok(data):
                # A serial slave ignores a frame that fails its CRC; on a socket such
                # bytes mean the two ends no longer agree where frames begin.
                raise FramingError(f"RTU request {data.hex(' ')} fails its CRC")
            return _frame(data)
        if len(data) > MAX_RTU_HELD:
            raise FramingError(f"{len(data)} bytes and no request")
        return None

    def encode(self, pdu: bytes, unit: int, transaction: int) -> bytes:  # noqa: ARG002
        """The answer as an RTU frame with the request's unit id and a CRC."""
        return bytes(self._framer.encode(pdu, unit, 0))


def _frame(frame: bytes) -> ClientFrame:
    return ClientFrame(used=len(frame), unit=frame[0], transaction=0, pdu=frame[1:-2])


def request_length(head: bytes) -> int:
    """The length of the RTU request ``head`` starts, by its function; 0: not known (yet)."""
    if len(head) < 2:  # noqa: PLR2004 - unit and function
        return 0
    function = head[1]
    if (fixed := _FIXED_LENGTH.get(function)) is not None:
        return fixed
    if (at := _BYTE_COUNT_AT.get(function)) is not None:
        return at + 1 + head[at] + 2 if len(head) > at else 0
    if function == MEI and len(head) > 2 and head[2] == READ_DEVICE_ID:  # noqa: PLR2004
        return READ_DEVICE_ID_LENGTH
    return 0


def framer_for(framing: Framing) -> Framer:
    """The framer of a listen address's framing."""
    return RtuFramer() if framing == "rtu" else TcpFramer()
