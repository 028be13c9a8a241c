"""Every write recorded: before it is sent, with the value as found, and after, as left.

Against the simulator on a pseudo-terminal: the as-found and as-left values of a record
are compared with the sensor's own registers before and after the write, and the
registers recorded with the simulator's write log.
"""

from __future__ import annotations

from datetime import date
from typing import TYPE_CHECKING

import pytest

from gateway.config import FlashPolicy
from gateway.control.flash import FlashLedger
from gateway.control.writes import SafeWriter
from gateway.errors import BusTimeoutError, CommandRejectedError
from gateway.records import Actor, FeedCounts, Kind, RecordStore, Via, acting, records_path
from tests.rigs import PLANT, link_rig, link_target

if TYPE_CHECKING:
    from pathlib import Path

    from gateway.line.engine.devices import DeviceTarget
    from gateway.records import Record
    from tests.rigs import LinkRig

pytestmark = [pytest.mark.line]

DAY = date(2026, 12, 2)
ALICE = Actor(user="alice", via=Via.PAGE, detail="192.0.2.7", reason="new sensor", signed=True)


def targets() -> list[DeviceTarget]:
    return [
        link_target("s10", "jumo-digiline-odo-s10", 1),
        link_target("cl2", "jumo-tecline-cl2", 20),
        link_target("ghost", "jumo-digiline-odo-s10", 99),  # nothing answers at 99
    ]


def writer(
    rig: LinkRig, device: str, tmp_path: Path, allowed: frozenset[str] = frozenset()
) -> SafeWriter:
    store = RecordStore(records_path(tmp_path / "state"), clock_synchronised=lambda: True)
    return SafeWriter(
        rig.links[device],
        policy=FlashPolicy(allowed=allowed, daily_budget=4),
        ledger=FlashLedger(tmp_path / "state" / "flash-writes.sqlite"),
        today=lambda: DAY,
        records=store,
    )


def records_of(tmp_path: Path) -> list[Record]:
    return list(RecordStore(records_path(tmp_path / "state"), read_only=True).records())


async def test_a_write_is_recorded_as_found_and_as_left_with_who_and_why(tmp_path: Path) -> None:
    async with link_rig(tmp_path, PLANT, targets()) as rig:
        sensor = rig.device(1)
        sensor.put("compensation_temperature", 18.75)
        s10 = writer(rig, "s10", tmp_path)
        with acting(ALICE):
            done = await s10.set(s10.point("compensation_temperature"), 21.5)
        found, left = 18.75, sensor.get("compensation_temperature")
        assert left == 21.5
        [on_wire] = rig.writes(1)
        serial = str(sensor.get("serial_number")).strip()
    write, outcome = records_of(tmp_path)
    assert done.record == write.seq == 1
    assert write.body["kind"] == Kind.WRITE
    assert write.body["result"] == "pending"  # as it was on disk when the registers went out
    assert write.body["actor"] == {
        "user": "alice",
        "via": "page",
        "detail": "192.0.2.7",
        "reason": "new sensor",
        "signed": True,
    }
    assert write.body["device"] == {
        "name": "s10",
        "profile": "jumo-digiline-odo-s10",
        "bus": rig.links["s10"].bus,
        "address": 1,
        "serial": serial,
    }
    assert serial
    [change] = write.body["points"]
    assert change == {
        "point": "compensation_temperature",
        "unit": "°C",
        "as_found": found,
        "sent": 21.5,
        "registers": [f"0x{word:04X}" for word in on_wire.values],
        "as_left": None,
    }
    assert write.body["clock_synchronised"] is True
    assert outcome.body["kind"] == Kind.OUTCOME
    assert outcome.body["completes"] == 1
    assert outcome.body["result"] == "done"
    assert outcome.body["points"][0]["as_left"] == left
    assert RecordStore(records_path(tmp_path / "state")).verify().intact


async def test_a_flash_write_records_the_value_it_replaced(tmp_path: Path) -> None:
    async with link_rig(tmp_path, PLANT, targets()) as rig:
        sensor = rig.device(20)
        before = sensor.get("x_span")
        cl2 = writer(rig, "cl2", tmp_path, allowed=frozenset({"x_span"}))
        with acting(ALICE):
            await cl2.set(cl2.point("x_span"), 55.0)
        after = sensor.get("x_span")
    assert before != after == 55.0
    write, outcome = records_of(tmp_path)
    assert write.body["points"][0]["as_found"] == before
    assert outcome.body["points"][0]["as_left"] == after


async def test_a_refused_write_leaves_no_record_and_nothing_on_the_wire(tmp_path: Path) -> None:
    async with link_rig(tmp_path, PLANT, targets()) as rig:
        s10 = writer(rig, "s10", tmp_path)
        with pytest.raises(CommandRejectedError, match="float32 needs a number"):
            await s10.set(s10.point("compensation_temperature"), "warm")
        assert rig.writes(1) == []
    assert records_of(tmp_path) == []


async def test_a_store_that_cannot_be_written_refuses_the_write(tmp_path: Path) -> None:
    (tmp_path / "state").write_text("a file where the state directory should be")
    async with link_rig(tmp_path, PLANT, targets()) as rig:
        store = RecordStore(records_path(tmp_path / "state" / "inner"))
        s10 = SafeWriter(
            rig.links["s10"],
            policy=FlashPolicy(allowed=frozenset(), daily_budget=4),
            ledger=FlashLedger(None),
            records=store,
        )
        with pytest.raises(CommandRejectedError, match=r"record store .* cannot be"):
            await s10.set(s10.point("compensation_temperature"), 21.0)
        assert rig.writes(1) == []  # not recorded, so not sent
        assert not store.health.writable
        assert store.catch_up() == []  # the running gateway's look goes on meanwhile
        # The state directory mended: the health recovers by itself (the metrics' probe),
        # and the next write is recorded and sent.
        (tmp_path / "state").unlink()
        store.probe()
        assert store.health.writable
        await s10.set(s10.point("compensation_temperature"), 21.0)
        assert len(rig.writes(1)) == 1
        assert [r.kind for r in store.records()] == ["write", "outcome"]


async def test_a_write_without_an_answer_is_recorded_as_unknown(tmp_path: Path) -> None:
    async with link_rig(tmp_path, PLANT, targets()) as rig:
        ghost = writer(rig, "ghost", tmp_path)
        with acting(ALICE), pytest.raises(BusTimeoutError):  # text: no word order to read
            await ghost.set(ghost.point("description"), "basin 2", explicit=True)
    write, outcome = records_of(tmp_path)
    assert write.body["points"][0]["as_found"] is None
    assert write.body["note"].startswith("as found: not read")
    assert write.body["device"]["serial"] is None
    assert outcome.body["result"] == "unknown"  # the request may have reached the sensor
    assert "whether the sensor took the value is not known" in outcome.body["note"]
    assert outcome.body["completes"] == write.seq


async def test_a_write_under_no_actor_is_recorded_as_unattributed(tmp_path: Path) -> None:
    async with link_rig(tmp_path, PLANT, targets()) as rig:
        s10 = writer(rig, "s10", tmp_path)
        await s10.set(s10.point("compensation_temperature"), 20.0)
    write, _outcome = records_of(tmp_path)
    assert write.body["actor"]["user"] == "unattributed"


async def test_a_compensation_feed_is_counted_not_recorded_and_reads_nothing_first(
    tmp_path: Path,
) -> None:
    async with link_rig(tmp_path, PLANT, targets()) as rig:
        s10 = writer(rig, "s10", tmp_path)
        assert s10.records is not None
        s10.feeds = FeedCounts(s10.records, today=lambda: DAY)
        point = s10.point("compensation_temperature")
        frames = len(rig.rig.frames())
        for value in (20.0, 20.5, 21.0):
            await s10.set(point, value, read_back=False, feed=True)
        # The writes, and once the sensor's response time and word order: no read of the
        # point before each write (as found), none of its serial number.
        sent = [(f.function, f.address) for f in rig.rig.frames()[frames:]]
        assert sent == [(3, 0x0305), (3, 0x0307), (16, 0x25B0), (16, 0x25B0), (16, 0x25B0)]
        assert s10.feeds.pending() == {"s10": {"compensation_temperature": 3}}
    assert records_of(tmp_path) == []
