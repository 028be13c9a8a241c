"""The deadline timer: never early, quiet when cancelled, and a fallback where it cannot run.

How close to the deadline it ends is a performance figure (bench/bus_efficiency.py prints
it), not asserted here by the wall clock.
"""

from __future__ import annotations

import asyncio
import contextlib
import socket
import time

import pytest

from gateway.line.transports import timer
from gateway.line.transports.timer import DeadlineTimer


async def test_a_wait_never_ends_before_its_deadline() -> None:
    clock = DeadlineTimer()
    try:
        for delay in (0.0003, 0.001, 0.0025, 0.0):
            deadline = time.monotonic() + delay
            await clock.sleep_until(deadline)
            assert time.monotonic() >= deadline
    finally:
        clock.close()


async def test_a_deadline_in_the_past_returns_at_once() -> None:
    clock = DeadlineTimer()
    assert await clock.sleep_until(time.monotonic() - 1.0) is False  # no wake: nothing polled
    clock.close()


async def test_a_wake_by_the_timer_says_so_and_the_port_was_read_in_its_pass() -> None:
    """What the line relies on to skip asking the kernel: the wake's pass read every port."""
    clock = DeadlineTimer()
    loop = asyncio.get_running_loop()
    reader, writer = socket.socketpair()
    received = bytearray()
    loop.add_reader(reader.fileno(), lambda: received.extend(reader.recv(64)))
    try:
        deadline = time.monotonic() + 0.01
        writer.send(b"late")  # readable long before the deadline; the loop reads it meanwhile
        assert await clock.sleep_until(deadline, loop) is True
        assert received == b"late"
        # Bytes that arrive during the wait, read in the pass that wakes it at the latest.
        writer.send(b"x")
        assert await clock.sleep_until(time.monotonic() + 0.005) is True
        assert received == b"latex"
    finally:
        loop.remove_reader(reader.fileno())
        reader.close()
        writer.close()
        clock.close()


async def test_a_cancelled_wait_leaves_the_timer_usable() -> None:
    clock = DeadlineTimer()
    try:
        waiting = asyncio.create_task(clock.sleep_until(time.monotonic() + 0.05))
        await asyncio.sleep(0.005)
        waiting.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await waiting
        await asyncio.sleep(0.06)  # the old deadline passes: nothing fires for nobody
        deadline = time.monotonic() + 0.002
        await clock.sleep_until(deadline)
        assert time.monotonic() >= deadline
    finally:
        clock.close()


async def test_close_then_wait_again_opens_a_new_timer() -> None:
    clock = DeadlineTimer()
    await clock.sleep_until(time.monotonic() + 0.001)
    clock.close()
    clock.close()  # idempotent
    deadline = time.monotonic() + 0.001
    await clock.sleep_until(deadline)
    assert time.monotonic() >= deadline
    clock.close()


async def test_without_a_timerfd_the_wait_falls_back_to_the_event_loop(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setattr(timer, "_LIBC", None)
    clock = DeadlineTimer()
    deadline = time.monotonic() + 0.002
    assert await clock.sleep_until(deadline) is False  # the loop's own timer: no such promise
    assert time.monotonic() >= deadline
    assert clock._fd is None
    clock.close()
