"""The line owner on a real pseudo-terminal, with the other end written by hand.

These tests put exact bytes at exact moments on the line, which the simulator (a correct
slave) never does: late answers of other devices ahead of the right one.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import shutil
import subprocess
import time
import tty
from typing import TYPE_CHECKING

import pytest
import serial

from gateway.config.echo import EchoMode
from gateway.errors import BusClosedError
from gateway.line.boundary import RequestOptions
from gateway.line.stats import ErrorKind
from gateway.line.transports.serial_line import SerialLine
from gateway.wire import frames
from gateway.wire.timing import LineFormat
from tests import unretrieved

if TYPE_CHECKING:
    from collections.abc import AsyncIterator, Callable, Iterator
    from pathlib import Path

pytestmark = [pytest.mark.line]

LINE = LineFormat(baudrate=9600, parity="N", stopbits=1)


def answer(device: int, registers: tuple[int, ...]) -> bytes:
    return frames.read_response(device, 0x03, registers)


@contextlib.asynccontextmanager
async def hand_wired(
    tmp_path: Path, *, echo: EchoMode = EchoMode.AUTO
) -> AsyncIterator[tuple[SerialLine, int]]:
    """A line open on a pty whose other end (the file descriptor yielded) the test writes."""
    master, slave = os.openpty()
    tty.setraw(slave)
    port = tmp_path / "ttyHAND"
    port.symlink_to(os.ttyname(slave))
    line = SerialLine(port=str(port), line=LINE, echo=echo)
    await line.open()
    try:
        yield line, master
    finally:
        with contextlib.suppress(serial.SerialException):  # a test may close it behind its back
            await line.close()
        for end in (master, slave):
            with contextlib.suppress(OSError):  # a test may have unplugged it (closed the master)
                os.close(end)


async def test_a_late_answer_of_another_device_does_not_end_the_wait(tmp_path: Path) -> None:
    """Device 20's late answer comes first; device 1's own answer 20 ms later is taken.

    Giving up at the foreign frame would put the next request on the line while device 1
    is still answering: a collision the soak found.
    """
    async with hand_wired(tmp_path) as (line, master):
        request = frames.read_request(1, 0x2620, 2)

        async def other_end() -> None:
            received = b""
            while len(received) < len(request.frame):
                await asyncio.sleep(0.001)
                try:
                    received += os.read(master, 64)
                except BlockingIOError:
                    continue
            os.write(master, answer(20, (0x1111, 0x2222)))  # someone else's late answer
            await asyncio.sleep(0.02)  # silence far longer than 3.5 characters
            os.write(master, answer(1, (0x0000, 0x41A2)))

        os.set_blocking(master, False)
        peer = asyncio.create_task(other_end())
        exchange = await line.transact(
            request, RequestOptions(timeout_s=0.2, gap_s=LINE.frame_gap_s())
        )
        await peer
        assert exchange is not None
        assert exchange.response.registers == (0x0000, 0x41A2)
        assert line.stats.errors[20, ErrorKind.STALE] == 1  # counted against its sender
        assert line.stats.errors[1, ErrorKind.WRONG_ADDRESS] == 0


async def test_bytes_the_event_loop_has_not_read_yet_restart_the_gap(tmp_path: Path) -> None:
    """A late answer still in the port's buffer when the gap looks over: wait again.

    The bytes arrive while the event loop is busy (here: no await between the write and
    the wait), so the receiver has not timestamped them. The gap must count from them.
    """
    async with hand_wired(tmp_path) as (line, master):
        await asyncio.sleep(0.1)  # the line has been quiet far longer than any gap
        gap_s = 0.02
        os.write(master, answer(20, (0x1111, 0x2222)))
        arrived = time.monotonic()
        time.sleep(0.005)  # noqa: ASYNC251 - busy elsewhere: the kernel has them, the loop not
        await line.wait_gap(gap_s)
        assert time.monotonic() - arrived >= gap_s


async def test_a_port_closed_under_the_line_is_not_an_unexpected_error(tmp_path: Path) -> None:
    """The port closes (unplugged) just as the gap is checked: a closed-port error or a
    normal return, never a crash in the check for unread bytes (the unplug test hit it)."""
    async with hand_wired(tmp_path) as (line, _):
        await asyncio.sleep(0.05)
        transport = line._transport  # the serial port under the transport
        assert transport is not None
        transport.get_extra_info("serial").close()
        with contextlib.suppress(BusClosedError):
            await line.wait_gap(0.0)


async def test_closing_a_line_whose_port_went_away_leaves_no_failed_task(tmp_path: Path) -> None:
    """The port vanishes (the pty's other end closes, as an unplugged adapter), the
    transport closes itself, then the bus owner closes the line: no task may fail.

    Aborting the transport a second time made pyserial-asyncio-fast run its closing task
    twice; the second called ``connection_lost`` on the protocol the first had cleared,
    and asyncio logged "Task exception was never retrieved" at every unplug.
    """
    with unretrieved.guard():
        async with hand_wired(tmp_path) as (line, master):
            receiver = line._inbox
            assert receiver is not None
            os.close(master)  # unplugged
            await asyncio.wait_for(receiver.lost.wait(), timeout=2)
            assert not line.is_open
            with pytest.raises(BusClosedError, match="went away"):
                line.flush_input(1)
            await line.close()
            await asyncio.sleep(0.2)  # any closing task of the transport has finished
        assert receiver.lost_reason is not None  # the transport said why, once


@pytest.fixture
def pty_bound_elsewhere(tmp_path: Path) -> Iterator[Path]:
    """A pty's slave bind-mounted at ``tmp_path/ttyUSB0``, as a container binds an adapter."""
    assert os.geteuid() == 0, "a bind mount needs root (scripts/test runs as root in CI)"
    mount, umount = shutil.which("mount"), shutil.which("umount")
    assert mount is not None, "mount is missing (util-linux)"
    assert umount is not None, "umount is missing (util-linux)"
    master, slave = os.openpty()
    port = tmp_path / "ttyUSB0"
    port.touch()
    subprocess.run([mount, "--bind", os.ttyname(slave), str(port)], check=True)
    try:
        yield port
    finally:
        subprocess.run([umount, "--lazy", str(port)], check=True)  # lazy: a failed open may hold it
        os.close(master)
        os.close(slave)


@pytest.mark.root
async def test_a_pseudo_terminal_bound_at_another_path_opens_with_parity(
    pty_bound_elsewhere: Path,
) -> None:
    """A pty reached through a bind mount (``/dev/ttyUSB0`` in the systemd test's container)
    is still a pty: parity stays off, which this kernel refuses on one with EINVAL.

    The path alone said "not a pty"; ``tcsetattr`` then raised ``termios.error`` (no
    OSError), which ended the whole gateway instead of the bus's retry.
    """
    line = SerialLine(
        port=str(pty_bound_elsewhere), line=LineFormat(baudrate=9600, parity="E", stopbits=1)
    )
    await line.open()
    assert line.is_open
    await line.close()


def held_up_at_the_next_wait(line: SerialLine, write: Callable[[], object]) -> list[float]:
    """At the line's next wait: ``write`` and hold the loop 10 ms, due just before its timer.

    The loop then runs the wait's timer in the pass it was held in, and hands the bytes
    over only in the next: as a process held by a CPU quota comes back to both at once.
    Returns the list that gets the moment of the hold's end (empty: it never ran).
    """
    inbox = line._inbox
    assert inbox is not None
    loop = asyncio.get_running_loop()
    wait = inbox.wait
    held: list[float] = []

    def write_and_hold() -> None:
        write()
        time.sleep(0.01)  # held up: the bytes reach the kernel, the loop does not run
        held.append(time.monotonic())

    async def wait_after_the_bytes(timeout_s: float) -> None:
        if not held:
            loop.call_at(loop.time() + timeout_s - 1e-6, write_and_hold)
        await wait(timeout_s)

    inbox.wait = wait_after_the_bytes  # type: ignore[method-assign]
    return held


async def test_an_answer_the_kernel_holds_at_the_deadline_is_taken(tmp_path: Path) -> None:
    """The answer is in the port's buffer when the wait's timer wakes the transaction.

    Giving up then counted a timeout and a stale frame, and held the device for its
    late-answer window (bench/budget.py under a 40 % quota: 1-5 missed deadlines in 7
    runs of 35, every one after such a timeout).
    """
    async with hand_wired(tmp_path) as (line, master):
        held = held_up_at_the_next_wait(line, lambda: os.write(master, answer(1, (0x0000, 0x41A2))))
        request = frames.read_request(1, 0x2620, 2)
        exchange = await line.transact(
            request, RequestOptions(timeout_s=0.05, gap_s=LINE.frame_gap_s())
        )
        assert held, "the answer was never written: the test did not set the race up"
        assert exchange is not None
        assert exchange.response.registers == (0x0000, 0x41A2)
        assert line.stats.errors[1, ErrorKind.TIMEOUT] == 0
        assert line.stats.errors[1, ErrorKind.STALE] == 0


async def test_an_echo_the_kernel_holds_at_its_deadline_is_read(tmp_path: Path) -> None:
    """``echo: on``, and the echo and the answer wait in the port's buffer at the echo's
    deadline: read, not "this adapter does not echo ... set `echo: off`" (wrong advice)."""
    async with hand_wired(tmp_path, echo=EchoMode.ON) as (line, master):
        request = frames.read_request(1, 0x2620, 2)
        held = held_up_at_the_next_wait(
            line, lambda: os.write(master, request.frame + answer(1, (0x0000, 0x41A2)))
        )
        exchange = await line.transact(
            request, RequestOptions(timeout_s=0.05, gap_s=LINE.frame_gap_s())
        )
        assert held, "the echo was never written: the test did not set the race up"
        assert exchange is not None
        assert exchange.response.registers == (0x0000, 0x41A2)
        assert line.stats.errors[1, ErrorKind.ECHO_MISMATCH] == 0
