"""Waiting for a condition, not for a fixed time: as long as a slow machine needs, no longer.

A fixed sleep is either too short on a loaded CI machine (a flaky test) or too long
everywhere else (a slow suite); these return as soon as the condition holds.
"""

from __future__ import annotations

import asyncio
import time
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from collections.abc import Callable


def wait_until(check: Callable[[], object], *, within_s: float, every_s: float = 0.1) -> Any:
    """Call ``check`` until it returns something true; that, or an AssertionError."""
    deadline = time.monotonic() + within_s
    while True:
        found = check()
        if found:
            return found
        if time.monotonic() > deadline:
            raise AssertionError(f"not within {within_s} s: {check}")
        time.sleep(every_s)


async def eventually(check: Callable[[], object], *, within_s: float, every_s: float = 0.02) -> Any:
    """Await until ``check`` returns something true; that, or an AssertionError."""
    loop = asyncio.get_running_loop()
    deadline = loop.time() + within_s
    while True:
        found = check()
        if found:
            return found
        if loop.time() > deadline:
            raise AssertionError(f"not within {within_s} s: {check}")
        await asyncio.sleep(every_s)


async def cancelled(task: asyncio.Task[Any], *, within_s: float = 10.0) -> None:
    """Cancel ``task`` and wait until it has ended, asking again while it runs on.

    aiomqtt awaits every answer of the broker with ``asyncio.wait_for``, which on Python
    3.11 returns the answer, not the cancellation, when both arrive in one turn of the loop
    (CPython issue 86296; ``wait_for`` was rewritten in 3.12): a subscriber's task cancelled
    at that instant runs on, and a teardown awaiting it waited until pytest-timeout ended
    the test at 120 s (seen under load, the loop idle in ``select``). The task's own
    failure, if it failed, is raised as awaiting it would.
    """
    loop = asyncio.get_running_loop()
    deadline = loop.time() + within_s
    while not task.done():
        if loop.time() > deadline:
            raise AssertionError(f"{task.get_name()} ran on {within_s} s after its cancellation")
        task.cancel()
        await asyncio.wait({task}, timeout=0.5)
    if not task.cancelled():
        task.result()
