"""A line handed over: the bus worker stops polling and closes its port while paused."""

from __future__ import annotations

import asyncio
from typing import TYPE_CHECKING

import pytest

from gateway.errors import BusError
from tests.rigs import link_rig, target

if TYPE_CHECKING:
    from pathlib import Path

pytestmark = [pytest.mark.line]

DEVICES = [{"profile": "jumo-tecline-cl2", "address": 20, "animate": False}]


async def test_a_paused_worker_sends_nothing_and_polls_again_after(tmp_path: Path) -> None:
    targets = [target("cl2", "jumo-tecline-cl2", 20, interval=0.1)]
    async with link_rig(tmp_path, DEVICES, targets, poll=True) as rig:
        worker = rig.rig.worker
        await asyncio.sleep(0.5)
        assert rig.rig.line.is_open
        async with worker.paused("a scan"):
            assert not rig.rig.line.is_open
            assert worker.paused_for == "a scan"
            with pytest.raises(BusError, match="already paused: a scan"):
                async with worker.paused("another"):
                    pass
            frames = len(rig.rig.frames())
            await asyncio.sleep(0.5)
            assert len(rig.rig.frames()) == frames  # the line is the scan's alone
        assert worker.paused_for is None
        await asyncio.sleep(0.5)
        assert rig.rig.line.is_open
        assert len(rig.rig.frames()) > frames  # polling again


async def test_a_write_queued_during_a_pause_runs_after_it(tmp_path: Path) -> None:
    targets = [target("cl2", "jumo-tecline-cl2", 20, interval=0.2)]
    async with link_rig(tmp_path, DEVICES, targets, poll=True) as rig:
        await asyncio.sleep(0.3)
        link = rig.links["cl2"]
        async with rig.rig.worker.paused("a scan"):
            read = asyncio.create_task(link.read("temperature"))
            await asyncio.sleep(0.3)
            assert not read.done()
        assert "temperature" in await asyncio.wait_for(read, timeout=5)


async def test_a_worker_that_is_not_running_pauses_at_once(tmp_path: Path) -> None:
    targets = [target("cl2", "jumo-tecline-cl2", 20)]
    async with link_rig(tmp_path, DEVICES, targets) as rig:
        async with asyncio.timeout(1):
            async with rig.rig.worker.paused("a scan"):
                assert rig.rig.worker.paused_for == "a scan"


async def test_stopping_a_paused_worker_ends_its_run(tmp_path: Path) -> None:
    targets = [target("cl2", "jumo-tecline-cl2", 20, interval=0.2)]
    async with link_rig(tmp_path, DEVICES, targets, poll=True) as rig:
        await asyncio.sleep(0.3)
        async with rig.rig.worker.paused("a scan"):
            rig.rig.worker.request_stop()
            assert rig.polling is not None
            await asyncio.wait_for(asyncio.shield(rig.polling), timeout=2)
