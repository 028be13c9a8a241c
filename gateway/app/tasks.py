"""Stopping the gateway's tasks within a bound: a stop must never hang on one of them."""

from __future__ import annotations

import asyncio
import logging
from typing import TYPE_CHECKING, Any, Final

if TYPE_CHECKING:
    from collections.abc import Sequence

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
