"""The simulator as a serial device server in Modbus TCP mode, read by independent masters.

mbpoll (libmodbus) reads it as it would a Moxa or USR converter; raw sockets show the
converter's own answers (0B, 0A), its serialisation of two masters, and the referee
still judging the serial side behind it.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import time
from typing import TYPE_CHECKING, Any

import pytest

from gateway.simulator import SimulatorServer, build_bus, parse_settings
from gateway.wire import frames, mbap
from tests.simulator.test_wire import DEVICES, mbpoll, mbpoll_values

if TYPE_CHECKING:
    from collections.abc import AsyncIterator

pytestmark = [pytest.mark.line]


@contextlib.asynccontextmanager
async def converter(
    devices: list[dict[str, Any]], *, timeout_s: float = 0.05, **settings: Any
) -> AsyncIterator[tuple[SimulatorServer, int]]:
    server = SimulatorServer(build_bus(parse_settings({"devices": devices, **settings})))
    try:
        port = await server.open_tcp("127.0.0.1", 0, framing="tcp", converter_timeout_s=timeout_s)
        yield server, port
    finally:
        await server.close()


async def ask(port: int, *requests: bytes, wait_s: float = 0.5) -> list[mbap.MbapFrame]:
    """Send MBAP requests on one connection; the frames that came back within ``wait_s``."""
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    try:
        for request in requests:
            writer.write(request)
        await writer.drain()
        received = bytearray()
        with contextlib.suppress(TimeoutError):
            async with asyncio.timeout(wait_s):
                while data := await reader.read(4096):
                    received.extend(data)
        answers = []
        while (cut := mbap.decode(received)) is not None:
            answers.append(cut[0])
            del received[: cut[1]]
        return answers
    finally:
        writer.close()
        await writer.wait_closed()


async def test_mbpoll_reads_the_simulator_as_a_modbus_tcp_converter() -> None:
    async with converter(DEVICES, pace=True) as (server, port):
        base = ["-m", "tcp", "-p", str(port), "-0", "-1", "-o", "1", "127.0.0.1"]
        code, out = await mbpoll("-a", "1", "-r", str(0x2620), "-c", "1", "-t", "4:float", *base)
        assert code == 0, out
        assert mbpoll_values(out) == {0x2620: "20.25"}
        code, out = await mbpoll("-a", "20", "-r", "0", "-c", "1", "-t", "4:float", *base)
        assert code == 0, out
        assert float(mbpoll_values(out)[0]) == pytest.approx(0.168, abs=1e-6)
        # The converter's own answer for a device that is not there: exception 0B.
        code, out = await mbpoll("-a", "9", "-r", "0", "-c", "1", *base)
        assert code != 0
        assert "Target device failed to respond" in out
        stats = server.bus.stats()
    assert stats["counters"]["mbap_0b"] == 1
    assert stats["timing_violations"] == 0


async def test_the_answer_keeps_the_transaction_id_and_unit() -> None:
    request = frames.read_request(1, 0x2620, 2)
    async with converter(DEVICES) as (_, port):
        (answer,) = await ask(port, mbap.from_rtu(0xBEEF, request.frame))
    assert (answer.transaction, answer.unit) == (0xBEEF, 1)
    assert answer.pdu == bytes.fromhex("03 04 00 00 41 a2")  # 20.25, CDAB


@pytest.mark.timing  # an answer's time held to 0.3 s
async def test_0b_comes_after_the_converters_timeout() -> None:
    request = frames.read_request(9, 0x0000, 1)
    async with converter(DEVICES, timeout_s=0.2, pace=True) as (_, port):
        reader, writer = await asyncio.open_connection("127.0.0.1", port)
        started = time.monotonic()
        writer.write(mbap.from_rtu(7, request.frame))
        answer = await asyncio.wait_for(reader.readexactly(9), timeout=2)
        took = time.monotonic() - started
        writer.close()
        await writer.wait_closed()
    assert answer == bytes.fromhex("00 07 00 00 00 03 09 83 0b")
    # The request and the answer it waited for on the wire (9600 8N1), then 0.2 s.
    assert 0.2 + 0.015 <= took < 0.2 + 0.015 + 0.3


async def test_a_unit_it_cannot_route_is_0a() -> None:
    async with converter(DEVICES) as (_, port):
        (answer,) = await ask(port, mbap.encode(1, 248, bytes.fromhex("03 00 00 00 01")))
    assert answer.pdu == bytes((0x83, mbap.GATEWAY_PATH_UNAVAILABLE))


async def test_a_stream_that_is_not_modbus_tcp_is_closed() -> None:
    async with converter(DEVICES) as (server, port):
        answers = await ask(port, b"\x00\x01\x00\x07\x00\x06\x01\x03\x00\x00\x00\x01")
        assert answers == []
        assert server.bus.counters["mbap_refused"] == 1


async def test_two_masters_are_served_one_at_a_time_with_the_gap() -> None:
    requests = [mbap.from_rtu(n, frames.read_request(1, 0x2620, 2).frame) for n in range(5)]
    async with converter(DEVICES, pace=True) as (server, port):
        first, second = await asyncio.gather(ask(port, *requests), ask(port, *requests))
        records = list(server.bus.frame_log)
        stats = server.bus.stats()
    assert [a.transaction for a in first] == [a.transaction for a in second] == list(range(5))
    assert stats["timing_violations"] == 0
    assert len(records) == 10
    gap = build_bus(parse_settings({"devices": DEVICES})).line.frame_gap_s(0.002)
    for before, after in itertools.pairwise(records):
        assert before.answer_at is not None
        assert after.start - before.answer_at >= gap


@pytest.mark.timing  # the read must reach the line within the 250 ms of the write's answer
async def test_a_request_inside_the_post_write_wait_is_ignored_and_answered_0b() -> None:
    """The converter does not know the H10's 250 ms: the master must; the referee says so."""
    write = frames.write_request(3, 0x2013, (0x0000, 0x41A8))  # compensation temperature 21
    read = frames.read_request(3, 0x2013, 2)
    async with converter(DEVICES, pace=True) as (server, port):
        answers = await ask(port, mbap.from_rtu(1, write.frame), mbap.from_rtu(2, read.frame))
        stats = server.bus.stats()
    assert [a.pdu[0] for a in answers] == [0x10, 0x83]
    assert answers[1].pdu[1] == mbap.GATEWAY_TARGET_FAILED
    assert stats["violations_by_rule"] == {"post_write_wait": 1}
