"""Requests on a client's socket: Modbus TCP (MBAP) or RTU frames, cut from the byte stream.

Modbus TCP is decoded and encoded with pymodbus's ``FramerSocket``; its header is checked
here first, because that framer waits for more bytes on a wrong protocol id or a length
beyond any PDU (a client that sends such a header would hold its connection for ever).
RTU frames are cut with the gateway's own request lengths and CRC (``wire.frames``, as the
simulator does): pymodbus's RTU framer skips a request of an unknown function code as
garbage, where a Modbus server must answer it with exception 01.
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

    def decode(self, data: bytes) -> ClientFrame | None:
        """The first request in ``data``; ``None`` while more bytes are needed."""

    def encode(self, pdu: bytes, unit: int, transaction: int) -> bytes:
        """An answer PDU framed for the client."""


class TcpFramer:
    """Modbus TCP: the MBAP header, then the PDU; no CRC (TCP checks the bytes)."""

    def __init__(self) -> None:
        """One pymodbus framer per connection (it keeps nothing between frames)."""
        self._framer = FramerSocket(DecodePDU(is_server=True))

    def decode(self, data: bytes) -> ClientFrame | None:
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

    def __init__(self) -> None:
        """Answers get their unit id and CRC from pymodbus's RTU framer."""
        self._framer = FramerRTU(DecodePDU(is_server=True))

    def decode(self, data: bytes) -> ClientFrame | None:
        """The first request in ``data``; a frame that fails its CRC raises FramingError."""
        need = frames.request_length(data)
        if need == 0 or len(data) < need:
            if len(data) >= MAX_RTU_FRAME:
                raise FramingError(f"{len(data)} bytes and no request")
            return None
        frame = data[:need]
        if not frames.crc_ok(frame):
            # A serial slave ignores a frame that fails its CRC; on a socket the stream
            # has no silence to resynchronise on, so the connection ends.
            raise FramingError(f"RTU request {frame.hex(' ')} fails its CRC")
        return ClientFrame(used=need, unit=frame[0], transaction=0, pdu=frame[1:-2])

    def encode(self, pdu: bytes, unit: int, transaction: int) -> bytes:  # noqa: ARG002
        """The answer as an RTU frame with the request's unit id and a CRC."""
        return bytes(self._framer.encode(pdu, unit, 0))


def framer_for(framing: Framing) -> Framer:
    """The framer of a listen address's framing."""
    return RtuFramer() if framing == "rtu" else TcpFramer()
