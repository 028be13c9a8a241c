"""A part's ending, judged (``app.tasks.ended_unasked``), on real asyncio tasks."""

from __future__ import annotations

import asyncio

import pytest

from gateway.app.tasks import TaskEndedError, ended_unasked


async def _returns() -> None:
    await asyncio.sleep(0)


async def _fails() -> None:
    await asyncio.sleep(0)
    raise OSError(5, "Input/output error")


async def _runs() -> None:
    await asyncio.Event().wait()


async def test_a_part_that_raised_stops_the_gateway_with_its_own_error() -> None:
    task = asyncio.create_task(_fails(), name="bus[basin]")
    await asyncio.wait([task])
    error = ended_unasked(task)
    assert isinstance(error, OSError)
    assert error.errno == 5


async def test_a_part_that_returned_is_named_as_a_defect() -> None:
    task = asyncio.create_task(_returns(), name="feeds")
    await asyncio.wait([task])
    error = ended_unasked(task)
    assert isinstance(error, TaskEndedError)
    assert str(error) == "feeds ended while the gateway ran (it should run until the stop)"


async def test_a_part_cancelled_from_outside_is_named_not_raised_as_a_cancellation() -> None:
    task = asyncio.create_task(_runs(), name="sink[mqtt]")
    await asyncio.sleep(0)
    task.cancel()
    await asyncio.wait([task])
    error = ended_unasked(task)
    assert isinstance(error, TaskEndedError)
    assert str(error) == "sink[mqtt] was cancelled while the gateway ran"
    with pytest.raises(asyncio.CancelledError):  # what run() used to raise out of
        task.exception()
