"""A reload's changes inside a running bus worker: devices added, re-planned and removed,
and a new line, between two transactions, on a simulated line with its timing referee.
"""

from __future__ import annotations

import asyncio
from typing import TYPE_CHECKING

import pytest

from gateway.errors import GatewayError
from gateway.line.transports.serial_line import SerialLine
from gateway.wire.timing import LineFormat
from tests.rigs import rig, target

if TYPE_CHECKING:
    from pathlib import Path

    from tests.rigs import Rig

pytestmark = [pytest.mark.line]

DEVICES = [
    {"profile": "jumo-digiline-odo-h10", "address": 2, "animate": False},
    {"profile": "jumo-tecline-cl2", "address": 20, "animate": False},
]
H10_WAIT_S = 0.65  # sensor_constant_f1: the H10's post-write wait (tests/line/test_scheduler.py)


def requests_to(r: Rig, address: int, after: float = 0.0) -> list[float]:
    """When each request to the device began on the wire (the simulator's clock)."""
    return [rec.start for rec in r.frames() if rec.device == address and rec.start > after]


async def test_a_device_added_is_polled_and_an_unchanged_one_keeps_its_state(
    tmp_path: Path,
) -> None:
    # A second's interval: the newcomer's first read (its identity, everything) fits.
    cl2 = target("cl2", "jumo-tecline-cl2", 20, interval=1.0)
    async with rig(tmp_path, DEVICES, [cl2]) as r:
        polling = asyncio.create_task(r.worker.run())
        await asyncio.sleep(1.2)
        assert requests_to(r, 2) == []
        kept = r.worker.devices["cl2"]
        missed = kept.deadlines.missed_deadlines
        await asyncio.wait_for(
            r.worker.change_devices([cl2, target("h10", "jumo-digiline-odo-h10", 2)]), 2
        )
        await asyncio.sleep(2.0)
        r.worker.request_stop()
        await asyncio.wait_for(polling, 5)
    assert r.worker.devices["cl2"] is kept  # the same state: schedule, values, counters
    assert kept.deadlines.missed_deadlines == missed
    assert len(r.sink.good("h10", "oxygen")) >= 1
    assert r.server.bus.stats()["timing_violations"] == 0


async def test_a_removed_device_gets_nothing_more_and_its_queued_write_fails(
    tmp_path: Path,
) -> None:
    h10 = target("h10", "jumo-digiline-odo-h10", 2, interval=0.2)
    cl2 = target("cl2", "jumo-tecline-cl2", 20, interval=0.2)
    async with rig(tmp_path, DEVICES, [h10, cl2]) as r:
        polling = asyncio.create_task(r.worker.run())
        await asyncio.sleep(0.6)
        await r.worker.submit_write("h10", "sensor_constant_f1", 1.5)
        # Queued behind the post-write wait of the first: still waiting when h10 goes.
        second = r.worker.submit_write("h10", "sensor_constant_f1", 1.25)
        await asyncio.sleep(0.1)
        assert not second.done()
        await asyncio.wait_for(r.worker.change_devices([cl2]), 2)
        gone_at = asyncio.get_running_loop().time()
        with pytest.raises(GatewayError, match="line1/h10 was removed from the config"):
            await second
        await asyncio.sleep(1.0)
        r.worker.request_stop()
        await asyncio.wait_for(polling, 5)
        records = r.frames()
    writes = [rec for rec in records if rec.device == 2 and rec.function in {6, 16}]
    assert len(writes) == 1  # the second never reached the sensor
    last_h10 = max(rec.start for rec in records if rec.device == 2)
    first_cl2_after = min(rec.start for rec in records if rec.device == 20 and rec.start > last_h10)
    assert first_cl2_after > last_h10  # polling of the others went on
    assert not any(rec.device == 2 and rec.start > last_h10 for rec in records)
    assert gone_at > 0
    assert "h10" not in r.worker.devices
    assert r.server.bus.stats()["timing_violations"] == 0


async def test_a_replanned_device_keeps_its_post_write_wait_on_the_wire(tmp_path: Path) -> None:
    h10 = target("h10", "jumo-digiline-odo-h10", 2, interval=0.2)
    cl2 = target("cl2", "jumo-tecline-cl2", 20, interval=0.2)
    async with rig(tmp_path, DEVICES, [h10, cl2]) as r:
        polling = asyncio.create_task(r.worker.run())
        await asyncio.sleep(0.6)
        await r.worker.submit_write("h10", "sensor_constant_f1", 1.5)
        # Re-planned at once (another interval): everything of it falls due again, and
        # yet nothing may reach it before its post-write wait is over.
        replanned = target("h10", "jumo-digiline-odo-h10", 2, interval=0.3)
        await asyncio.wait_for(r.worker.change_devices([replanned, cl2]), 2)
        await asyncio.sleep(1.5)
        r.worker.request_stop()
        await asyncio.wait_for(polling, 5)
        records = r.frames()
    index = next(i for i, rec in enumerate(records) if rec.function in {6, 16})
    written = records[index]
    assert written.answer_at is not None
    following = [rec for rec in records[index + 1 :] if rec.device == 2]
    assert following, "the re-planned device is polled"
    assert following[0].start - written.answer_at >= H10_WAIT_S
    assert r.worker.devices["h10"].target is replanned
    assert r.server.bus.stats()["timing_violations"] == 0


async def test_a_new_line_takes_over_after_the_transaction_in_flight(tmp_path: Path) -> None:
    cl2 = target("cl2", "jumo-tecline-cl2", 20, interval=0.2)
    async with rig(tmp_path, DEVICES, [cl2]) as r:
        polling = asyncio.create_task(r.worker.run())
        await asyncio.sleep(0.6)
        kept = r.worker.devices["cl2"]
        old = r.worker.line
        new = SerialLine(
            port=str(tmp_path / "ttyRS485"), line=LineFormat(baudrate=9600, parity="E", stopbits=1)
        )
        assert await asyncio.wait_for(r.worker.use_line(new), 5)
        await asyncio.sleep(0.6)
        r.worker.request_stop()
        await asyncio.wait_for(polling, 5)
        await new.close()
    assert not old.is_open
    assert r.worker.line is new
    assert r.worker.transactions.line is new
    assert new.stats.requests[20] > 0  # the new line's own counters
    assert r.worker.devices["cl2"] is kept
    assert r.server.bus.stats()["timing_violations"] == 0
