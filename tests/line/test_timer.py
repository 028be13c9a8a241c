"""The deadline timer: never early, quiet when cancelled, and a fallback where it cannot run.

How close to the deadline it ends is a performance figure (bench/bus_efficiency.py prints
it), not asserted here by the wall clock.
"""

from __future__ import annotations

import asyncio
import contextlib
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
    await clock.sleep_until(time.monotonic() - 1.0)
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
    await clock.sleep_until(deadline)
    assert time.monotonic() >= deadline
    assert clock._fd is None
    clock.close()
