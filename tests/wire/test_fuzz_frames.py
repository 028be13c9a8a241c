"""Fuzzing the frame parser, master and slave side, against an oracle written from the manuals.

:mod:`gateway.wire.frames` leans on pymodbus's decoders, which swallow their own
``IndexError``/``struct.error`` on garbage (a log line and ``None``) and ignore bytes after
what they decode. These tests throw random bytes and mutated valid frames
(bit flips, truncation, extension, inserted and deleted bytes, another device, another
function, a wrong byte count, the digiLine two-byte byte count with the tolerance on and
off) at :func:`frames.parse_response`, :func:`frames.response_length`,
:func:`frames.parse_request` and :func:`frames.request_length`, and compare every verdict
with a small oracle that restates the Modbus RTU rules (length, CRC, device, function,
byte count, echo) independently of the code under test. So a frame is accepted exactly
when it is a correct answer, and every rejection is the documented error class.

``test_frames.py`` holds the worked examples and the read round trip; this file adds
the adversarial inputs. Example counts are in each ``@fuzz(...)``; ``FUZZ_SCALE``
multiplies them (see :mod:`tests.fuzzing`).
"""

from __future__ import annotations

from typing import Final

import pytest
from hypothesis import given
from hypothesis import strategies as st

from gateway.errors import (
    CrcError,
    DeviceExceptionError,
    FrameError,
    GatewayError,
    MalformedFrameError,
    UnexpectedDeviceError,
)
from gateway.wire import frames
from tests.fuzzing import FUNCTIONS, fuzz, good_answers, mutations, requests

MASTER_ERRORS: Final = (CrcError, UnexpectedDeviceError, MalformedFrameError, DeviceExceptionError)
MIN_FRAME: Final = 5  # device, function, one byte, CRC: the shortest answer (an exception)

# --- the oracle: what the manuals say a master and a slave must accept -------------------


def _registers(data: bytes) -> tuple[int, ...]:
    return tuple(int.from_bytes(data[i : i + 2], "big") for i in range(0, len(data), 2))


def answer_oracle(  # noqa: PLR0911 - one return per rule of the protocol
    request: frames.Request, frame: bytes, *, quirk: bool
) -> type[GatewayError] | tuple[int, ...]:
    """The error class a master must raise for ``frame``, or the registers it carries.

    Checked in the order a strict master can know them: length, CRC, device, then what
    the function code promises (exception: 5 bytes; read: byte count 2 x quantity, or the
    digiLine two-byte count where tolerated; write: the 8-byte echo of the request).
    """
    if len(frame) < MIN_FRAME:
        return MalformedFrameError
    if not frames.crc_ok(frame):
        return CrcError
    if frame[0] != request.device:
        return UnexpectedDeviceError
    function, count = request.function, request.count
    if frame[1] == function | frames.EXCEPTION_FLAG:
        return (
            DeviceExceptionError
            if len(frame) == frames.EXCEPTION_FRAME_LENGTH
            else MalformedFrameError
        )
    if frame[1] != function:
        return MalformedFrameError
    if function in frames.READ_FUNCTIONS:
        if len(frame) == 5 + 2 * count and frame[2] == 2 * count:
            return _registers(frame[3:-2])
        if quirk and len(frame) == 6 + 2 * count and frame[2] == 0 and frame[3] == 2 * count:
            return _registers(frame[4:-2])
        return MalformedFrameError
    # 06 echoes address and value, 16 confirms address and quantity: bytes 2..5 of the request.
    if len(frame) != frames.WRITE_RESPONSE_LENGTH or frame[2:6] != request.frame[2:6]:
        return MalformedFrameError
    return ()


def request_oracle(frame: bytes) -> type[FrameError] | tuple[int, int, int, int, tuple[int, ...]]:
    """The error class a slave must raise, or (device, function, address, count, values).

    Reads take any quantity (the slave answers a bad one with exception 02); a write of
    many registers must carry a byte count of 2 x quantity and exactly that many bytes.
    """
    if len(frame) < 4:
        return MalformedFrameError
    if not frames.crc_ok(frame):
        return CrcError
    device, function = frame[0], frame[1]
    head = _registers(frame[2:6]) if len(frame) >= 6 else ()
    if function in frames.READ_FUNCTIONS and len(frame) == frames.READ_REQUEST_LENGTH:
        return device, function, head[0], head[1], ()
    if function == frames.WRITE_SINGLE and len(frame) == frames.READ_REQUEST_LENGTH:
        return device, function, head[0], 1, (head[1],)
    if function == frames.WRITE_MULTIPLE and len(frame) >= 9:
        byte_count = frame[6]
        if len(frame) == 9 + byte_count and byte_count == 2 * head[1]:
            return device, function, head[0], head[1], _registers(frame[7:-2])
    return MalformedFrameError


def judge_answer(
    request: frames.Request, frame: bytes, *, quirk: bool
) -> type[GatewayError] | tuple[int, ...]:
    """What :func:`frames.parse_response` does with ``frame``: its error class or registers.

    Any exception outside the gateway's documented frame errors fails the test here.
    """
    try:
        response = frames.parse_response(request, frame, byte_count_16bit=quirk)
    except MASTER_ERRORS as exc:
        return type(exc)
    assert response.device == request.device
    assert response.function == request.function
    assert response.count == request.count
    if request.function in frames.READ_FUNCTIONS:
        assert len(response.registers) == request.count
        assert (response.tolerated is not None) == (frame[2] == 0)
    return response.registers


def judge_request(frame: bytes) -> type[FrameError] | tuple[int, int, int, int, tuple[int, ...]]:
    """What :func:`frames.parse_request` does with ``frame``: its error class or the fields."""
    try:
        request = frames.parse_request(frame)
    except (CrcError, MalformedFrameError) as exc:
        return type(exc)
    assert request.frame == frame
    return request.device, request.function, request.address, request.count, request.values


# --- strategies ----------------------------------------------------------------------------


@st.composite
def plausible_frames(draw: st.DrawFn, device: int) -> bytes:
    """Random bytes shaped like a frame: a likely device and function, and a valid CRC.

    Uniformly random bytes almost never pass the CRC, so they would only ever test the
    first check; these reach pymodbus's decoders with every kind of wrong content.
    """
    head = bytes(
        [
            draw(st.sampled_from([device, device, 0, 255, (device + 1) % 256])),
            draw(st.sampled_from([*FUNCTIONS, *(f | 0x80 for f in FUNCTIONS), 0x2B, 0x80, 0xFF])),
        ]
    )
    body = head + draw(st.binary(max_size=260))
    return body + frames.crc16(body)


# --- master side ----------------------------------------------------------------------------


@fuzz(400)
@given(data=st.data(), request=requests(), quirk=st.booleans())
def test_random_frames_get_the_oracles_verdict(
    data: st.DataObject,
    request: frames.Request,
    quirk: bool,  # noqa: FBT001
) -> None:
    frame = data.draw(st.one_of(st.binary(max_size=300), plausible_frames(request.device)))
    assert judge_answer(request, frame, quirk=quirk) == answer_oracle(request, frame, quirk=quirk)


@fuzz(600)
@given(data=st.data(), request=requests(), quirk=st.booleans(), recrc=st.booleans())
def test_mutated_answers_get_the_oracles_verdict(
    data: st.DataObject,
    request: frames.Request,
    quirk: bool,  # noqa: FBT001
    recrc: bool,  # noqa: FBT001
) -> None:
    answer = data.draw(good_answers(request, quirk=quirk))
    mutated = data.draw(mutations(answer, recrc=recrc))
    verdict = judge_answer(request, mutated, quirk=quirk)
    assert verdict == answer_oracle(request, mutated, quirk=quirk)
    if not frames.crc_ok(mutated):  # a frame with a wrong CRC is never accepted
        assert verdict in {CrcError, MalformedFrameError}


@fuzz(300)
@given(data=st.data(), request=requests(), quirk=st.booleans())
def test_up_to_three_flipped_bits_are_always_caught_by_the_crc(
    data: st.DataObject,
    request: frames.Request,
    quirk: bool,  # noqa: FBT001
) -> None:
    # CRC-16/MODBUS has the factor (x + 1) and detects every two-bit error in frames far
    # longer than 256 bytes: one, two or three flipped bits never pass.
    answer = data.draw(good_answers(request, quirk=quirk))
    bits = data.draw(st.sets(st.integers(0, 8 * len(answer) - 1), min_size=1, max_size=3))
    flipped = bytearray(answer)
    for bit in bits:
        flipped[bit // 8] ^= 1 << (bit % 8)
    with pytest.raises(CrcError):
        frames.parse_response(request, bytes(flipped), byte_count_16bit=quirk)


@fuzz(300)
@given(data=st.data(), request=requests(), other=requests(), quirk=st.booleans())
def test_an_answer_to_another_request_passes_only_if_it_says_the_same(
    data: st.DataObject,
    request: frames.Request,
    other: frames.Request,
    quirk: bool,  # noqa: FBT001
) -> None:
    # A late answer to the previous request (another device, function, quantity, address
    # or value) must not pass for this one unless its bytes answer this one too.
    stale = data.draw(good_answers(other, quirk=quirk))
    verdict = judge_answer(request, stale, quirk=quirk)
    assert verdict == answer_oracle(request, stale, quirk=quirk)
    if isinstance(verdict, tuple):
        assert stale[0] == request.device
        assert stale[1] == request.function
        if request.function in frames.READ_FUNCTIONS:
            assert request.count == other.count
        else:
            assert stale[2:6] == request.frame[2:6]


@fuzz(300)
@given(
    request=requests(),
    function=st.integers(0, 0x7F),
    code=st.integers(0, 255),
    meanings=st.dictionaries(st.integers(0, 255), st.text(min_size=1, max_size=12), max_size=4),
)
def test_exception_answers_carry_any_code_with_the_familys_meaning(
    request: frames.Request, function: int, code: int, meanings: dict[int, str]
) -> None:
    answer = frames.exception_response(request.device, function, code)
    if function != request.function:
        with pytest.raises(MalformedFrameError):
            frames.parse_response(request, answer, exceptions=meanings)
        return
    with pytest.raises(DeviceExceptionError) as caught:
        frames.parse_response(request, answer, exceptions=meanings)
    error = caught.value
    assert (error.device, error.function, error.code) == (request.device, request.function, code)
    assert error.meaning == meanings.get(code, f"exception_{code}")


@fuzz(400)
@given(data=st.data(), request=requests(), quirk=st.booleans())
def test_response_length_knows_the_length_from_the_first_three_bytes(
    data: st.DataObject,
    request: frames.Request,
    quirk: bool,  # noqa: FBT001
) -> None:
    answer = data.draw(good_answers(request, quirk=quirk))
    for size in range(len(answer) + 1):
        need = frames.response_length(request, answer[:size], byte_count_16bit=quirk)
        # 0 ("more bytes") until the head says it, then the answer's length, never another;
        # three bytes (device, function, byte count) always say it.
        if size >= 3:
            assert need == len(answer)
        else:
            assert need in {0, len(answer)}


@fuzz(400)
@given(
    request=requests(),
    head=st.binary(max_size=8),
    quirk=st.booleans(),
)
def test_response_length_of_any_head_is_a_length_or_a_malformed_frame(
    request: frames.Request,
    head: bytes,
    quirk: bool,  # noqa: FBT001
) -> None:
    try:
        need = frames.response_length(request, head, byte_count_16bit=quirk)
    except MalformedFrameError:
        # Only a function code that can answer neither the request nor as its exception.
        assert head[1] not in {request.function, request.function | frames.EXCEPTION_FLAG}
        return
    if need == 0:
        return
    # A length some frame can have: the shortest (an exception) up to a byte count of 255.
    assert MIN_FRAME <= need <= 5 + 0xFF


# --- slave side (the simulator) ---------------------------------------------------------------


@st.composite
def built_requests(draw: st.DrawFn) -> frames.Request:
    """Requests as a master builds them, broadcast writes included."""
    request = draw(requests())
    if request.is_write and draw(st.booleans()):
        return frames.write_request(frames.BROADCAST, request.address, request.values)
    return request


@fuzz(300)
@given(request=built_requests())
def test_every_request_the_master_builds_round_trips_through_the_slave(
    request: frames.Request,
) -> None:
    assert frames.parse_request(request.frame) == request
    for size in range(len(request.frame)):
        assert frames.request_length(request.frame[:size]) in {0, len(request.frame)}
    assert frames.request_length(request.frame) == len(request.frame)


@fuzz(400)
@given(data=st.data())
def test_random_requests_get_the_oracles_verdict(data: st.DataObject) -> None:
    frame = data.draw(st.one_of(st.binary(max_size=300), plausible_frames(1)))
    assert judge_request(frame) == request_oracle(frame)
    need = frames.request_length(frame)
    assert need == 0 or need >= frames.READ_REQUEST_LENGTH


@fuzz(500)
@given(data=st.data(), request=built_requests(), recrc=st.booleans())
def test_mutated_requests_get_the_oracles_verdict(
    data: st.DataObject,
    request: frames.Request,
    recrc: bool,  # noqa: FBT001
) -> None:
    mutated = data.draw(mutations(request.frame, recrc=recrc))
    verdict = judge_request(mutated)
    assert verdict == request_oracle(mutated)
    if not frames.crc_ok(mutated):  # the simulator never acts on a frame with a bad CRC
        assert verdict in {CrcError, MalformedFrameError}


# --- regressions found by the fuzzing above ----------------------------------------------------
#
# CRC-16/MODBUS has no final XOR, so a frame followed by one 0x00 byte passes the CRC
# again, shifted by a byte (a common glitch when an RS485 driver lets go of the line).
# pymodbus decodes a write echo, a write confirmation, an exception or a request and
# ignores what follows, so those frames passed for answers and requests of the wrong length.


def test_a_trailing_zero_byte_keeps_the_crc_valid() -> None:
    echo = frames.write_single_response(1, 0, 0)
    assert frames.crc_ok(echo + b"\x00")


@pytest.mark.parametrize(
    ("request_", "answer"),
    [
        (frames.write_single_request(1, 0, 0), frames.write_single_response(1, 0, 0)),
        (frames.write_multiple_request(1, 0, [0]), frames.write_multiple_response(1, 0, 1)),
        (frames.read_request(1, 0, 1), frames.exception_response(1, 3, 0)),
    ],
    ids=["06-echo", "16-confirmation", "exception"],
)
def test_an_answer_with_a_trailing_byte_is_malformed(
    request_: frames.Request, answer: bytes
) -> None:
    with pytest.raises(MalformedFrameError, match="bytes for"):
        frames.parse_response(request_, answer + b"\x00")


@pytest.mark.parametrize(
    "request_",
    [
        frames.write_single_request(1, 0, 0),
        frames.write_multiple_request(1, 0, [0]),
    ],
    ids=["06", "16"],
)
def test_a_request_with_a_trailing_byte_is_not_acted_on(request_: frames.Request) -> None:
    with pytest.raises(MalformedFrameError, match="bytes for"):
        frames.parse_request(request_.frame + b"\x00")
