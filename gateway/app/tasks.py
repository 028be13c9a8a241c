"""The gateway's running tasks: a child's ending judged, and a stop that never hangs."""

from __future__ import annotations

import asyncio
import logging
from typing import TYPE_CHECKING, Any, Final

if TYPE_CHECKING:
    from collections.abc import Sequence

from gateway.errors import GatewayError

_LOGGER = logging.getLogger(__name__)
SHUTDOWN_S: Final = 5.0  # bound on stopping: finish the frame in flight, close the ports


async def stop_tasks(tasks: Sequence[asyncio.Task[Any]]) -> None:
    """Cancel and wait, but never for longer than ``SHUTDOWN_S``: stopping must not hang."""
    if not tasks:
        return
    for task in tasks:
        task.cancel()
    done, pending = await asyncio.wait(tasks, timeout=SHUTDOWN_S)
    for task in pending:
        _LOGGER.warning("%s did not stop within %.0f s; leaving it", task.get_name(), SHUTDOWN_S)
    for task in done:
        if not task.cancelled() and (exc := task.exception()) is not None:
            _LOGGER.debug("%s ended with %r", task.get_name(), exc)


class TaskEndedError(GatewayError):
    """A part of the gateway that runs until the stop ended on its own."""


def ended_unasked(task: asyncio.Task[Any]) -> BaseException:
    """Why a task that should run until the stop is done: the error the gateway stops with.

    Each part (a bus, a sink, the page, the feeds, the records) runs until it is stopped.
    Its exception is raised as it is; a part that returned, or that something other than
    the gateway cancelled, is a defect named here, so that the gateway stops with a
    reason instead of asking ``exception()`` of a cancelled task (which raised
    ``CancelledError`` out of the run) or waiting again at once on a task already done (a
    busy loop).
    """
    name = task.get_name()
    if task.cancelled():
        return TaskEndedError(f"{name} was cancelled while the gateway ran")
    exc = task.exception()
    if exc is not None:
        return exc
    return TaskEndedError(f"{name} ended while the gateway ran (it should run until the stop)")
