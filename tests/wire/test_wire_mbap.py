"""The MBAP header (Modbus Messaging on TCP/IP Implementation Guide V1.0b, 3.1.3), without I/O."""

from __future__ import annotations

import pytest

from gateway.errors import (
    ConverterNoAnswerError,
    ConverterPathError,
    DeviceExceptionError,
    MalformedFrameError,
    UnexpectedDeviceError,
)
from gateway.wire import frames, mbap

# The S10 manual's example (2, "Data request"): temperature at 0x2620, and its answer 20.25;
# as Modbus TCP: transaction 1, protocol 0, length 6 (the unit id and the PDU), unit 1.
READ_RTU = bytes.fromhex("01 03 26 20 00 02 ce 89")
ANSWER_RTU = bytes.fromhex("01 03 04 00 00 41 a2 4b da")
READ_TCP = bytes.fromhex("00 01 00 00 00 06 01 03 26 20 00 02")


def test_the_manuals_request_as_modbus_tcp() -> None:
    assert frames.read_request(1, 0x2620, 2).frame == READ_RTU
    assert mbap.from_rtu(1, READ_RTU) == READ_TCP


def test_decode_cuts_one_frame_and_says_what_it_took() -> None:
    answer = mbap.encode(0xFFFF, 1, bytes.fromhex("03 04 00 00 41 a2"))
    decoded = mbap.decode(answer + READ_TCP[:3])
    assert decoded is not None
    frame, used = decoded
    assert (frame.transaction, frame.unit, frame.pdu.hex(" ")) == (0xFFFF, 1, "03 04 00 00 41 a2")
    assert used == len(answer)
    assert mbap.to_rtu(frame.unit, frame.pdu) == ANSWER_RTU


@pytest.mark.parametrize("cut", range(len(READ_TCP)))
def test_a_frame_cut_short_waits_for_more(cut: int) -> None:
    assert mbap.decode(READ_TCP[:cut]) is None


def test_transaction_ids_wrap_at_16_bits() -> None:
    assert mbap.encode(0x1_0002, 1, b"\x03")[:2] == b"\x00\x02"


@pytest.mark.parametrize(
    ("header", "message"),
    [
        ("00 01 00 01 00 06 01", "MBAP protocol id 1, not 0"),
        ("00 01 00 00 00 01 01", "MBAP length 1 outside 2..254"),
        ("00 01 00 00 01 00 01", "MBAP length 256 outside 2..254"),
    ],
)
def test_a_header_that_cannot_start_a_modbus_frame(header: str, message: str) -> None:
    with pytest.raises(MalformedFrameError, match=message):
        mbap.decode(bytes.fromhex(header))


REQUEST = frames.read_request(1, 0x2620, 2)


@pytest.mark.parametrize(
    ("pdu", "error", "message"),
    [
        ("83 0b", ConverterNoAnswerError, "exception 0B for device 1 function 0x03 at 0x2620"),
        ("83 0a", ConverterPathError, "exception 0A .*: gateway path unavailable"),
        ("83 02", DeviceExceptionError, "exception 02 \\(illegal_address\\)"),
        ("03 04 00 00 41", MalformedFrameError, "cannot decode response 01 03 04 00 00 41"),
    ],
)
def test_answers_that_are_not_values(pdu: str, error: type[Exception], message: str) -> None:
    frame = mbap.MbapFrame(transaction=1, unit=1, pdu=bytes.fromhex(pdu))
    with pytest.raises(error, match=message):
        mbap.parse_answer(REQUEST, frame, where="tcp://converter:502")


def test_an_answer_of_another_unit() -> None:
    frame = mbap.MbapFrame(transaction=1, unit=2, pdu=ANSWER_RTU[1:-2])
    with pytest.raises(UnexpectedDeviceError, match="unit 2 answered a request for device 1"):
        mbap.parse_answer(REQUEST, frame, where="tcp://converter:502")


def test_an_answer_is_read_as_the_serial_one_is() -> None:
    frame = mbap.MbapFrame(transaction=1, unit=1, pdu=ANSWER_RTU[1:-2])
    assert mbap.parse_answer(REQUEST, frame, where="").registers == (0x0000, 0x41A2)
