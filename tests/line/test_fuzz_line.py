"""Fuzzing :class:`gateway.line.transports.serial_line.SerialLine` on a real pseudo-terminal: any answer, any timing.

The device end of the pty plays a sensor that answers each request with a random script:
garbage, the right answer, a mutated one, another device's answer, an exception, a late
answer to another request, a partial frame, or nothing, cut into chunks with pauses
shorter and longer than the line's 3.5-character silence. For every transaction:

- ``transact`` raises only the documented errors (:class:`BusTimeoutError`, the
  :class:`FrameError` kinds, :class:`DeviceExceptionError`), never a foreign one;
- every failure is counted in :class:`LineStats` under its kind, every success as a
  response, and a success is one of the frames the device really sent;
- the line resynchronises: the next clean answer is accepted, and what the failed
  transaction left behind is counted once, as noise or a stale frame.

Each example costs real time on the line (up to the 100 ms response timeout), so the
counts here are small; ``FUZZ_SCALE`` multiplies them (see :mod:`tests.fuzzing`).
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import os
import termios
import tty
from collections import Counter
from dataclasses import dataclass
from typing import TYPE_CHECKING, Final

import pytest
from hypothesis import given
from hypothesis import strategies as st

from gateway.errors import (
    BusTimeoutError,
    CrcError,
    DeviceExceptionError,
    GatewayError,
    MalformedFrameError,
    UnexpectedDeviceError,
)
from gateway.line.boundary import Exchange, RequestOptions
from gateway.line.stats import ErrorKind, LineStats
from gateway.line.transports.serial_line import SerialLine
from gateway.wire import frames
from gateway.wire.timing import LineFormat
from tests.fuzzing import fuzz, good_answers, mutations, requests

if TYPE_CHECKING:
    from collections.abc import AsyncIterator, Sequence

pytestmark = [pytest.mark.line, pytest.mark.timing]

FORMAT: Final = LineFormat(baudrate=115200, parity="N", stopbits=1)  # short frames, same rules
TIMEOUT_S: Final = 0.1
GAP_S: Final = 0.002
SETTLED_S: Final = 0.01  # the pty has delivered what the device end wrote
KIND_OF: Final[dict[type[GatewayError], str]] = {
    BusTimeoutError: ErrorKind.TIMEOUT,
    CrcError: ErrorKind.CRC,
    UnexpectedDeviceError: ErrorKind.WRONG_ADDRESS,
    MalformedFrameError: ErrorKind.MALFORMED,
    DeviceExceptionError: ErrorKind.EXCEPTION,
}
LINE_ERRORS: Final = tuple(KIND_OF)


class DeviceEnd:
    """The sensor's end of a pseudo-terminal pair: reads requests, writes scripted bytes."""

    def __init__(self) -> None:
        """Open a raw pty pair and listen on its master end."""
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave, termios.TCSANOW)  # no echo, no line discipline
        os.set_blocking(self.master, False)
        self.port = os.ttyname(self.slave)
        self.received = bytearray()
        self._arrived = asyncio.Event()
        asyncio.get_running_loop().add_reader(self.master, self._readable)

    def _readable(self) -> None:
        with contextlib.suppress(BlockingIOError, OSError):
            self.received += os.read(self.master, 4096)
            self._arrived.set()

    async def request(self, size: int) -> bytes:
        """The next ``size`` bytes the gateway sent (one request)."""
        async with asyncio.timeout(2.0):
            while len(self.received) < size:
                self._arrived.clear()
                await self._arrived.wait()
        request = bytes(self.received[:size])
        del self.received[:size]
        return request

    def send(self, data: bytes) -> None:
        """Put bytes on the line towards the gateway."""
        os.write(self.master, data)

    def close(self) -> None:
        """Stop listening and close both ends."""
        asyncio.get_running_loop().remove_reader(self.master)
        os.close(self.master)
        os.close(self.slave)


@contextlib.asynccontextmanager
async def wired_line() -> AsyncIterator[tuple[SerialLine, DeviceEnd]]:
    """A :class:`SerialLine` opened on one end of a pty, the device end on the other."""
    device = DeviceEnd()
    line = SerialLine(port=device.port, line=FORMAT)
    try:
        await line.open()
        yield line, device
    finally:
        await line.close()
        device.close()


# --- scripts: what the device end sends back ---------------------------------------------


@dataclass(frozen=True, slots=True)
class Chunk:
    """Bytes the device end writes after a pause."""

    pause_s: float
    data: bytes


@dataclass(frozen=True, slots=True)
class Script:
    """One request and the device end's reply to it, piece by piece."""

    request: frames.Request
    quirk: bool
    answer: bytes  # a correct answer (data or exception), the reference
    pieces: tuple[tuple[str, bytes], ...]  # (kind, bytes) in the order sent
    chunks: tuple[Chunk, ...]

    @property
    def sent(self) -> bytes:
        """Everything the device end sends."""
        return b"".join(chunk.data for chunk in self.chunks)

    @property
    def clean(self) -> bool:
        """The reply is exactly the correct answer, at once: its outcome is known."""
        return len(self.pieces) == 1 and self.pieces[0][0] == "answer" and self._prompt

    @property
    def _prompt(self) -> bool:
        return sum(chunk.pause_s for chunk in self.chunks) <= TIMEOUT_S / 4


PIECES: Final = ("answer", "mutated", "other_device", "stale", "partial", "garbage")
# Pauses below the 3 ms silence the line waits for, above it, and beyond the timeout.
PAUSES: Final = (0.0, 0.0, 0.0, 0.001, 0.005, 0.03, 0.12)


@st.composite
def scripts(draw: st.DrawFn) -> Script:
    """A request and a random reply built from pieces of answers and noise."""
    request = draw(requests())
    quirk = draw(st.booleans())
    answer = draw(good_answers(request, quirk=quirk))
    pieces: list[tuple[str, bytes]] = []
    # One reply in four is the plain answer: the case whose outcome is known exactly.
    kinds = (
        ["answer"]
        if draw(st.integers(0, 3)) == 0
        else draw(st.lists(st.sampled_from(PIECES), max_size=4))
    )
    for kind in kinds:
        if kind == "answer":
            data = answer
        elif kind == "mutated":
            data = draw(mutations(answer, recrc=draw(st.booleans())))
        elif kind == "other_device":
            data = bytes([draw(st.integers(0, 255).filter(lambda d: d != request.device))])
            data = data + answer[1:-2]
            data += frames.crc16(data)
        elif kind == "stale":
            data = draw(good_answers(draw(requests()), quirk=quirk))
        elif kind == "partial":
            data = answer[: draw(st.integers(1, len(answer) - 1))]
        else:
            data = draw(st.binary(min_size=1, max_size=24))
        pieces.append((kind, data))
    sent = b"".join(data for _, data in pieces)
    cuts = sorted(draw(st.sets(st.integers(1, max(1, len(sent) - 1)), max_size=3)))
    bounds = [0, *(c for c in cuts if c < len(sent)), len(sent)] if sent else []
    chunks = tuple(
        Chunk(pause_s=draw(st.sampled_from(PAUSES)), data=sent[start:end])
        for start, end in itertools.pairwise(bounds)
    )
    return Script(request=request, quirk=quirk, answer=answer, pieces=tuple(pieces), chunks=chunks)


# --- the checks ------------------------------------------------------------------------------


def answers_in(request: frames.Request, data: bytes, *, quirk: bool) -> list[frames.Response]:
    """Every frame inside ``data`` that answers ``request``, wherever it starts."""
    found = []
    for start in range(len(data)):
        try:
            need = frames.response_length(request, data[start:], byte_count_16bit=quirk)
            if need:
                found.append(
                    frames.parse_response(
                        request, data[start : start + need], byte_count_16bit=quirk
                    )
                )
        except (CrcError, UnexpectedDeviceError, MalformedFrameError, DeviceExceptionError):
            continue
    return found


@dataclass(frozen=True, slots=True)
class Counts:
    """A copy of the counters a transaction may change."""

    requests: Counter[int]
    responses: Counter[int]
    errors: Counter[tuple[int, str]]
    exception_codes: Counter[tuple[int, int]]

    @classmethod
    def of(cls, stats: LineStats) -> Counts:
        """Copy the counters now."""
        return cls(
            Counter(stats.requests),
            Counter(stats.responses),
            Counter(stats.errors),
            Counter(stats.exception_codes),
        )


async def run_script(
    line: SerialLine, device: DeviceEnd, script: Script
) -> Exchange | GatewayError:
    """Send the request, play the script from the device end, return what ``transact`` did.

    The script plays to its end even when the transaction is over, so what comes late is
    on the line for the next transaction, as on a real bus.
    """
    request = script.request
    transaction = asyncio.create_task(
        line.transact(
            request, RequestOptions(timeout_s=TIMEOUT_S, gap_s=GAP_S, byte_count_16bit=script.quirk)
        )
    )
    assert await device.request(len(request.frame)) == request.frame
    # A pty carries bytes at once; a line does not. Nothing the device sends can be in
    # before the request and the reply have taken their time on the wire (the gateway
    # refuses such an answer as an echo of its own request).
    await asyncio.sleep(FORMAT.wire_s(len(request.frame) + len(script.sent)))
    for chunk in script.chunks:
        await asyncio.sleep(chunk.pause_s)
        device.send(chunk.data)
    try:
        exchange = await transaction
    except LINE_ERRORS as exc:
        outcome: Exchange | GatewayError = exc
    else:
        assert exchange is not None  # not a broadcast
        outcome = exchange
    await asyncio.sleep(SETTLED_S)
    return outcome


def check_counted(
    script: Script, outcome: Exchange | GatewayError, before: Counts, line: SerialLine
) -> None:
    """The outcome is counted once under its kind; a success is a frame really sent."""
    stats, device = line.stats, script.request.device
    assert stats.requests[device] == before.requests[device] + 1
    if isinstance(outcome, Exchange):
        assert stats.responses[device] == before.responses[device] + 1
        assert outcome.response in answers_in(script.request, script.sent, quirk=script.quirk)
        return
    assert stats.responses[device] == before.responses[device]
    kind = KIND_OF[type(outcome)]
    assert stats.errors[device, kind] == before.errors[device, kind] + 1, (kind, outcome)
    if isinstance(outcome, DeviceExceptionError):
        code = outcome.code
        assert stats.exception_codes[device, code] == before.exception_codes[device, code] + 1
        exception = frames.exception_response(device, script.request.function, code)
        assert exception in script.sent


def check_consumed(script: Script, outcome: Exchange | GatewayError, line: SerialLine) -> None:
    """After an answer or an exception, only bytes sent after that frame are left to flush.

    (After any other failure the buffer is cleared: only bytes that came later are left.)
    """
    left = bytes(line._inbox.buffer) if line._inbox else b""
    if isinstance(outcome, DeviceExceptionError):
        decided = frames.EXCEPTION_FRAME_LENGTH
    elif isinstance(outcome, Exchange):
        decided = (
            frames.WRITE_RESPONSE_LENGTH
            if script.request.is_write
            else 5 + 2 * outcome.response.count
        )
    else:
        decided = 0
    assert script.sent.endswith(left)
    assert len(left) <= len(script.sent) - decided


def check_answered(script: Script, outcome: Exchange | GatewayError, line: SerialLine) -> None:
    """A clean reply's outcome is its answer (or its exception), and nothing is left over."""
    if script.answer[1] & frames.EXCEPTION_FLAG:
        assert isinstance(outcome, DeviceExceptionError)
        assert outcome.code == script.answer[2]
    else:
        assert isinstance(outcome, Exchange)
        assert outcome.response == frames.parse_response(
            script.request, script.answer, byte_count_16bit=script.quirk
        )
    assert not line._inbox or not line._inbox.buffer, "the answer was left to flush"


async def check_resynchronised(line: SerialLine, device: DeviceEnd, script: Script) -> None:
    """A clean answer right after is accepted; leftovers are counted once, as noise or stale."""
    left_over = bool(line._inbox and line._inbox.buffer)
    before = Counts.of(line.stats)
    clean = Script(
        request=script.request,
        quirk=script.quirk,
        answer=script.answer,
        pieces=(("answer", script.answer),),
        chunks=(Chunk(pause_s=0.0, data=script.answer),),
    )
    outcome = await run_script(line, device, clean)
    check_counted(clean, outcome, before, line)
    check_answered(clean, outcome, line)
    leftovers = sum(
        line.stats.errors[script.request.device, kind] - before.errors[script.request.device, kind]
        for kind in (ErrorKind.NOISE, ErrorKind.STALE)
    )
    assert leftovers == (1 if left_over else 0)


async def play(scripts_: Sequence[Script]) -> None:
    """Run scripts one after another on one line, checking each, then resynchronise."""
    async with wired_line() as (line, device):
        for script in scripts_:
            before = Counts.of(line.stats)
            outcome = await run_script(line, device, script)
            check_counted(script, outcome, before, line)
            check_consumed(script, outcome, line)
            if script.clean:  # the only reply whose outcome is fixed in advance
                check_answered(script, outcome, line)
        await check_resynchronised(line, device, scripts_[-1])


@fuzz(100)
@given(script=scripts())
def test_any_reply_to_one_request_is_survived_and_counted(script: Script) -> None:
    asyncio.run(play([script]), debug=True)


@fuzz(25)
@given(sequence=st.lists(scripts(), min_size=2, max_size=5))
def test_a_run_of_bad_replies_leaves_the_line_usable(sequence: list[Script]) -> None:
    asyncio.run(play(sequence), debug=True)


# --- regression found by the fuzzing above -------------------------------------------------


async def test_an_exception_answer_is_consumed_not_counted_again_as_a_stale_frame() -> None:
    # The exception frame used to stay in the receive buffer; the next transaction then
    # flushed it and counted a stale frame that never happened.
    read = frames.read_request(1, 0x2620, 2)
    async with wired_line() as (line, device):
        refused = Script(
            request=read,
            quirk=False,
            answer=frames.exception_response(1, read.function, 2),
            pieces=(),
            chunks=(Chunk(pause_s=0.0, data=frames.exception_response(1, read.function, 2)),),
        )
        outcome = await run_script(line, device, refused)
        assert isinstance(outcome, DeviceExceptionError)
        answered = Script(
            request=read,
            quirk=False,
            answer=frames.read_response(1, read.function, [0, 0x41A2]),
            pieces=(),
            chunks=(Chunk(pause_s=0.0, data=frames.read_response(1, read.function, [0, 0x41A2])),),
        )
        assert isinstance(await run_script(line, device, answered), Exchange)
    assert line.stats.errors == Counter({(1, ErrorKind.EXCEPTION): 1})
