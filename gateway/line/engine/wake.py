"""Work for a sleeping bus worker: a flag, and the one sleep it ends.

A bus worker sleeps between polls until the next one is due, unless work comes first (a
queued write or read, another master's request, a reload, a pause, a stop). The sleep is
on the line's own timer where it has one, as a gap's wait is: the timer goes on looking
for the event loop's watch (``line/transports/timer``), so a sleep between polls sets no
timer of the loop and tells the watch nothing, where ``asyncio.timeout`` and an
``asyncio.Event`` made a timer, a task's timeout and a future, and the watch's own timer
was set and cancelled twice around each sleep. Elsewhere (a Modbus TCP line) a timer of
the loop ends it, and the worker tells the watch it sleeps.
"""

from __future__ import annotations

import asyncio
import time
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from gateway.line.boundary import LineTimer, WaitWatch


class Wake:
    """Set when work arrives for the worker; ends its sleep (:meth:`sleep_until`)."""

    def __init__(self) -> None:
        """Not set; the loop is the one of the first sleep."""
        self._set = False
        self._waiter: asyncio.Future[None] | None = None
        # Known after the first sleep: asking for the running loop costs a system call
        # (``getpid``, asyncio's check for a fork) at every sleep.
        self._loop: asyncio.AbstractEventLoop | None = None

    def set(self) -> None:
        """Work arrived: a sleep ends now, the next one does not begin."""
        self._set = True
        waiter = self._waiter
        if waiter is not None and not waiter.done():
            waiter.set_result(None)

    def clear(self) -> None:
        """The worker looks for work: what arrives from now on ends its next sleep."""
        self._set = False

    def is_set(self) -> bool:
        """Whether work arrived since :meth:`clear`."""
        return self._set

    async def sleep_until(
        self, deadline: float, timer: LineTimer | None, watch: WaitWatch | None
    ) -> None:
        """Until :meth:`set`, or until ``deadline`` (monotonic seconds).

        On the line's own ``timer`` where it lends one (it looks for ``watch``, and says
        how late it fired); else on a timer of the loop, ``watch`` told that the worker
        sleeps and when it woke.
        """
        if self._set:
            return
        loop = self._loop
        if loop is None or loop.is_closed():
            loop = self._loop = asyncio.get_running_loop()
        waiter = self._waiter = loop.create_future()
        try:
            now = time.monotonic()
            if timer is not None and timer.wake(waiter, deadline, now, look_for=watch, asleep=True):
                try:
                    await waiter
                finally:
                    timer.unwake(waiter)
                return
            if watch is not None:
                watch.asleep()
            handle = loop.call_at(deadline, _resolve, waiter)  # the loop's clock is monotonic
            try:
                await waiter
            finally:
                handle.cancel()
                if watch is not None:
                    watch.awake(deadline, time.monotonic())
        finally:
            self._waiter = None


def _resolve(waiter: asyncio.Future[None]) -> None:
    if not waiter.done():
        waiter.set_result(None)
