"""The guard against unretrieved asyncio exceptions catches what it is there for."""

from __future__ import annotations

import asyncio

import pytest

from tests import unretrieved


async def fail() -> None:
    message = "nobody awaits this"
    raise RuntimeError(message)


async def leave_a_failed_task() -> None:
    """A task fails and nobody awaits it; its last reference goes with this frame."""
    task = asyncio.create_task(fail())
    await asyncio.sleep(0.01)
    assert task.done()


async def leave_a_failed_future() -> None:
    future = asyncio.get_running_loop().create_future()
    future.set_exception(RuntimeError("nobody awaits this either"))


async def test_a_task_exception_nobody_retrieves_fails_the_guard() -> None:
    with (
        pytest.raises(unretrieved.UnretrievedExceptionError, match="nobody awaits this"),
        unretrieved.guard(),
    ):
        await leave_a_failed_task()


async def test_a_future_exception_nobody_retrieves_fails_the_guard() -> None:
    with (
        pytest.raises(unretrieved.UnretrievedExceptionError, match="Future exception"),
        unretrieved.guard(),
    ):
        await leave_a_failed_future()


async def test_a_retrieved_exception_passes_the_guard() -> None:
    with unretrieved.guard() as catcher:
        task = asyncio.create_task(fail())
        with pytest.raises(RuntimeError):
            await task
        del task
    assert catcher.reports == []


def test_the_line_of_a_child_process_is_found() -> None:
    stderr = (
        "WARNING line1: port went away\n"
        "ERROR Task exception was never retrieved\n"
        "future: <Task finished name='Task-21' coro=...>\n"
    )
    assert unretrieved.reported_in(stderr) == ["ERROR Task exception was never retrieved"]
    assert unretrieved.reported_in("WARNING line1: port went away\n") == []
