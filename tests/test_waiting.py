"""The tests' own waiting helpers do what the tests count on."""

from __future__ import annotations

import asyncio

import pytest

from tests.waiting import cancelled


async def _swallowing_one_cancellation(ran_on: asyncio.Event) -> None:
    """As a task awaiting aiomqtt on Python 3.11 may: the first cancellation is lost."""
    try:
        await asyncio.sleep(3600)
    except asyncio.CancelledError:
        ran_on.set()  # asyncio.wait_for returned the answer instead
    await asyncio.sleep(3600)


async def test_a_task_that_lost_its_cancellation_is_asked_again_and_ends() -> None:
    ran_on = asyncio.Event()
    task = asyncio.create_task(_swallowing_one_cancellation(ran_on))
    await asyncio.sleep(0)
    await cancelled(task)
    assert ran_on.is_set()  # the first cancellation was lost, as in the race
    assert task.cancelled()


async def test_a_task_that_failed_raises_its_failure() -> None:
    async def failing() -> None:
        try:
            await asyncio.sleep(3600)
        except asyncio.CancelledError:
            raise RuntimeError("broken on the way out") from None

    task = asyncio.create_task(failing())
    await asyncio.sleep(0)
    with pytest.raises(RuntimeError, match="broken on the way out"):
        await cancelled(task)


async def test_a_task_that_never_ends_is_named_after_the_bound() -> None:
    stubborn_now = True

    async def stubborn() -> None:
        while True:
            try:
                await asyncio.sleep(3600)
            except asyncio.CancelledError:
                if not stubborn_now:
                    raise

    task = asyncio.create_task(stubborn(), name="stubborn")
    await asyncio.sleep(0)
    with pytest.raises(AssertionError, match=r"stubborn ran on 1\.0 s after its cancellation"):
        await cancelled(task, within_s=1.0)
    stubborn_now = False
    await cancelled(task)
    assert task.cancelled()
