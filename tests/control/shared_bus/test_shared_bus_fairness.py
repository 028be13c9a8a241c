"""Other masters share the bus time fairly: one that pipelines long reads leaves another its part.

The gateway polls two simulated sensors (9600 8E1 on a pseudo-terminal). A greedy master
pipelines reads of the H10's 120 logbook registers (0.29 s on the wire each) and reads
none of its answers; a well-behaved master beside it (pymodbus) reads the tecLine's two
concentration registers, one at a time, as a SCADA does. The simulator's frame log says
who had the line and for how long.
"""

from __future__ import annotations

import asyncio
import socket
import struct
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import pytest
from pymodbus.client import AsyncModbusTcpClient

from tests.control.shared_bus.test_shared_bus import H10, TECLINE, Plant, _mbap, plant

if TYPE_CHECKING:
    from pathlib import Path

pytestmark = [pytest.mark.line, pytest.mark.timing]

GREEDY_READ = (0x0600, 120)  # H10 logbook: 8 + 245 bytes, 0.29 s at 9600 8E1
GREEDY_ANSWER = bytes([0x03, 240])  # function, byte count
GOOD_READ = (0x0000, 2)  # tecLine concentration: 8 + 9 bytes, 20 ms
GOOD_SECONDS = 8.0
GREEDY_ADDRESS = "127.0.0.1"
GOOD_ADDRESS = "127.0.0.2"  # the loopback interface answers to all of 127.0.0.0/8
BUSY = b"\x83\x06"
SHARE = 0.25  # shared_bus.bus_share's default
BURST_S = 2.0  # the window the share is kept over: a full bucket may go at once


def _read_pdu(address: int, count: int) -> bytes:
    return bytes([3]) + address.to_bytes(2, "big") + count.to_bytes(2, "big")


def pipeline(port: int, source: str, reads: int) -> socket.socket:
    """A connection from ``source`` that sent ``reads`` long reads at once and reads nothing."""
    sock = socket.create_connection(("127.0.0.1", port), source_address=(source, 0))
    pdu = _read_pdu(*GREEDY_READ)
    sock.sendall(b"".join(_mbap(n, H10, pdu) for n in range(reads)))
    return sock


def answers_so_far(sock: socket.socket) -> list[tuple[int, bytes]]:
    """The answers the connection was sent until now: (transaction id, PDU), as they came."""
    sock.settimeout(0.1)
    buffer = b""
    while True:
        try:
            chunk = sock.recv(65536)
        except TimeoutError:
            break
        if not chunk:
            break
        buffer += chunk
    found = []
    while len(buffer) >= 6 and len(buffer) >= 6 + int.from_bytes(buffer[4:6], "big"):
        length = int.from_bytes(buffer[4:6], "big")
        found.append((int.from_bytes(buffer[:2], "big"), buffer[7 : 6 + length]))
        buffer = buffer[6 + length :]
    return found


def reset(sock: socket.socket) -> None:
    """Close with a reset: what the gateway still had for it goes with the connection."""
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
    sock.close()


@dataclass(repr=False)
class Figures:
    """What the well-behaved master got beside the greedy one, and the line time of each."""

    right: int = 0
    wrong: list[object] = field(default_factory=list)
    longest_s: float = 0.0
    started: float = 0.0  # on the simulator's clock
    ended: float = 0.0
    good_s: float = 0.0  # line time of its reads
    greedy_s: float = 0.0  # line time of the greedy master's

    def __repr__(self) -> str:
        return (
            f"{self.right} right, {len(self.wrong)} not ({self.wrong[:5]}), longest wait "
            f"{self.longest_s:.2f} s; line time: good {self.good_s:.2f} s, greedy "
            f"{self.greedy_s:.2f} s in {self.ended - self.started:.1f} s"
        )


async def good_client(p: Plant, source: str, seconds: float) -> Figures:
    """Read the tecLine's concentration from ``source``, one request at a time, for ``seconds``."""
    expected = [p.device(TECLINE).registers.get(a, 0) for a in range(GOOD_READ[1])]
    client = AsyncModbusTcpClient(
        "127.0.0.1", port=p.tcp_port, source_address=(source, 0), timeout=5, retries=0
    )
    await client.connect()
    figures = Figures(started=bus_time(p))
    until = time.monotonic() + seconds
    try:
        while time.monotonic() < until:
            asked = time.monotonic()
            answer = await client.read_holding_registers(
                GOOD_READ[0], count=GOOD_READ[1], device_id=TECLINE
            )
            figures.longest_s = max(figures.longest_s, time.monotonic() - asked)
            if not answer.isError() and answer.registers == expected:
                figures.right += 1
            else:
                figures.wrong.append(getattr(answer, "exception_code", answer))
    finally:
        client.close()
    figures.ended = bus_time(p)
    figures.good_s = line_seconds(p, TECLINE, GOOD_READ, figures.started, figures.ended)
    figures.greedy_s = line_seconds(p, H10, GREEDY_READ, figures.started, figures.ended)
    return figures


def bus_time(p: Plant) -> float:
    """Now, on the simulator's clock (seconds since its bus started)."""
    return asyncio.get_running_loop().time() - p.simulator.bus.started


def line_seconds(p: Plant, device: int, read: tuple[int, int], since: float, until: float) -> float:
    """The line time the reads of ``read`` to ``device`` took, as the share counts it.

    The silence before the request (3.5 characters for both sensors), the request, the
    device's wait and its answer: the simulator sends an answer once its last byte would
    be on the wire (``answer_at``).
    """
    gap_s = p.simulator.bus.line.frame_gap_s()
    return float(
        sum(
            gap_s + f.answer_at - f.start
            for f in p.frames_to(device)
            if (f.address, f.quantity) == read and since <= f.start <= until and f.answer_at
        )
    )


def greedy_read_s(p: Plant) -> float:
    """One of the greedy master's reads on the line, its gap included."""
    line = p.simulator.bus.line
    return line.frame_gap_s() + line.wire_s(8 + 5 + 2 * GREEDY_READ[1])


def missed(p: Plant) -> int:
    return sum(h.missed_deadlines for h in p.state.health())


def assert_fair(p: Plant, figures: Figures) -> None:
    """Every read of the good master answered right (none waited past max_wait: 06), with
    its part of the share."""
    assert figures.wrong == [], figures
    # Both asked all along: half the share each, by line time. Start-time fair queueing
    # keeps the two within one request of each of them (Goyal et al. 1996), and the
    # window's ends may cut one more of the greedy master's.
    assert figures.good_s >= figures.greedy_s - 2 * greedy_read_s(p), figures
    # Together, the share and no more (and the full bucket they started with).
    window = figures.ended - figures.started
    assert figures.good_s + figures.greedy_s <= SHARE * (window + BURST_S) + 0.05, figures


@pytest.mark.parametrize(
    "good_source", [GOOD_ADDRESS, GREEDY_ADDRESS], ids=["another address", "the same address"]
)
async def test_a_client_pipelining_long_reads_leaves_another_its_part_of_the_share(
    tmp_path: Path, good_source: str
) -> None:
    async with plant(tmp_path, "shared_bus:\n  listen: [{host: 127.0.0.1, port: 0}]\n") as p:
        missed_before = missed(p)
        greedy = pipeline(p.tcp_port, GREEDY_ADDRESS, 30)
        figures = await good_client(p, good_source, GOOD_SECONDS)
        greedy_answers = await asyncio.to_thread(answers_so_far, greedy)
        reset(greedy)
        missed_after = missed(p)
        violations = list(p.simulator.bus.violations)
    assert_fair(p, figures)
    # The greedy master's answers so far, in the order asked: the device's registers, or
    # 06 where its reads asked for more than its half (one 0.29 s read per 2.3 s).
    assert [n for n, _ in greedy_answers] == list(range(len(greedy_answers)))
    assert {pdu[:2] for _, pdu in greedy_answers} <= {GREEDY_ANSWER, BUSY}
    assert missed_after == missed_before
    assert violations == []


async def test_a_client_on_many_connections_gets_one_addresss_part_and_no_more(
    tmp_path: Path,
) -> None:
    # Fifteen connections of one address, 20 long reads pipelined on each: more than the
    # eight requests that may wait on the line, all the time.
    shared = "shared_bus:\n  listen: [{host: 127.0.0.1, port: 0}]\n  max_pending: 8\n"
    async with plant(tmp_path, shared) as p:
        missed_before = missed(p)
        greedy = [pipeline(p.tcp_port, GREEDY_ADDRESS, 20) for _ in range(15)]
        await asyncio.sleep(0.2)  # they fill the queue first
        figures = await good_client(p, GOOD_ADDRESS, GOOD_SECONDS)
        greedy_answers = [await asyncio.to_thread(answers_so_far, sock) for sock in greedy]
        foreign = p.state.shared_bus.buses["basin"]  # after the answers: each 06 is counted
        refused = foreign.refused["queue_full"] + foreign.refused["no_share"]
        for sock in greedy:
            reset(sock)
        missed_after = missed(p)
        violations = list(p.simulator.bus.violations)
    assert_fair(p, figures)
    # The greedy master got 06 for what did not fit its part: its newest requests gave
    # their places in the full queue to the good master's, or waited past max_wait.
    busy = sum(pdu == BUSY for answers in greedy_answers for _, pdu in answers)
    assert 0 < busy <= refused
    for answers in greedy_answers:  # each connection's in the order asked
        assert [n for n, _ in answers] == list(range(len(answers)))
        assert {pdu[:2] for _, pdu in answers} <= {GREEDY_ANSWER, BUSY}
    assert missed_after == missed_before
    assert violations == []
