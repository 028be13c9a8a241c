"""The deadline timer: never early, quiet when cancelled, and a fallback where it cannot run.

How close to the deadline it ends is a performance figure (bench/bus_efficiency.py prints
it), not asserted here by the wall clock.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import socket
import time

import pytest

from gateway.line.engine.lateness import LoopWatch
from gateway.line.transports import timer
from gateway.line.transports.timer import DeadlineTimer
from tests.waiting import eventually


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


async def test_a_wake_resolves_its_waiter_at_the_deadline_never_before() -> None:
    """An answer's wait: the line's timer ends it at its timeout (no timer of the loop)."""
    clock = DeadlineTimer()
    loop = asyncio.get_running_loop()
    try:
        for delay in (0.002, 0.0005):
            waiter: asyncio.Future[None] = loop.create_future()
            now = time.monotonic()
            assert clock.wake(waiter, now + delay, now) is True
            await waiter
            assert time.monotonic() >= now + delay
            clock.unwake(waiter)
        # Bytes first: the waiter is resolved by them, and the timer wakes nobody after.
        waiter = loop.create_future()
        now = time.monotonic()
        assert clock.wake(waiter, now + 0.02, now) is True
        waiter.set_result(None)
        clock.unwake(waiter)
        await asyncio.sleep(0.03)
        deadline = time.monotonic() + 0.001
        assert await clock.sleep_until(deadline) is True  # the timer is free and on time
        assert time.monotonic() >= deadline
    finally:
        clock.close()


def _hold(seconds: float) -> None:
    time.sleep(seconds)  # the event loop held: a process that is not scheduled


def _stalled_since(watch: LoopWatch, start: float) -> float:
    return watch.since(start).stalled_s


def _answered(clock: DeadlineTimer, loop: asyncio.AbstractEventLoop) -> float:
    """An answer's wait on ``clock``, ended by its bytes at once; when it began."""
    waiter: asyncio.Future[None] = loop.create_future()
    began = time.monotonic()
    assert clock.wake(waiter, began + 5.0, began) is True
    waiter.set_result(None)  # the answer came
    clock.unwake(waiter)
    return began


async def test_while_it_looks_every_firing_says_how_late_the_loop_ran_it() -> None:
    """The loop watch's look: a late firing is the loop's lateness; after an answer came,
    the timer stays set over what the worker does next and, firing for nobody, looks
    again one look on; a rest ends it."""
    loop = asyncio.get_running_loop()
    watch = LoopWatch(loop)  # no worker attached: its own timer never runs
    clock = DeadlineTimer()
    start = time.monotonic()
    try:
        clock.look(watch)
        sleeping = asyncio.create_task(clock.sleep_until(start + 0.02, loop))
        await asyncio.sleep(0)  # the timer is set
        _hold(0.3)
        assert await sleeping is True
        assert 0.3 - 0.02 - 0.01 <= watch.since(start).stalled_s <= time.monotonic() - start
        # An answer's wait, ended by its bytes: the look stays set, a look from its start.
        mark = _answered(clock, loop)
        for _ in range(2):  # held past it, and past the look it set again as it fired
            _hold(0.3)
            late = await eventually(functools.partial(_stalled_since, watch, mark), within_s=2.0)
            assert 0.3 - watch.look_s - 0.02 <= late <= time.monotonic() - mark
            mark = time.monotonic()
        # At rest it looks no more: a hold now is no firing of it.
        clock.rest()
        # An absence: waited out for as long as a look set before the rest would take.
        await asyncio.sleep(2 * watch.look_s)
        mark = time.monotonic()
        _hold(0.2)
        await asyncio.sleep(watch.look_s + 0.01)
        assert watch.since(mark).stalled_s == 0.0
    finally:
        clock.close()


async def test_an_answer_wait_while_it_looks_ends_one_look_on() -> None:
    """A slow answer does not blind the watch: the wait is woken a look after it began,
    for the line to wait again, as the watch's own timer would have woken the loop."""
    loop = asyncio.get_running_loop()
    watch = LoopWatch(loop)
    clock = DeadlineTimer()
    try:
        clock.look(watch)
        waiter: asyncio.Future[None] = loop.create_future()
        now = time.monotonic()
        assert clock.wake(waiter, now + 5.0, now) is True
        async with asyncio.timeout(2.0):
            await waiter
        assert time.monotonic() >= now + watch.look_s
        clock.unwake(waiter)
    finally:
        clock.close()


async def test_set_anew_past_its_deadline_it_still_says_how_late_the_loop_was() -> None:
    """A worker that computes past the look and waits again with no turn of the loop
    between (a sink's work, then the next poll's wait): setting the timer clears the
    firing the loop never handed over, and the watch is told of it all the same."""
    loop = asyncio.get_running_loop()
    watch = LoopWatch(loop)
    clock = DeadlineTimer()
    try:
        clock.look(watch)
        mark = _answered(clock, loop)
        _hold(0.3)  # past the look, and no turn of the loop before the next wait
        assert await clock.sleep_until(time.monotonic() + 0.002, loop) is True
        late = watch.since(mark).stalled_s
        assert 0.3 - watch.look_s - 0.02 <= late <= time.monotonic() - mark
    finally:
        clock.close()
