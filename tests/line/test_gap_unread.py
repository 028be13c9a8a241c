"""The gap counts from bytes the port holds, read or not: when the kernel is asked, and when not.

Before a request the line must have been silent for its gap. Bytes can wait in the
port's kernel buffer that the event loop has not read yet (a late answer or noise while
the process was busy elsewhere; the soak found a request sent 2 ms after such an answer),
so the line asks the kernel (one ioctl) before it sends. Where the gap's own timer woke
the wait, the loop had just read every port it watches in the same pass, and the ask is
left out unless the loop was held for more than a character after that wake.

On a real pseudo-terminal: the test writes the "device's" bytes to its master side.
"""

from __future__ import annotations

import asyncio
import os
import select
import time
from typing import TYPE_CHECKING

import pytest

from gateway.line.transports.serial_line import SerialLine
from gateway.line.transports.timer import DeadlineTimer
from gateway.wire.timing import LineFormat

if TYPE_CHECKING:
    from collections.abc import AsyncIterator

pytestmark = pytest.mark.line

# 1200 baud, 8N1: a character lasts 8.3 ms, so a loop that resumes the woken wait within
# that is not taken for a held one on a busy machine.
SLOW = LineFormat(baudrate=1200, parity="N", stopbits=1)
GAP_S = 0.02


class CountingLine(SerialLine):
    """A serial line that counts how often it asks the kernel for unread bytes."""

    asked = 0

    def _unread_input(self) -> bool:
        self.asked += 1
        return super()._unread_input()


class HeldAfterWake(DeadlineTimer):
    """The gap's timer, with the loop held after its first wake while the device sends."""

    def __init__(self, device_fd: int, tty_fd: int, hold_s: float) -> None:
        super().__init__()
        self._device_fd, self._tty_fd, self._hold_s = device_fd, tty_fd, hold_s
        self.held_until: float | None = None

    async def sleep_until(
        self, deadline: float, loop: asyncio.AbstractEventLoop | None = None
    ) -> bool:
        woken = await super().sleep_until(deadline, loop)
        if self.held_until is None:
            os.write(self._device_fd, b"\x55\xaa")
            in_kernel(self._tty_fd)
            time.sleep(self._hold_s)  # noqa: ASYNC251 - the loop held on purpose: nothing reads the port
            self.held_until = time.monotonic()
        return woken


def in_kernel(tty_fd: int) -> None:
    """Return once bytes written to the master side are readable on the port."""
    readable, _, _ = select.select([tty_fd], [], [], 2.0)
    assert readable, "the pseudo-terminal never passed the bytes on"


@pytest.fixture
async def pty_line() -> AsyncIterator[tuple[CountingLine, int, int]]:
    device_fd, tty_fd = os.openpty()
    line = CountingLine(port=os.ttyname(tty_fd), line=SLOW)
    await line.open()
    try:
        yield line, device_fd, tty_fd
    finally:
        await line.close()
        os.close(device_fd)
        os.close(tty_fd)


async def test_bytes_the_loop_has_not_read_restart_a_gap_that_was_over(
    pty_line: tuple[CountingLine, int, int],
) -> None:
    line, device_fd, tty_fd = pty_line
    line.last_frame_end = time.monotonic() - 1.0  # the gap is long over by the last frame
    os.write(device_fd, b"\x01\x02\x03")
    in_kernel(tty_fd)
    noticed_after = time.monotonic()  # no await since: the loop has not read them
    due = await line.wait_gap(GAP_S)
    assert line.asked >= 1
    assert due >= noticed_after + GAP_S  # the gap counted again from the bytes
    assert time.monotonic() >= due


async def test_a_gap_the_timer_woke_is_not_asked_of_the_kernel_again(
    pty_line: tuple[CountingLine, int, int],
) -> None:
    line, _, _ = pty_line
    start = time.monotonic()
    line.last_frame_end = start
    due = await line.wait_gap(GAP_S)
    assert due == pytest.approx(start + GAP_S, abs=1e-9)
    assert line.asked == 0  # woken by its timer: the loop had read the port just then
    # A gap over when asked for has no such wake: the kernel is asked.
    line.last_frame_end = time.monotonic() - 1.0
    await line.wait_gap(GAP_S)
    assert line.asked == 1


async def test_a_loop_held_after_the_wake_asks_and_the_bytes_restart_the_gap(
    pty_line: tuple[CountingLine, int, int],
) -> None:
    line, device_fd, tty_fd = pty_line
    timer = HeldAfterWake(device_fd, tty_fd, hold_s=3 * SLOW.character_s)
    line._timer = timer  # the hold between wake and resume needs the timer
    line.last_frame_end = time.monotonic()
    due = await line.wait_gap(GAP_S)
    assert timer.held_until is not None
    assert line.asked >= 1  # held longer than a character: the kernel was asked
    assert due >= timer.held_until + GAP_S  # the bytes sent meanwhile restarted the gap
    timer.close()
