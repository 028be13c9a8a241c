"""The bus worker's sleep between polls: ended by work or by its deadline, never early.

On the line's own timer where it lends one (the timer looks for the loop's watch: a late
wake is the loop's lateness); on a timer of the loop elsewhere (a Modbus TCP line), the
watch told that the worker sleeps.
"""

from __future__ import annotations

import asyncio
import time

import pytest

from gateway.line.engine.lateness import LoopWatch
from gateway.line.engine.wake import Wake
from gateway.line.transports.timer import DeadlineTimer


@pytest.mark.parametrize("lent", [True, False], ids=["line's timer", "loop's timer"])
async def test_the_sleep_ends_at_its_deadline_never_before(*, lent: bool) -> None:
    wake = Wake()
    timer = DeadlineTimer() if lent else None
    try:
        for delay in (0.002, 0.02):
            deadline = time.monotonic() + delay
            await wake.sleep_until(deadline, timer, None)
            assert time.monotonic() >= deadline
    finally:
        if timer is not None:
            timer.close()


@pytest.mark.parametrize("lent", [True, False], ids=["line's timer", "loop's timer"])
async def test_work_ends_the_sleep_at_once_and_work_before_it_skips_it(*, lent: bool) -> None:
    wake = Wake()
    timer = DeadlineTimer() if lent else None
    try:
        start = time.monotonic()
        sleeping = asyncio.create_task(wake.sleep_until(start + 5.0, timer, None))
        await asyncio.sleep(0.01)
        assert not sleeping.done()
        wake.set()  # a write queued
        async with asyncio.timeout(1.0):
            await sleeping
        assert wake.is_set()
        # Set before the sleep: no sleep at all; cleared, the next one sleeps.
        await wake.sleep_until(time.monotonic() + 5.0, timer, None)
        wake.clear()
        deadline = time.monotonic() + 0.01
        await wake.sleep_until(deadline, timer, None)
        assert time.monotonic() >= deadline
        assert time.monotonic() - start < 2.0
    finally:
        if timer is not None:
            timer.close()


@pytest.mark.parametrize("lent", [True, False], ids=["line's timer", "loop's timer"])
async def test_a_sleep_woken_late_is_the_loops_lateness(*, lent: bool) -> None:
    """The loop held past the sleep's deadline: the watch counts it, on either timer."""
    loop = asyncio.get_running_loop()
    watch = LoopWatch(loop)
    watch.attach()  # the worker
    timer = DeadlineTimer() if lent else None
    try:
        start = time.monotonic()
        sleeping = asyncio.create_task(Wake().sleep_until(start + 0.02, timer, watch))
        await asyncio.sleep(0)  # asleep
        time.sleep(0.3)  # noqa: ASYNC251 - the loop held past the deadline
        await sleeping
        stalled = watch.since(start).stalled_s
        assert 0.3 - 0.02 - 0.01 <= stalled <= time.monotonic() - start
    finally:
        watch.detach()
        if timer is not None:
            timer.close()


async def test_a_closed_line_ends_the_sleep_on_its_timer() -> None:
    """The port closed while the worker sleeps on its timer: the sleep ends, and the
    worker finds the line closed, as it did at a timer of the loop."""
    wake = Wake()
    timer = DeadlineTimer()
    sleeping = asyncio.create_task(wake.sleep_until(time.monotonic() + 5.0, timer, None))
    await asyncio.sleep(0.01)
    timer.close()
    async with asyncio.timeout(1.0):
        await sleeping
