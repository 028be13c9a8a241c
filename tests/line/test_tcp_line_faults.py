"""The network lines against peers that misbehave as converters in the field do.

Real sockets on loopback. Each peer is a converter written by hand (a listening socket
whose every byte a test scripts) or the simulator in a process of its own that is stopped
(SIGSTOP) and let go again. The misbehaviours are those users of serial device servers and
Modbus TCP gateways report: a peer that stays connected but answers nothing (the kernel
still acknowledges, so only the gateway's own rule can end the session); one that closes
or resets mid-frame; MBAP headers with a wrong protocol id, length or unit id; answers to
earlier transactions (a late answer must never be taken for the current one) and
converters that do not return the request's transaction id; garbage after an answer; and
over RTU: bad CRCs, answers from other addresses, frames split over many TCP segments and
two frames in one. Every case asserts the registers taken when the answer is good, the
exception and the counter of its kind when it is not, and the times the peer saw the
requests where timing is the point.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import re
import signal
import socket
import struct
import subprocess
import sys
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import pytest

from gateway.config.network import TcpSettings
from gateway.errors import (
    BusClosedError,
    BusTimeoutError,
    CrcError,
    MalformedFrameError,
    UnexpectedDeviceError,
)
from gateway.line.boundary import RequestOptions
from gateway.line.engine.worker import BusWorker
from gateway.line.stats import ErrorKind
from gateway.line.transports.modbus_tcp import ModbusTcpLine
from gateway.line.transports.rtu_over_tcp import RtuOverTcpLine
from gateway.wire import frames, mbap
from gateway.wire.timing import LineFormat
from tests.rigs import ListSink, target

if TYPE_CHECKING:
    from collections.abc import AsyncIterator, Awaitable, Callable, Iterator
    from pathlib import Path

pytestmark = [pytest.mark.line, pytest.mark.timing]

LINE: dict[str, Any] = {"baudrate": 9600, "parity": "E", "stopbits": 1}
READ = frames.read_request(1, 0x2620, 2)  # the S10 manual's example: temperature
TWENTY = (0x0000, 0x41A2)  # 20.25 as the S10 manual's answer has it
FRESH = (0x0000, 0x41A4)  # 20.5: a value the current request's answer alone carries
TIMEOUT_S = 0.2


# --- a converter written by hand ----------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Arrival:
    """A request as the peer read it: when its last byte came, on which connection."""

    at: float
    frame: bytes
    connection: int


class Talk:
    """One accepted connection as a test's script drives it."""

    def __init__(
        self, peer: Peer, number: int, reader: asyncio.StreamReader, writer: asyncio.StreamWriter
    ) -> None:
        self.peer, self.number, self.reader, self.writer = peer, number, reader, writer

    async def mbap_request(self) -> mbap.MbapFrame:
        header = await self.reader.readexactly(mbap.MBAP_HEADER_LENGTH)
        rest = await self.reader.readexactly(int.from_bytes(header[4:6], "big") - 1)
        self.peer.arrivals.append(Arrival(time.monotonic(), header + rest, self.number))
        decoded = mbap.decode(header + rest)
        assert decoded is not None
        return decoded[0]

    async def rtu_request(self) -> frames.Request:
        frame = await self.reader.readexactly(len(READ.frame))  # a read is eight bytes
        self.peer.arrivals.append(Arrival(time.monotonic(), frame, self.number))
        return frames.parse_request(frame)

    async def send(self, *pieces: bytes, pause_s: float = 0.0) -> None:
        """Each piece a segment of its own (no Nagle here), ``pause_s`` between them."""
        for index, piece in enumerate(pieces):
            if index and pause_s:
                await asyncio.sleep(pause_s)
            self.writer.write(piece)
            await self.writer.drain()
            self.peer.sent_at.append(time.monotonic())

    def finish(self) -> None:
        """Close this side: a FIN after what was sent."""
        self.writer.close()

    def reset(self) -> None:
        """Close with SO_LINGER 0: the kernel sends an RST, what was queued is dropped."""
        sock = self.writer.get_extra_info("socket")
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
        self.writer.transport.abort()

    async def drain_silently(self) -> None:
        """Read (and record) every request from now on, answer none: a half-open session."""
        while True:
            data = await self.reader.read(4096)
            if not data:
                return
            self.peer.arrivals.append(Arrival(time.monotonic(), data, self.number))


@dataclass
class Peer:
    """A listening socket on loopback; every connection it accepts runs ``script``."""

    script: Callable[[Talk], Awaitable[None]]
    accepted: list[float] = field(default_factory=list)
    arrivals: list[Arrival] = field(default_factory=list)
    sent_at: list[float] = field(default_factory=list)
    _writers: list[asyncio.StreamWriter] = field(default_factory=list)
    _tasks: list[asyncio.Task[None]] = field(default_factory=list)

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        task = asyncio.current_task()
        assert task is not None
        self._tasks.append(task)
        self._writers.append(writer)
        number = len(self.accepted)
        self.accepted.append(time.monotonic())
        writer.get_extra_info("socket").setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        with contextlib.suppress(ConnectionError, asyncio.IncompleteReadError):
            await self.script(Talk(self, number, reader, writer))
        if not writer.is_closing():
            writer.close()

    def on(self, connection: int) -> list[Arrival]:
        return [a for a in self.arrivals if a.connection == connection]


@contextlib.asynccontextmanager
async def serving(script: Callable[[Talk], Awaitable[None]]) -> AsyncIterator[tuple[Peer, int]]:
    peer = Peer(script)
    server = await asyncio.start_server(peer._serve, "127.0.0.1", 0)
    try:
        yield peer, int(server.sockets[0].getsockname()[1])
    finally:
        server.close()
        for writer in peer._writers:
            writer.transport.abort()
        await server.wait_closed()
        await asyncio.wait_for(asyncio.gather(*peer._tasks), timeout=2)


def mbap_answer(frame: mbap.MbapFrame, registers: tuple[int, ...] = TWENTY) -> bytes:
    pdu = frames.read_response(frame.unit, frames.READ_HOLDING, registers)[1:-2]
    return mbap.encode(frame.transaction, frame.unit, pdu)


def rtu_answer(request: frames.Request, registers: tuple[int, ...] = TWENTY) -> bytes:
    return frames.read_response(request.device, request.function, registers)


def mbap_line(port: int, **tcp: Any) -> ModbusTcpLine:
    return ModbusTcpLine(
        port=f"tcp://127.0.0.1:{port}", line=LineFormat(**LINE), tcp=TcpSettings(**tcp)
    )


def rtu_line(port: int, **tcp: Any) -> RtuOverTcpLine:
    return RtuOverTcpLine(
        port=f"socket://127.0.0.1:{port}", line=LineFormat(**LINE), tcp=TcpSettings(**tcp)
    )


@contextlib.asynccontextmanager
async def opened(line: ModbusTcpLine | RtuOverTcpLine) -> AsyncIterator[None]:
    await line.open()
    try:
        yield
    finally:
        await line.close()


async def read(line: ModbusTcpLine | RtuOverTcpLine) -> tuple[int, ...]:
    exchange = await line.transact(READ, RequestOptions(timeout_s=TIMEOUT_S, gap_s=0.005))
    assert exchange is not None
    return exchange.response.registers


async def fails(
    line: ModbusTcpLine | RtuOverTcpLine, error: type[Exception]
) -> tuple[Exception, float]:
    """The transaction's failure, and how long after it began."""
    started = time.monotonic()
    with pytest.raises(error) as caught:
        await line.transact(READ, RequestOptions(timeout_s=TIMEOUT_S, gap_s=0.005))
    return caught.value, time.monotonic() - started


def errors(line: ModbusTcpLine | RtuOverTcpLine) -> dict[tuple[int, str], int]:
    return {key: count for key, count in line.stats.errors.items() if count}


# --- Modbus TCP: the MBAP header --------------------------------------------------------


async def test_mbap_an_answer_in_one_byte_segments_is_taken_whole() -> None:
    async def script(talk: Talk) -> None:
        while True:
            answer = mbap_answer(await talk.mbap_request())
            await talk.send(*(answer[i : i + 1] for i in range(len(answer))), pause_s=0.01)

    async with serving(script) as (peer, port):
        line = mbap_line(port)
        async with opened(line):
            assert await read(line) == TWENTY
            exchange_end = line.last_frame_end
    assert len(peer.sent_at) == 13  # 7 bytes of header, 6 of PDU: thirteen segments
    assert exchange_end >= peer.sent_at[-1]  # taken when its last byte came, not before
    assert not errors(line)


async def test_mbap_a_wrong_protocol_id_is_malformed_and_the_session_goes_on() -> None:
    async def script(talk: Talk) -> None:
        frame = await talk.mbap_request()
        bad = bytearray(mbap_answer(frame))
        bad[2:4] = b"\x00\x01"  # protocol 1: not Modbus
        await talk.send(bytes(bad))
        await talk.send(mbap_answer(await talk.mbap_request(), FRESH))

    async with serving(script) as (_, port):
        line = mbap_line(port)
        async with opened(line):
            error, took = await fails(line, MalformedFrameError)
            assert await read(line) == FRESH
    assert "no valid answer of device 1 function 0x03 at 0x2620" in str(error)
    assert TIMEOUT_S <= took < TIMEOUT_S + 0.15  # its own answer might still have come
    assert errors(line) == {(1, ErrorKind.MALFORMED): 1}
    assert line.stats.responses[1] == 1


async def test_mbap_a_length_too_long_fails_at_the_deadline_then_the_next_answer_is_whole() -> None:
    """A header that announces more than comes cannot be told from a slow network: the
    request times out (saying what came) and the bytes go, so the next answer is not read
    as the rest of it."""

    async def script(talk: Talk) -> None:
        frame = await talk.mbap_request()
        bad = bytearray(mbap_answer(frame))
        bad[5] += 1  # one byte more announced than sent (a reported exception answer's bug)
        await talk.send(bytes(bad))
        await talk.send(mbap_answer(await talk.mbap_request(), FRESH))

    async with serving(script) as (_, port):
        line = mbap_line(port)
        async with opened(line):
            error, took = await fails(line, BusTimeoutError)
            assert await read(line) == FRESH
    assert "incomplete answer of device 1" in str(error)
    assert "13 of the 14 bytes its MBAP header announces" in str(error)
    assert TIMEOUT_S <= took < TIMEOUT_S + 0.15
    assert errors(line) == {(1, ErrorKind.TIMEOUT): 1}
    assert line.watch.silent == 0  # bytes came: not a silent converter


async def test_mbap_a_length_too_short_is_malformed_and_its_rest_is_not_the_next_answer() -> None:
    async def script(talk: Talk) -> None:
        frame = await talk.mbap_request()
        bad = bytearray(mbap_answer(frame))
        bad[5] -= 2  # the header cuts the last register off; its two bytes trail
        await talk.send(bytes(bad))
        await talk.send(mbap_answer(await talk.mbap_request(), FRESH))

    async with serving(script) as (_, port):
        line = mbap_line(port)
        async with opened(line):
            error, took = await fails(line, MalformedFrameError)
            assert await read(line) == FRESH
    assert "cannot decode response 01 03 04 00 00" in str(error)
    assert took < 0.1  # the frame is complete and wrong: no wait for the deadline
    # The two trailing bytes were thrown away before the next request went out.
    assert errors(line) == {(1, ErrorKind.MALFORMED): 1, (1, ErrorKind.NOISE): 1}


async def test_mbap_an_answer_of_another_unit_is_a_wrong_address() -> None:
    async def script(talk: Talk) -> None:
        frame = await talk.mbap_request()
        other = mbap.MbapFrame(transaction=frame.transaction, unit=2, pdu=b"")
        await talk.send(mbap_answer(other))
        await talk.send(mbap_answer(await talk.mbap_request(), FRESH))

    async with serving(script) as (_, port):
        line = mbap_line(port)
        async with opened(line):
            error, took = await fails(line, UnexpectedDeviceError)
            assert await read(line) == FRESH
    assert "unit 2 answered a request for device 1" in str(error)
    assert took < 0.1
    assert errors(line) == {(1, ErrorKind.WRONG_ADDRESS): 1}


async def test_mbap_a_late_answer_to_an_earlier_request_is_not_the_current_answer() -> None:
    """The first request's answer comes after its timeout, in the middle of the second
    transaction and ahead of its answer: it is dropped by its transaction id, and the
    second request gets its own (different) registers."""

    async def script(talk: Talk) -> None:
        first = await talk.mbap_request()
        second = await talk.mbap_request()  # sent once the first timed out
        await asyncio.sleep(0.03)
        await talk.send(mbap_answer(first, TWENTY))
        await asyncio.sleep(0.03)
        await talk.send(mbap_answer(second, FRESH))

    async with serving(script) as (peer, port):
        line = mbap_line(port)
        async with opened(line):
            await fails(line, BusTimeoutError)
            assert await read(line) == FRESH
    first, second = peer.arrivals
    assert second.at - first.at >= TIMEOUT_S  # not sent again before its timeout
    assert errors(line) == {(1, ErrorKind.TIMEOUT): 1, (1, ErrorKind.STALE): 1}
    assert line.stats.responses[1] == 1


async def test_mbap_a_converter_that_never_returns_the_transaction_id_is_named() -> None:
    """Some converters answer with a transaction id of their own (the next one, or 0):
    every answer is dropped, and the timeout says why and what to do."""

    async def script(talk: Talk) -> None:
        while True:
            frame = await talk.mbap_request()
            wrong = mbap.MbapFrame(transaction=frame.transaction + 1, unit=1, pdu=b"")
            await talk.send(mbap_answer(wrong))

    async with serving(script) as (peer, port):
        line = mbap_line(port, silent_requests=2)
        async with opened(line):
            for _ in range(3):
                error, took = await fails(line, BusTimeoutError)
                assert TIMEOUT_S <= took < TIMEOUT_S + 0.15
    message = str(error)
    assert "an answer came with transaction id 4, this request's is 3" in message
    assert "does not return the transaction id" in message
    assert errors(line) == {(1, ErrorKind.TIMEOUT): 3, (1, ErrorKind.STALE): 3}
    assert len(peer.accepted) == 1  # it answers: the session is not reopened for silence


async def test_mbap_garbage_after_a_good_answer_is_noise_not_an_answer() -> None:
    """Garbage after an answer, in its segment and in one of its own that arrives with the
    next answer: the registers are the answers', the garbage is counted as noise."""
    garbage = bytes.fromhex("00 00 ff")

    async def script(talk: Talk) -> None:
        await talk.send(mbap_answer(await talk.mbap_request(), TWENTY) + garbage)
        frame = await talk.mbap_request()
        await talk.send(mbap_answer(frame, FRESH))
        await asyncio.sleep(0.02)
        late = await talk.mbap_request()
        await talk.send(garbage, mbap_answer(late, TWENTY), pause_s=0.01)

    async with serving(script) as (_, port):
        line = mbap_line(port)
        async with opened(line):
            assert await read(line) == TWENTY
            assert await read(line) == FRESH
            assert await read(line) == TWENTY
    assert errors(line) == {(1, ErrorKind.NOISE): 2}
    assert line.stats.responses[1] == 3


# --- RTU over TCP ---------------------------------------------------------------------


async def test_rtu_an_answer_split_over_many_segments_with_pauses_is_taken_whole() -> None:
    async def script(talk: Talk) -> None:
        while True:
            answer = rtu_answer(await talk.rtu_request())
            pieces = [answer[:1], answer[1:2], answer[2:5], answer[5:8], answer[8:]]
            await talk.send(*pieces, pause_s=0.02)  # each pause five RTU gaps at 9600

    async with serving(script) as (peer, port):
        line = rtu_line(port)
        async with opened(line):
            assert await read(line) == TWENTY
            assert line.last_frame_end >= peer.sent_at[-1]
    assert not errors(line)


async def test_rtu_a_bad_crc_is_a_crc_error_and_the_next_answer_is_read() -> None:
    async def script(talk: Talk) -> None:
        bad = bytearray(rtu_answer(await talk.rtu_request()))
        bad[-1] ^= 0xFF
        await talk.send(bytes(bad))
        await talk.send(rtu_answer(await talk.rtu_request(), FRESH))

    async with serving(script) as (_, port):
        line = rtu_line(port)
        async with opened(line):
            error, took = await fails(line, CrcError)
            assert await read(line) == FRESH
    assert "answer of device 1 function 0x03 at 0x2620 failed its CRC" in str(error)
    assert took < TIMEOUT_S  # final once the line fell silent, not at the deadline
    assert errors(line) == {(1, ErrorKind.CRC): 1}


async def test_rtu_an_answer_from_another_address_is_a_wrong_address() -> None:
    async def script(talk: Talk) -> None:
        await talk.rtu_request()
        await talk.send(rtu_answer(frames.read_request(2, 0x2620, 2)))
        await talk.send(rtu_answer(await talk.rtu_request(), FRESH))

    async with serving(script) as (_, port):
        line = rtu_line(port)
        async with opened(line):
            error, took = await fails(line, UnexpectedDeviceError)
            assert await read(line) == FRESH
    assert "device 2 answered a request for device 1" in str(error)
    assert took >= TIMEOUT_S  # the device's own answer may still follow another's frame
    assert errors(line) == {(1, ErrorKind.WRONG_ADDRESS): 1}


async def test_rtu_another_devices_frame_and_the_answer_in_one_segment() -> None:
    async def script(talk: Talk) -> None:
        request = await talk.rtu_request()
        other = rtu_answer(frames.read_request(2, 0x2620, 2), TWENTY)
        await talk.send(other + rtu_answer(request, FRESH))

    async with serving(script) as (_, port):
        line = rtu_line(port)
        async with opened(line):
            assert await read(line) == FRESH
    assert errors(line) == {(2, ErrorKind.STALE): 1}


async def test_rtu_a_doubled_answer_in_one_segment_is_not_the_next_answer() -> None:
    async def script(talk: Talk) -> None:
        answer = rtu_answer(await talk.rtu_request(), TWENTY)
        await talk.send(answer + answer)  # a converter that sent its buffer twice
        await talk.send(rtu_answer(await talk.rtu_request(), FRESH))

    async with serving(script) as (_, port):
        line = rtu_line(port)
        async with opened(line):
            assert await read(line) == TWENTY
            assert await read(line) == FRESH
    assert errors(line) == {(1, ErrorKind.STALE): 1}


async def test_rtu_a_late_answer_and_the_answer_in_one_segment_the_later_is_taken() -> None:
    """A converter that held a late answer of the same device and sends it with the answer
    to the current request, in one segment. TCP keeps the order: the first frame is the
    old one, the last one the device's answer to this request."""

    async def script(talk: Talk) -> None:
        request = await talk.rtu_request()
        await talk.send(rtu_answer(request, TWENTY) + rtu_answer(request, FRESH))

    async with serving(script) as (_, port):
        line = rtu_line(port)
        async with opened(line):
            assert await read(line) == FRESH
    assert errors(line) == {(1, ErrorKind.STALE): 1}


# --- both kinds: the session ---------------------------------------------------------------


def line_for(scheme: str, port: int, **tcp: Any) -> ModbusTcpLine | RtuOverTcpLine:
    return mbap_line(port, **tcp) if scheme == "tcp" else rtu_line(port, **tcp)


async def request_of(talk: Talk, scheme: str) -> bytes:
    """The next request, and the bytes of its good answer."""
    if scheme == "tcp":
        return mbap_answer(await talk.mbap_request(), FRESH)
    return rtu_answer(await talk.rtu_request(), FRESH)


@pytest.mark.parametrize("scheme", ["tcp", "socket"])
@pytest.mark.parametrize("ending", ["fin", "rst"])
async def test_a_peer_that_ends_the_session_mid_frame(scheme: str, ending: str) -> None:
    """Half an answer, then a FIN or an RST: the request fails at once as a closed port,
    saying so, and the line opens again to a peer that answers."""

    async def script(talk: Talk) -> None:
        answer = await request_of(talk, scheme)
        if talk.number == 0:
            await talk.send(answer[: len(answer) // 2])
            await asyncio.sleep(0.02)
            talk.finish() if ending == "fin" else talk.reset()
            return
        await talk.send(answer)

    async with serving(script) as (peer, port):
        line = line_for(scheme, port)
        async with opened(line):
            error, took = await fails(line, BusClosedError)
            assert not line.is_open
            assert not line.stats.port_open
            await line.close()
            await line.open()
            assert await read(line) == FRESH
    assert took < 0.1  # not the response timeout: the end of the session wakes the wait
    words = {
        "fin": "the converter closed the connection",
        "rst": "the converter reset the connection",
    }[ending]
    assert f"{line.port} went away: {words}" in str(error)
    assert "no other client" in str(error)
    assert len(peer.accepted) == 2
    assert not errors(line)  # a closed session is a port failure, not a device's


@pytest.mark.parametrize("scheme", ["tcp", "socket"])
async def test_a_reset_between_requests_fails_the_next_one_at_once(scheme: str) -> None:
    async def script(talk: Talk) -> None:
        await talk.send(await request_of(talk, scheme))
        await asyncio.sleep(0.02)
        talk.reset()

    async with serving(script) as (_, port):
        line = line_for(scheme, port)
        async with opened(line):
            assert await read(line) == FRESH
            await asyncio.sleep(0.1)
            error, took = await fails(line, BusClosedError)
    assert took < 0.1  # the reset is known: no wait for a timeout
    assert "reset the connection" in str(error)


@pytest.mark.parametrize("scheme", ["tcp", "socket"])
async def test_a_peer_that_goes_silent_is_left_after_the_silence_rule(scheme: str) -> None:
    """The first session answers twice, then reads everything and answers nothing (the
    kernel acknowledges: no TCP timer ends it). Each request times out on its own,
    counted; the third silent one ends the session, with the cause and the fix in its
    message; the next session answers and the reads go on."""

    async def script(talk: Talk) -> None:
        if talk.number == 0:
            for _ in range(2):
                await talk.send(await request_of(talk, scheme))
            await talk.drain_silently()
            return
        while True:
            await talk.send(await request_of(talk, scheme))

    results: list[tuple[int, ...] | Exception] = []
    async with serving(script) as (peer, port):
        line = line_for(scheme, port, silent_requests=3)
        async with opened(line):
            for _ in range(7):
                try:
                    results.append(await read(line))
                except BusTimeoutError as exc:
                    results.append(exc)
                    ended_at = time.monotonic()
    assert [r if isinstance(r, tuple) else type(r) for r in results] == [
        FRESH, FRESH, BusTimeoutError, BusTimeoutError, BusTimeoutError, FRESH, FRESH,
    ]  # fmt: skip
    assert errors(line) == {(1, ErrorKind.TIMEOUT): 3}
    silent = [a.at for a in peer.on(0)][2:]
    assert len(silent) == 3  # each silent request sent once, none again before its timeout
    assert all(b - a >= TIMEOUT_S for a, b in itertools.pairwise(silent))
    assert len(peer.accepted) == 2
    assert peer.accepted[1] - ended_at < 0  # reopened before the failure was raised
    assert peer.accepted[1] - silent[-1] < TIMEOUT_S + 0.1  # at once after the third
    assert len(line.watch.ended_at) == 1
    last = str(results[4])
    assert "no answer of device 1 function 0x03 at 0x2620" in last
    assert "no byte back for 3 requests in a row" in last
    assert "the connection is closed and opened again" in last
    assert "restart the converter" in last
    assert "no byte back" not in str(results[2])  # the first two are plain timeouts


# --- a converter whose process is stopped: the worker -------------------------------------

SIMULATED = (
    "line: {baudrate: 9600, parity: E, stopbits: 1}\n"
    "pace: true\n"
    "devices:\n"
    "  - {profile: jumo-digiline-odo-s10, address: 1, animate: false,"
    " values: {temperature: 20.25}}\n"
)


@contextlib.contextmanager
def simulator_process(tmp_path: Path, framing: str) -> Iterator[tuple[subprocess.Popen[str], int]]:
    """``gateway simulate --tcp`` in a process of its own, which a test may stop."""
    config = tmp_path / "sim.yaml"
    config.write_text(SIMULATED, encoding="utf-8")
    command = [sys.executable, "-m", "gateway", "simulate", "--config", str(config)]
    command += ["--tcp", "127.0.0.1:0", "--framing", framing]
    with subprocess.Popen(
        command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    ) as sim:
        assert sim.stdout is not None
        banner = sim.stdout.readline()
        match = re.search(r"://127\.0\.0\.1:(\d+)", banner)
        assert match, banner + (sim.stderr.read() if sim.stderr else "")
        try:
            yield sim, int(match.group(1))
        finally:
            sim.send_signal(signal.SIGCONT)
            sim.send_signal(signal.SIGINT)
            _, stderr = sim.communicate(timeout=10)
            sys.stderr.write(stderr)  # shown with a failure: what the simulator said


async def until(
    condition: Callable[[], bool], timeout_s: float, what: str, line: RtuOverTcpLine | ModbusTcpLine
) -> float:
    """Wait for ``condition`` (the worker's state); the seconds it took."""
    started = time.monotonic()
    with contextlib.suppress(TimeoutError):
        async with asyncio.timeout(timeout_s):
            while not condition():  # noqa: ASYNC110 - another task's state, every 20 ms
                await asyncio.sleep(0.02)
    assert condition(), f"{what}: {errors(line)}, reopened at {line.watch.ended_at}"
    return time.monotonic() - started


@pytest.mark.parametrize("scheme", ["tcp", "socket"])
async def test_a_stopped_converter_process_then_polling_resumes(
    scheme: str, tmp_path: Path
) -> None:
    """SIGSTOP: the kernel still accepts and acknowledges for the stopped process, so the
    session looks alive and only the silence rule ends it (and its reopenings land in the
    backlog). SIGCONT: the reopened session is served and the device is back online with
    the simulated value."""
    with simulator_process(tmp_path, "tcp" if scheme == "tcp" else "rtu") as (sim, port):
        line = line_for(scheme, port, silent_requests=2)
        sink = ListSink()
        device = target("s10", "jumo-digiline-odo-s10", 1, interval=0.5, timeout_s=TIMEOUT_S)
        worker = BusWorker(
            name="line1",
            line=line,
            devices=[device],
            sinks=[sink],
            reconnect_max_s=0.5,
            late_answer_window_s=0.1,
        )
        state = worker.devices["s10"]

        def fresh(since: float) -> list[object]:
            """The temperatures taken since ``since``."""
            return [s.value for s in sink.good("s10", "temperature") if s.monotonic > since]

        task = asyncio.create_task(worker.run())
        try:
            await until(lambda: bool(sink.good("s10", "temperature")), 10, "never polled", line)
            sim.send_signal(signal.SIGSTOP)
            stopped = time.monotonic()
            await until(
                lambda: state.presence.online is False, 10, "still online while stopped", line
            )
            await until(lambda: len(line.watch.ended_at) >= 1, 10, "the session was kept", line)
            timeouts = line.stats.errors[1, ErrorKind.TIMEOUT]
            assert timeouts >= 2
            sim.send_signal(signal.SIGCONT)
            resumed = time.monotonic()
            back = await until(
                lambda: state.presence.online is True, 10, "not back after SIGCONT", line
            )
            await until(lambda: bool(fresh(resumed)), 5, "no value after SIGCONT", line)
        finally:
            worker.request_stop()
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task
            await line.close()
    assert line.watch.ended_at[0] - stopped < 2 * (TIMEOUT_S + 0.1) + 1.0
    assert back < 3.0
    assert set(fresh(resumed)) == {20.25}
    offline = [e for e in sink.events if e.device == "s10" and not e.online]
    assert offline
