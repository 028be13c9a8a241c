"""What one other master can do to the line: floods, clients that never read, odd RTU frames.

The gateway polls two simulated sensors (9600 8E1 on a pseudo-terminal) while another
master, in a process of its own (``tests.flood_client``), pipelines requests at it as fast
as TCP takes them. The simulator's frame log is the judge of the polling: it holds the
time every request reached the line.
"""

from __future__ import annotations

import asyncio
import itertools
import json
import random
import socket
import sys
from pathlib import Path
from typing import Any

import pytest

from gateway.config.shared_bus import DEFAULT_RATE_LIMIT
from gateway.control.shared_bus import listener
from gateway.publish.prometheus.shared_bus import shared_bus_families
from gateway.wire import frames
from tests import paths
from tests.control.shared_bus.test_shared_bus import H10, TECLINE, Plant, _mbap, _raw, plant

pytestmark = [pytest.mark.line, pytest.mark.timing]

ROOT = paths.ROOT
POLL_S = 0.5
# A poll that comes due while the other sensor's transaction holds the line waits it out
# (the H10 answers some reads in 0.24 s), then the loop's turn, under the flood, on 2 cores.
TURN_S = 0.1


async def flood(port: int, unit: int, seconds: float, pdu: str = "0300000002") -> dict[str, Any]:
    """Run ``tests.flood_client`` against ``port``: what it sent, and the answers it read."""
    process = await asyncio.create_subprocess_exec(
        sys.executable,
        "-m",
        "tests.flood_client",
        "--port",
        str(port),
        "--unit",
        str(unit),
        "--pdu",
        pdu,
        "--seconds",
        str(seconds),
        cwd=ROOT,
        stdout=asyncio.subprocess.PIPE,
    )
    assert process.stdout is not None
    assert await asyncio.wait_for(process.stdout.readline(), timeout=10) == b"connected\n"
    output = await asyncio.wait_for(process.stdout.read(), timeout=seconds + 10)
    assert await process.wait() == 0
    result: dict[str, Any] = json.loads(output)
    return result


def largest_gaps(p: Plant, since: float, until: float) -> dict[int, float]:
    """Per sensor, the longest time between two requests the line carried to it."""
    gaps: dict[int, float] = {}
    for address in (TECLINE, H10):
        starts = (
            [since] + [f.start for f in p.frames_to(address) if since <= f.start <= until] + [until]
        )
        gaps[address] = max(b - a for a, b in itertools.pairwise(starts))
    return gaps


def allowed_gap(p: Plant, since: float, until: float) -> float:
    """The longest wait between two polls of a sensor that leaves its rate kept: the poll
    interval, the longest transaction the line carried meanwhile, and the loop's turn."""
    held = [
        f.answer_at - f.start
        for f in p.simulator.bus.frame_log
        if since <= f.start <= until and f.answer_at is not None
    ]
    return POLL_S + max(held, default=0.0) + TURN_S


def bus_time(p: Plant) -> float:
    """Now, on the simulator's clock (seconds since its bus started)."""
    return asyncio.get_running_loop().time() - p.simulator.bus.started


def missed(p: Plant) -> int:
    return sum(h.missed_deadlines for h in p.state.health())


async def test_a_client_pipelining_unknown_unit_ids_does_not_stop_the_polling(
    tmp_path: Path,
) -> None:
    shared = "shared_bus:\n  listen: [{host: 127.0.0.1, port: 0}]\n"
    async with plant(tmp_path, shared, poll_interval=POLL_S) as p:
        await asyncio.sleep(1.0)  # identity and the first slow reads are through
        missed_before, since = missed(p), bus_time(p)
        result = await flood(p.tcp_port, 99, 4.0)
        until = bus_time(p)
        gaps, allowed = largest_gaps(p, since, until), allowed_gap(p, since, until)
        missed_after = missed(p)
        other = p.state.shared_bus.clients["other"]
    print(f"largest gaps between polls (s): {gaps}, allowed {allowed:.3f}")  # noqa: T201
    assert result["answers"]
    assert set(result["answers"]) == {"830a"}
    assert all(gap <= allowed for gap in gaps.values()), (gaps, allowed)
    assert missed_after == missed_before
    # Every answer the client read was counted; the gateway may have answered a few more
    # that were on their way when the client stopped reading (a second's worth at most).
    read = result["answers"]["830a"]
    assert read <= other.refused["unknown_unit"] <= read + int(DEFAULT_RATE_LIMIT)


async def test_a_client_pipelining_unknown_unit_ids_is_answered_in_turn_with_the_polls(
    tmp_path: Path,
) -> None:
    # No rate limit to speak of: answering in turn (a yield per frame) is what keeps the
    # polls; the limit only spares the process the work.
    shared = "shared_bus:\n  listen: [{host: 127.0.0.1, port: 0}]\n  rate_limit: 10000\n"
    async with plant(tmp_path, shared, poll_interval=POLL_S) as p:
        await asyncio.sleep(1.0)
        missed_before, since = missed(p), bus_time(p)
        result = await flood(p.tcp_port, 99, 4.0)
        until = bus_time(p)
        gaps, allowed = largest_gaps(p, since, until), allowed_gap(p, since, until)
        missed_after = missed(p)
    assert result["answers"]["830a"] > 2_000  # far more than the default limit lets through
    assert set(result["answers"]) == {"830a"}
    assert all(gap <= allowed for gap in gaps.values()), (gaps, allowed)
    assert missed_after == missed_before


async def test_a_client_pipelining_cache_hits_does_not_stop_the_polling(tmp_path: Path) -> None:
    shared = (
        "shared_bus:\n"
        "  listen: [{host: 127.0.0.1, port: 0}]\n"
        "  clients:\n"
        "    - {name: scada, networks: [127.0.0.0/8], cache_max_age: 5.0}\n"
    )
    async with plant(tmp_path, shared, poll_interval=POLL_S) as p:
        await asyncio.sleep(1.0)
        missed_before, since = missed(p), bus_time(p)
        on_the_line = len(p.frames_to(TECLINE))
        result = await flood(p.tcp_port, TECLINE, 4.0, pdu="0300000006")
        until = bus_time(p)
        gaps, allowed = largest_gaps(p, since, until), allowed_gap(p, since, until)
        polls = len(p.frames_to(TECLINE)) - on_the_line
        missed_after = missed(p)
        scada = p.state.shared_bus.clients["scada"]
    answered = result["answers"]["03"]
    assert set(result["answers"]) == {"03"}  # every one the device's registers, from the cache
    # The default limit: a second's worth at once, then 50 a second (the last may be cut off).
    assert 50 + 50 * 4.0 - 5 <= answered <= 50 + 50 * 4.0 + 5
    assert answered <= scada.cache_answers <= answered + int(DEFAULT_RATE_LIMIT)  # as above
    assert scada.throttled_s > 3.0  # the rest of the time it waited, reading nothing
    assert all(gap <= allowed for gap in gaps.values()), (gaps, allowed)
    assert missed_after == missed_before
    # The line carried the gateway's own polls only (a few reads per poll), not the flood.
    assert polls <= 4 * (until - since) / POLL_S


async def test_requests_over_the_rate_wait_and_past_max_wait_are_shed_with_06(
    tmp_path: Path,
) -> None:
    shared = (
        "shared_bus:\n  listen: [{host: 127.0.0.1, port: 0}]\n  max_wait: 0.5\n  rate_limit: 1\n"
    )
    async with plant(tmp_path, shared) as p:
        reader, writer = await asyncio.open_connection("127.0.0.1", p.tcp_port)
        started = asyncio.get_running_loop().time()
        writer.write(b"".join(_mbap(n, 99, bytes.fromhex("0300000001")) for n in range(5)))
        answers, times = [], []
        for _ in range(5):
            answers.append(await asyncio.wait_for(reader.readexactly(9), timeout=5))
            times.append(asyncio.get_running_loop().time() - started)
        writer.close()
        other = p.state.shared_bus.clients["other"]
        families = {
            (s.name, tuple(sorted(s.labels.items()))): s.value
            for family in shared_bus_families(p.state)
            for s in family.samples
        }
    # One token a second, a burst of one: the first at once; the second's turn would come
    # after 1 s, past max_wait: 06 after 0.5 s; the third's comes then (0.5 s refilled);
    # and so on. Transaction ids and unit kept.
    assert [a[7:] for a in answers] == [bytes.fromhex(c) for c in ("830A", "8306") * 2 + ("830A",)]
    assert [a[:2] for a in answers] == [n.to_bytes(2, "big") for n in range(5)]
    assert [round(t, 1) for t in times] == pytest.approx([0.0, 0.5, 1.0, 1.5, 2.0], abs=0.15)
    assert other.shed["rate_limit"] == 2
    assert other.exceptions[6] == 2
    assert other.throttled_s == pytest.approx(2.0, abs=0.05)
    other_client = (("client", "other"),)
    assert families["gateway_shared_bus_shed_total", (*other_client, ("reason", "rate_limit"))] == 2
    assert families["gateway_shared_bus_throttled_seconds_total", other_client] == pytest.approx(
        2.0, abs=0.05
    )
    assert families["gateway_shared_bus_requests_total", (*other_client, ("function", "03"))] == 5


def _sockets(port: int) -> list[tuple[int, int, str]]:
    """The kernel's TCP sockets with ``port`` at one end: (local port, remote port, state)."""
    found = []
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        for line in Path(table).read_text(encoding="ascii").splitlines()[1:]:
            fields = line.split()
            local, remote = (int(f.rsplit(":", 1)[1], 16) for f in fields[1:3])
            if port in {local, remote}:
                found.append((local, remote, TCP_STATES.get(fields[3], fields[3])))
    return found


def _read_to_the_end(sock: socket.socket) -> str:
    """What the client finds after what was delivered: ``reset`` or ``eof``."""
    sock.settimeout(5.0)
    while True:
        try:
            if not sock.recv(1 << 20):
                return "eof"
        except ConnectionResetError:
            return "reset"


TCP_STATES = {"01": "ESTABLISHED", "04": "FIN_WAIT1", "06": "TIME_WAIT", "0A": "LISTEN"}


async def test_a_client_that_reads_no_answers_is_reset_and_its_socket_is_gone(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # The client's wait shrunk from 10 s: how long is not the point, that the socket goes is.
    monkeypatch.setattr(listener, "DRAIN_TIMEOUT_S", 1.0)
    shared = (
        "shared_bus:\n"
        "  listen: [{host: 127.0.0.1, port: 0}]\n"
        "  max_connections: 1\n"
        "  rate_limit: 10000\n"
        "  clients:\n"
        "    - {name: scada, networks: [127.0.0.0/8], cache_max_age: 60}\n"
    )
    async with plant(tmp_path, shared) as p:
        sock = socket.socket()
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)  # before the handshake
        sock.connect(("127.0.0.1", p.tcp_port))
        sock.settimeout(0.0)  # non-blocking: send what the kernel takes
        mine = sock.getsockname()[1]
        # 123 registers of the H10's diagnostics, read at its start, from the cache: 255
        # bytes back for each 12 sent. 40,000 of them: 10 MB of answers, more than the
        # kernel buffers of both ends hold.
        requests = b"".join(_mbap(n, H10, bytes.fromhex("030600007B")) for n in range(40_000))
        sent = 0
        while sent < len(requests):
            try:
                sent += sock.send(requests[sent : sent + 65536])
            except BlockingIOError:
                await asyncio.sleep(0.01)  # the gateway reads no more for now
            except ConnectionResetError:
                break
        held = _sockets(p.tcp_port)
        # Meanwhile the connection counts: another client is turned away.
        reader, writer = await asyncio.open_connection("127.0.0.1", p.tcp_port)
        turned_away = await asyncio.wait_for(reader.read(), timeout=5)
        writer.close()
        # The kernel takes megabytes of answers before a send blocks (its buffer grows to
        # tcp_wmem's 4 MiB): at some 2.6 MB/s that and the wait take a few seconds.
        for _ in range(200):
            if p.state.shared_bus.clients["scada"].closed["not_reading"]:
                break
            await asyncio.sleep(0.1)
        await asyncio.sleep(0.1)
        after = [s for s in _sockets(p.tcp_port) if mine in s[:2]]
        ending = _read_to_the_end(sock)
        sock.close()
        # The place is free again.
        answer = await _raw(p.tcp_port, _mbap(1, TECLINE, bytes.fromhex("0300000002")))
        closed = p.state.shared_bus.clients["scada"].closed
    assert sent > 0
    assert (p.tcp_port, mine, "ESTABLISHED") in held  # the gateway's end, answers queued
    assert turned_away == b""
    assert closed["not_reading"] == 1
    assert ending == "reset"
    assert after == []  # neither end left: not ESTABLISHED, not FIN_WAIT, not TIME_WAIT
    assert answer[7:9] == b"\x03\x04"


async def _rtu_answer(reader: asyncio.StreamReader) -> bytes:
    """One RTU answer: an exception (5 bytes) or a read's (by its byte count)."""
    head = await asyncio.wait_for(reader.readexactly(3), timeout=5)
    if head[1] & 0x80:
        return head + await asyncio.wait_for(reader.readexactly(2), timeout=5)
    return head + await asyncio.wait_for(reader.readexactly(head[2] + 2), timeout=5)


def _rtu(body: bytes) -> bytes:
    return body + frames.crc16(body)


RTU_SHARED = "shared_bus:\n  listen: [{host: 127.0.0.1, port: 0, framing: rtu}]\n"


async def test_rtu_over_tcp_answers_report_server_id_and_device_identification_with_01(
    tmp_path: Path,
) -> None:
    async with plant(tmp_path, RTU_SHARED) as p:
        reader, writer = await asyncio.open_connection("127.0.0.1", p.rtu_port)
        server_id = _rtu(bytes([TECLINE, 0x11]))  # 4 bytes
        identification = _rtu(bytes([TECLINE, 0x2B, 0x0E, 0x01, 0x00]))  # 7 bytes
        read = frames.read_request(TECLINE, 0x0000, 2).frame
        answers = []
        for frame in (server_id, identification, read):
            writer.write(frame)
            answers.append(await _rtu_answer(reader))
        # A client that does not wait: the three at once, cut where their lengths say.
        writer.write(server_id + identification + read)
        pipelined = [await _rtu_answer(reader) for _ in range(3)]
        writer.close()
        registers = p.device(TECLINE).registers
        logged = [f.function for f in p.frames_to(TECLINE)]
    words = [registers.get(0, 0), registers.get(1, 0)]
    expected = [
        frames.exception_response(TECLINE, 0x11, 0x01),
        frames.exception_response(TECLINE, 0x2B, 0x01),
        frames.read_response(TECLINE, 3, words),
    ]
    assert answers == expected
    assert pipelined == expected
    assert set(logged) <= {3, 4}  # neither went on the line


# side_by_side: its time is 514 silences of 50 ms (RTU_SILENCE_S), each ending a frame of
# a function whose length the framer cannot know, slept through (26.8 s beside two others,
# 26.9 s alone).
@pytest.mark.side_by_side
async def test_rtu_over_tcp_frames_of_every_length_are_answered_one_by_one(
    tmp_path: Path,
) -> None:
    rng = random.Random(22)  # noqa: S311 - fuzz data, nothing secret
    unused = [f for f in range(1, 128) if f not in {3, 4, 6, 16}]
    async with plant(tmp_path, RTU_SHARED) as p:
        before = len(p.simulator.bus.frame_log)
        reader, writer = await asyncio.open_connection("127.0.0.1", p.rtu_port)
        wrong: list[tuple[int, bytes, bytes]] = []
        for length in range(4, 261):
            # A function no family uses, and one they use at a length not its own.
            functions = [rng.choice(unused)]
            if length != 8:  # a read of its own length may be a valid one
                functions.append(rng.choice([3, 4, 6]))
            for function in functions:
                body = bytes([TECLINE, function]) + rng.randbytes(length - 4)
                writer.write(_rtu(body))
                answer = await _rtu_answer(reader)
                code = 0x01 if function in unused else 0x03
                if answer != frames.exception_response(TECLINE, function, code):
                    wrong.append((length, body, answer))
        writer.write(frames.read_request(TECLINE, 0x0000, 2).frame)
        last = await _rtu_answer(reader)  # the same connection, still in step
        writer.close()
        foreign = [f for f in list(p.simulator.bus.frame_log)[before:] if f.function not in {3, 4}]
        client = p.state.shared_bus.clients["other"]
    assert wrong == []
    assert last[:3] == bytes([TECLINE, 3, 4])
    assert foreign == []
    assert client.refused["malformed_frame"] == 0


async def test_a_connection_is_read_no_further_than_max_in_flight_requests_ahead(
    tmp_path: Path,
) -> None:
    shared = (
        "shared_bus:\n  listen: [{host: 127.0.0.1, port: 0}]\n  max_in_flight: 4\n  rate_limit: 2\n"
    )
    request = _mbap(1, 99, bytes.fromhex("0300000001"))  # 12 bytes
    async with plant(tmp_path, shared) as p:
        reader, writer = await asyncio.open_connection("127.0.0.1", p.tcp_port)
        writer.write(request * 1000)  # all at once, as a pipelining client does
        await asyncio.sleep(2.0)
        other = p.state.shared_bus.clients["other"]
        answered, received = other.refused["unknown_unit"], other.received_bytes
        got = await asyncio.wait_for(reader.readexactly(9 * answered), timeout=5)
        writer.close()
    # Two a second, a burst of two: some six answered in 2 s. The socket was read only
    # when no whole request was left, 4 requests' worth of the smallest (32 bytes) a time:
    # what the gateway took in is what it answered and the few it held, not 12 kB.
    assert 5 <= answered <= 7
    assert got == _mbap(1, 99, bytes.fromhex("830A")) * answered
    assert received <= 12 * answered + 4 * 8 + 12


async def test_a_client_that_ends_its_side_first_still_reads_every_answer(
    tmp_path: Path,
) -> None:
    async with plant(tmp_path, "shared_bus:\n  listen: [{host: 127.0.0.1, port: 0}]\n") as p:
        reader, writer = await asyncio.open_connection("127.0.0.1", p.tcp_port)
        writer.write(b"".join(_mbap(n, 99, bytes.fromhex("0300000001")) for n in range(3)))
        writer.write_eof()  # half-closed: sent all it will
        rest = await asyncio.wait_for(reader.read(), timeout=5)  # until the gateway's end
        writer.close()
        await asyncio.sleep(0.1)
        closed = dict(p.state.shared_bus.clients["other"].closed)
    assert rest == b"".join(_mbap(n, 99, bytes.fromhex("830A")) for n in range(3))
    assert closed == {"eof": 1}
