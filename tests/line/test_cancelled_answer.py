"""A transaction cancelled after its request went out: the line waits for the answer still due.

The gateway stops waiting when a worker is stopped or paused for a command; the device
does not, and its answer comes all the same. The next request on the line, sent at once,
went out into that answer: the device heard a collision and the answer was taken for
noise (or, come before the next request, counted a stale frame of the device). Now the
next transaction waits for the answer, or for the cancelled one's timeout, keeps the gap
after it, and drops it uncounted.

On a real pseudo-terminal: the test plays the device on its master side.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import select
import time
import tty
from typing import TYPE_CHECKING

import pytest

from gateway.line.boundary import RequestOptions
from gateway.line.transports.serial_line import SerialLine
from gateway.wire import frames
from gateway.wire.timing import LineFormat
from tests.waiting import eventually

if TYPE_CHECKING:
    from collections.abc import AsyncIterator
    from pathlib import Path

    from gateway.line.boundary import Exchange

pytestmark = [pytest.mark.line]

LINE = LineFormat(baudrate=9600, parity="N", stopbits=1)
GAP_S = LINE.frame_gap_s()
FIRST = frames.read_request(1, 0x2620, 2)
SECOND = frames.read_request(1, 0x2630, 2)
SECOND_VALUES = (0x4148, 0x0000)
# No request may follow the cancelled one within this: its answer is still due. Long
# enough for a request sent at once to have reached the pseudo-terminal on a busy machine.
HELD_S = 0.3


@contextlib.asynccontextmanager
async def device_side(tmp_path: Path) -> AsyncIterator[tuple[SerialLine, int]]:
    """A line open on a pty; the test reads and writes the other end (the descriptor)."""
    master, slave = os.openpty()
    tty.setraw(slave)
    port = tmp_path / "ttyDEVICE"
    port.symlink_to(os.ttyname(slave))
    line = SerialLine(port=str(port), line=LINE)
    await line.open()
    try:
        yield line, master
    finally:
        await line.close()
        for end in (master, slave):
            os.close(end)


async def read_frame(master: int, size: int, *, within_s: float) -> tuple[bytes, float]:
    """The next ``size`` bytes the line sends, and when the first of them could be read."""
    loop = asyncio.get_running_loop()
    data = b""
    first_at = 0.0
    deadline = time.monotonic() + within_s
    while len(data) < size:
        left = deadline - time.monotonic()
        readable: list[int]
        readable, _, _ = await loop.run_in_executor(None, select.select, [master], [], [], left)
        assert readable, f"the line sent {data.hex(' ') or 'nothing'} within {within_s} s"
        if not data:
            first_at = time.monotonic()
        data += os.read(master, size - len(data))
    return data, first_at


async def nothing_sent(master: int, within_s: float) -> bool:
    loop = asyncio.get_running_loop()
    readable: list[int]
    readable, _, _ = await loop.run_in_executor(None, select.select, [master], [], [], within_s)
    return not readable


async def cancelled_once_sent(line: SerialLine, master: int, options: RequestOptions) -> None:
    """Send :data:`FIRST`, then cancel its transaction once the device has it."""
    first = asyncio.create_task(line.transact(FIRST, options))
    request, _ = await read_frame(master, len(FIRST.frame), within_s=2.0)
    assert request == FIRST.frame
    first.cancel()
    with contextlib.suppress(asyncio.CancelledError):
        await first
    assert first.cancelled()


async def answer(master: int, request: frames.Request, registers: tuple[int, ...]) -> None:
    """Answer ``request`` as the device does: not before both frames took their wire time.

    A pseudo-terminal carries bytes at once; an answer sooner than the wire allows is not
    the device's (the line passes over it).
    """
    frame = frames.read_response(request.device, 0x03, registers)
    await asyncio.sleep((len(request.frame) + len(frame)) * LINE.character_s)
    os.write(master, frame)


async def second_answered(master: int, second: asyncio.Task[Exchange | None]) -> float:
    """:data:`SECOND` goes out and the device answers it; when it went out (answer checked)."""
    request, sent_at = await read_frame(master, len(SECOND.frame), within_s=5.0)
    assert request == SECOND.frame
    await answer(master, SECOND, SECOND_VALUES)
    exchange = await second
    assert exchange is not None
    assert exchange.response.registers == SECOND_VALUES
    return sent_at


def errors_of_device_1(line: SerialLine) -> dict[str, int]:
    """Every failure counted against device 1, by kind."""
    return {kind: n for (device, kind), n in line.stats.errors.items() if device == 1 and n}


async def test_the_next_request_waits_for_the_answer_still_due_and_its_gap(tmp_path: Path) -> None:
    async with device_side(tmp_path) as (line, master):
        options = RequestOptions(timeout_s=2.0, gap_s=GAP_S)
        await cancelled_once_sent(line, master, options)
        second = asyncio.create_task(line.transact(SECOND, options))
        assert await nothing_sent(master, HELD_S), "a request went out into the answer still due"
        answered_at = time.monotonic()
        os.write(master, frames.read_response(1, 0x03, (0x0000, 0x41A2)))
        sent_at = await second_answered(master, second)
        # 3.5 characters after the answer's last byte (9600 8N1: 4.01 ms)
        assert sent_at - answered_at >= GAP_S
        assert errors_of_device_1(line) == {}
        assert line.late_answer is None


async def test_an_answer_come_meanwhile_is_dropped_not_counted_stale(tmp_path: Path) -> None:
    async with device_side(tmp_path) as (line, master):
        options = RequestOptions(timeout_s=2.0, gap_s=GAP_S)
        await cancelled_once_sent(line, master, options)
        os.write(master, frames.read_response(1, 0x03, (0x0000, 0x41A2)))
        inbox = line._inbox  # the answer in the line's hands: the case set up
        assert inbox is not None
        await eventually(lambda: len(inbox.buffer) == 9, within_s=2.0)
        await second_answered(master, asyncio.create_task(line.transact(SECOND, options)))
        assert errors_of_device_1(line) == {}  # before: one stale frame of the device


async def test_no_answer_holds_the_line_for_the_cancelled_timeout_only(tmp_path: Path) -> None:
    async with device_side(tmp_path) as (line, master):
        timeout_s = 0.5
        options = RequestOptions(timeout_s=timeout_s, gap_s=GAP_S)
        first_sent = time.monotonic()
        await cancelled_once_sent(line, master, options)
        sent_at = await second_answered(master, asyncio.create_task(line.transact(SECOND, options)))
        # not before the cancelled request's own timeout, counted from its end on the wire
        assert sent_at - first_sent >= timeout_s
        assert errors_of_device_1(line) == {}  # the cancelled request's timeout is not the device's


async def test_a_line_opened_again_owes_nothing(tmp_path: Path) -> None:
    async with device_side(tmp_path) as (line, master):
        options = RequestOptions(timeout_s=5.0, gap_s=GAP_S)
        await cancelled_once_sent(line, master, options)
        await line.close()
        await line.open()
        opened_at = time.monotonic()
        sent_at = await second_answered(master, asyncio.create_task(line.transact(SECOND, options)))
        assert sent_at - opened_at < 1.0  # not after the cancelled request's 5 s timeout


async def test_noise_instead_of_the_answer_holds_the_line_to_the_timeout_uncounted(
    tmp_path: Path,
) -> None:
    """Garbage where the answer was due (a collision, a bad earth): the line keeps waiting
    out the cancelled request's timeout, sends after the gap, and counts no noise."""
    async with device_side(tmp_path) as (line, master):
        timeout_s = 0.5
        options = RequestOptions(timeout_s=timeout_s, gap_s=GAP_S)
        first_sent = time.monotonic()
        await cancelled_once_sent(line, master, options)
        second = asyncio.create_task(line.transact(SECOND, options))
        os.write(master, b"\x00\xff\x55\xaa\x13")  # no frame of any device
        sent_at = await second_answered(master, second)
        assert sent_at - first_sent >= timeout_s
        assert errors_of_device_1(line) == {}
