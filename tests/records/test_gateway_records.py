"""The gateway's own records: the host clock's trust and steps, reloads, counted feeds."""

from __future__ import annotations

import hashlib
from datetime import date
from typing import TYPE_CHECKING

from gateway.records import FeedCounts, Kind, RecordStore, records_path
from gateway.records.clock_watch import ClockWatch
from gateway.records.reloads import record_reload
from gateway.shared.host_clock import STA_UNSYNC, HostClock, KernelClock

if TYPE_CHECKING:
    from pathlib import Path

SYNCHRONISED = KernelClock(state=0, status=0, max_error_us=20_000, estimated_error_us=500)
ADRIFT = KernelClock(state=5, status=STA_UNSYNC, max_error_us=16_000_000, estimated_error_us=0)


def store_in(tmp_path: Path) -> RecordStore:
    return RecordStore(records_path(tmp_path), clock_synchronised=lambda: True)


def test_the_clock_is_recorded_at_start_at_each_change_and_at_a_step(tmp_path: Path) -> None:
    store = store_in(tmp_path)
    reading = [ADRIFT]
    wall, mono = [1_000_000.0], [50.0]
    watch = ClockWatch(
        store,
        HostClock(trust_unsynchronised=False, read=lambda: reading[0]),
        wall=lambda: wall[0],
        monotonic=lambda: mono[0],
    )
    watch.look()
    mono[0] += 10
    wall[0] += 10
    watch.look()  # nothing changed: nothing recorded
    reading[0] = SYNCHRONISED  # an NTP service sets the clock: synchronised, and stepped
    mono[0] += 10
    wall[0] += 10 + 3 * 3600
    watch.look()
    records = list(store.records())
    assert [r.kind for r in records] == [Kind.CLOCK] * 3
    started, synchronised, stepped = records
    assert started.body["action"] == "the gateway started"
    assert started.body["data"]["synchronised"] is False
    assert "unsynchronised" in started.body["note"]
    assert synchronised.body["action"] == "the host clock is synchronised"
    assert synchronised.body["data"]["trusted"] is True
    assert stepped.body["action"] == "the host clock was stepped"
    assert stepped.body["data"]["step_s"] == 3 * 3600


def test_a_reload_is_recorded_with_the_files_hash_or_its_problems(tmp_path: Path) -> None:
    store = store_in(tmp_path)
    config = tmp_path / "gateway.yaml"
    config.write_text("devices: []\n", encoding="utf-8")
    record_reload(store, config, summary="devices added: basin")
    record_reload(store, config, problems=["devices[0].address (line 3): out of range"])
    applied, refused = store.records()
    assert applied.body["result"] == "done"
    assert applied.body["data"]["sha256"] == hashlib.sha256(b"devices: []\n").hexdigest()
    assert applied.body["note"] == "devices added: basin"
    assert refused.body["result"] == "failed"
    assert refused.body["data"]["problems"] == ["devices[0].address (line 3): out of range"]


def test_feeds_are_counted_per_device_and_day_not_recorded_one_by_one(tmp_path: Path) -> None:
    store = store_in(tmp_path)
    today = [date(2026, 12, 1)]
    feeds = FeedCounts(store, profiles=lambda _d: "jumo-digiline-odo-s10", today=lambda: today[0])
    for _ in range(1440):  # a feed a minute
        feeds.count("aeration", "compensation_temperature")
    feeds.count("aeration", "compensation_pressure")
    assert list(store.records()) == []
    today[0] = date(2026, 12, 2)
    feeds.count("aeration", "compensation_temperature")  # a new day: yesterday's recorded
    [yesterday] = store.records()
    assert yesterday.body["kind"] == Kind.FEEDS
    assert yesterday.body["data"] == {
        "day": "2026-12-01",
        "writes": {"compensation_pressure": 1, "compensation_temperature": 1440},
    }
    feeds.flush()  # the stop
    assert [r.body["data"]["writes"] for r in store.records()][-1] == {
        "compensation_temperature": 1
    }
