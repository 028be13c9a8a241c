"""RTU frames: building, matching and classifying, without I/O."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from gateway.errors import (
    CrcError,
    DeviceExceptionError,
    EncodeError,
    MalformedFrameError,
    UnexpectedDeviceError,
)
from gateway.wire import frames

TEMPERATURE_READ = frames.read_request(1, 0x2620, 2)
TEMPERATURE_ANSWER = bytes.fromhex("01 03 04 00 00 41 A2 4B DA")  # S10 manual 2.6.2


def with_crc(hex_text: str) -> bytes:
    body = bytes.fromhex(hex_text)
    return body + frames.crc16(body)


def test_crc_is_low_byte_first() -> None:
    assert frames.crc16(bytes.fromhex("01 03 00 00 00 05")) == bytes.fromhex("85 C9")
    assert frames.crc_ok(TEMPERATURE_ANSWER)
    assert not frames.crc_ok(TEMPERATURE_ANSWER[:-1] + b"\x00")


def test_read_request_bytes() -> None:
    assert TEMPERATURE_READ.frame == bytes.fromhex("01 03 26 20 00 02 CE 89")
    assert frames.read_request(1, 0x2620, 2, function=4).frame[:2] == b"\x01\x04"


def test_parse_a_read_response() -> None:
    response = frames.parse_response(TEMPERATURE_READ, TEMPERATURE_ANSWER)
    assert response.registers == (0x0000, 0x41A2)
    assert response.tolerated is None


@pytest.mark.parametrize(
    ("build", "message"),
    [
        (lambda: frames.read_request(0, 0, 1), "device address 0"),
        (lambda: frames.read_request(248, 0, 1), "device address 248"),
        (lambda: frames.read_request(1, 0, 126), "cannot read 126"),
        (lambda: frames.read_request(1, 0, 0), "cannot read 0"),
        (lambda: frames.read_request(1, 0xFFFF, 2), "outside the map"),
        (lambda: frames.read_request(1, 0, 1, function=6), "does not read"),
        (lambda: frames.write_single_request(1, 0, 0x10000), "outside 0..65535"),
        (lambda: frames.write_multiple_request(1, 0, [0] * 124), "cannot write 124"),
    ],
)
def test_bad_requests_are_refused_before_bytes_exist(build: object, message: str) -> None:
    with pytest.raises(EncodeError, match=message):
        build()  # type: ignore[operator]


def test_broadcast_writes_are_allowed_reads_are_not() -> None:
    assert frames.write_single_request(0, 0x0305, 10).is_broadcast
    with pytest.raises(EncodeError):
        frames.read_request(0, 0, 1)


def test_write_request_picks_06_or_16() -> None:
    assert frames.write_request(1, 0x3009, [1]).function == frames.WRITE_SINGLE
    assert frames.write_request(1, 0x2013, [0, 0x41A2]).function == frames.WRITE_MULTIPLE


def test_corrupted_crc_is_a_crc_error() -> None:
    corrupted = bytearray(TEMPERATURE_ANSWER)
    corrupted[5] ^= 0x01
    with pytest.raises(CrcError):
        frames.parse_response(TEMPERATURE_READ, bytes(corrupted))


def test_answer_from_another_device_is_attributed_to_nobody() -> None:
    other = with_crc("02 03 04 00 00 41 A2")
    with pytest.raises(UnexpectedDeviceError) as caught:
        frames.parse_response(TEMPERATURE_READ, other)
    assert (caught.value.expected, caught.value.received) == (1, 2)


def test_stale_answer_with_wrong_length_is_rejected() -> None:
    # A late answer to an earlier one-register read must not pass for this one.
    stale = with_crc("01 03 02 07 E4")
    with pytest.raises(MalformedFrameError, match="byte count 2 for 2 registers"):
        frames.parse_response(TEMPERATURE_READ, stale)


def test_answer_to_another_function_is_rejected() -> None:
    echo = with_crc("01 06 26 20 00 02")
    with pytest.raises(MalformedFrameError, match="does not answer"):
        frames.parse_response(TEMPERATURE_READ, echo)


def test_exception_response_carries_the_family_meaning() -> None:
    request = frames.write_single_request(1, 0x2345, 1)
    answer = bytes.fromhex("01 86 02 C3 A1")  # every manual's exception example
    with pytest.raises(DeviceExceptionError) as caught:
        frames.parse_response(request, answer, exceptions={2: "illegal_address"})
    error = caught.value
    assert (error.device, error.function, error.code, error.meaning) == (1, 6, 2, "illegal_address")


def test_exception_for_another_function_is_malformed() -> None:
    with pytest.raises(MalformedFrameError, match="exception for function"):
        frames.parse_response(TEMPERATURE_READ, frames.exception_response(1, 6, 2))


def test_write_echo_must_match() -> None:
    request = frames.write_single_request(1, 0x3009, 1)
    assert frames.parse_response(request, request.frame).address == 0x3009
    with pytest.raises(MalformedFrameError, match="echo"):
        frames.parse_response(request, frames.write_single_response(1, 0x3009, 2))
    multi = frames.write_multiple_request(1, 0x2013, [0, 0x41A2])
    assert frames.parse_response(multi, frames.write_multiple_response(1, 0x2013, 2)).count == 2
    with pytest.raises(MalformedFrameError, match="confirmation"):
        frames.parse_response(multi, frames.write_multiple_response(1, 0x2013, 1))


# --- the digiLine two-byte byte count ---------------------------------------------------

DESCRIPTION_READ = frames.read_request(1, 0x021E, 7)
QUIRK_ANSWER = bytes.fromhex("01 03 00 0E 41 6E 6C 61 67 65 20 4E 6F 72 64 00 00 AA C5 DF")


def test_two_byte_byte_count_is_refused_by_default() -> None:
    with pytest.raises(MalformedFrameError):
        frames.parse_response(DESCRIPTION_READ, QUIRK_ANSWER)


def test_two_byte_byte_count_is_tolerated_and_marked_where_documented() -> None:
    response = frames.parse_response(DESCRIPTION_READ, QUIRK_ANSWER, byte_count_16bit=True)
    assert response.tolerated == frames.QUIRK_STRING_BYTE_COUNT
    assert response.registers[0] == 0x416E
    assert len(response.registers) == 7


def test_ambiguous_two_byte_count_is_not_guessed() -> None:
    # High byte zero but a low byte that does not equal 2 x quantity: not the quirk.
    wrong = with_crc("01 03 00 0C" + " 00" * 14)
    with pytest.raises(MalformedFrameError):
        frames.parse_response(DESCRIPTION_READ, wrong, byte_count_16bit=True)


def test_standard_answers_still_parse_with_the_tolerance_enabled() -> None:
    standard = frames.read_response(1, 3, [0x416E] * 7)
    response = frames.parse_response(DESCRIPTION_READ, standard, byte_count_16bit=True)
    assert response.tolerated is None


# --- lengths from the first bytes -------------------------------------------------------


def test_response_length_from_the_head() -> None:
    assert frames.response_length(TEMPERATURE_READ, b"\x01") == 0
    assert frames.response_length(TEMPERATURE_READ, b"\x01\x03") == 0
    assert frames.response_length(TEMPERATURE_READ, b"\x01\x03\x04") == 9
    assert frames.response_length(TEMPERATURE_READ, b"\x01\x83") == 5
    write = frames.write_single_request(1, 0x3009, 1)
    assert frames.response_length(write, b"\x01\x06") == 8
    assert frames.response_length(DESCRIPTION_READ, b"\x01\x03\x00", byte_count_16bit=True) == 20
    with pytest.raises(MalformedFrameError):
        frames.response_length(TEMPERATURE_READ, b"\x01\x10")


# --- slave side -------------------------------------------------------------------------


def test_parse_requests_of_each_function() -> None:
    read = frames.parse_request(bytes.fromhex("01 03 26 20 00 02 CE 89"))
    assert (read.device, read.function, read.address, read.count) == (1, 3, 0x2620, 2)
    single = frames.parse_request(bytes.fromhex("01 06 28 40 07 E5 42 05"))
    assert (single.address, single.values) == (0x2840, (2021,))
    multi = frames.parse_request(frames.write_multiple_request(3, 0x2013, [0, 0x41A2]).frame)
    assert (multi.device, multi.count, multi.values) == (3, 2, (0, 0x41A2))


def test_request_errors_on_the_slave_side() -> None:
    with pytest.raises(CrcError):
        frames.parse_request(bytes.fromhex("01 03 26 20 00 02 CE 88"))
    with pytest.raises(MalformedFrameError, match="not supported"):
        frames.parse_request(with_crc("01 2B 0E 01 00"))
    lying = with_crc("01 10 20 13 00 02 02 00 00")
    with pytest.raises(MalformedFrameError):
        frames.parse_request(lying)


def test_request_length_from_the_head() -> None:
    assert frames.request_length(b"\x01") == 0
    assert frames.request_length(b"\x01\x03") == 8
    assert frames.request_length(bytes.fromhex("01 10 20 13 00 02")) == 0
    assert frames.request_length(bytes.fromhex("01 10 20 13 00 02 04")) == 13


@given(
    device=st.integers(1, 247),
    address=st.integers(0, 0xFF00),
    registers=st.lists(st.integers(0, 0xFFFF), min_size=1, max_size=125),
    function=st.sampled_from([3, 4]),
    quirk=st.booleans(),
)
def test_any_read_round_trips_between_slave_and_master(
    device: int,
    address: int,
    registers: list[int],
    function: int,
    quirk: bool,  # noqa: FBT001
) -> None:
    request = frames.read_request(device, address, len(registers), function=function)
    assert frames.parse_request(request.frame) == request
    answer = frames.read_response(device, function, registers, byte_count_16bit=quirk)
    assert frames.response_length(request, answer[:3], byte_count_16bit=quirk) == len(answer)
    response = frames.parse_response(request, answer, byte_count_16bit=quirk)
    assert response.registers == tuple(registers)
    assert (response.tolerated is not None) == quirk


@given(data=st.binary(min_size=0, max_size=64))
def test_random_bytes_never_pass_for_an_answer_by_accident(data: bytes) -> None:
    try:
        response = frames.parse_response(TEMPERATURE_READ, data)
    except (CrcError, UnexpectedDeviceError, MalformedFrameError, DeviceExceptionError):
        return
    # Only a frame with a valid CRC, the right device, function and length gets here.
    assert frames.crc_ok(data)
    assert data[:3] == b"\x01\x03\x04"
    assert len(response.registers) == 2
