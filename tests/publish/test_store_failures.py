"""The MQTT queue and the flash-write ledger on a disk that fills up or turns read-only.

Real file systems (a small tmpfs filled by a file, a read-only bind mount; the tests run
as root), the stores themselves, and a clock of the test's for their retries.
"""

from __future__ import annotations

import logging
import sqlite3
from datetime import date
from typing import TYPE_CHECKING

import pytest

from gateway.config import ConfigProblems, parse_config
from gateway.control.flash import FlashLedger
from gateway.errors import CommandRejectedError
from gateway.publish.message import Message
from gateway.publish.store import MessageStore
from gateway.shared.storage import RETRY_S, StorageStatus
from tests.storage_rig import fill, read_only_bind, small_tmpfs

if TYPE_CHECKING:
    from collections.abc import Iterator
    from pathlib import Path

DAY = date(2026, 11, 27)


class Clock:
    """Monotonic seconds that the test moves on."""

    def __init__(self) -> None:
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now


@pytest.fixture
def disk(tmp_path: Path) -> Iterator[Path]:
    """A 1 MiB file system of its own."""
    with small_tmpfs(tmp_path / "disk", 1024) as mounted:
        yield mounted


def msgs(start: int, stop: int, *, topic: str = "gw/basin/state") -> list[Message]:
    return [Message.text(topic, str(n)) for n in range(start, stop)]


def texts(store: MessageStore) -> list[str]:
    return [m.payload.decode() for _, m in store.peek(1000)]


def warnings_about(caplog: pytest.LogCaptureFixture, path: Path) -> list[str]:
    return [
        r.getMessage()
        for r in caplog.records
        if r.levelno == logging.WARNING and str(path) in r.getMessage()
    ]


@pytest.mark.root
def test_a_full_disk_keeps_the_queue_in_memory_in_order_and_writes_it_back(
    disk: Path, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.INFO, logger="gateway")
    clock = Clock()
    path = disk / "mqtt-queue.sqlite"
    store = MessageStore(path, max_messages=1000, clock=clock)
    on_disk = store.put(msgs(0, 5))
    assert all(i > 0 for i in on_disk)
    filler = fill(disk)
    waiting = store.put(msgs(5, 10))  # the disk is full: in memory, behind the disk's
    assert all(i < 0 for i in waiting)
    store.put(msgs(10, 15))
    assert not store.health.writable
    assert "the disk is full" in store.health.view().cause
    assert len(warnings_about(caplog, path)) == 1  # once, with the path and the cause
    assert texts(store) == [str(n) for n in range(15)]
    # Acknowledged: two on disk (which cannot be deleted now) and one in memory.
    store.remove([on_disk[0], on_disk[1], waiting[0]])
    assert len(store) == 12
    assert texts(store) == [str(n) for n in (2, 3, 4, *range(6, 15))]
    # Room again: nothing is tried before the retry is due, then all of it is written.
    filler.unlink()
    clock.now += RETRY_S - 1
    store.put(msgs(15, 16))
    assert not store.health.writable
    clock.now += 1
    store.put(msgs(16, 17))
    assert store.health.writable
    assert texts(store) == [str(n) for n in (2, 3, 4, *range(6, 17))]
    assert any("can be written again" in r.getMessage() for r in caplog.records)
    # The ids handed out while in memory still remove their messages, now on disk.
    store.remove(waiting[1:3])
    assert texts(store)[:4] == ["2", "3", "4", "8"]
    store.close()
    reopened = MessageStore(path, max_messages=1000)
    assert texts(reopened) == [str(n) for n in (2, 3, 4, *range(8, 17))]
    reopened.close()
    assert len(warnings_about(caplog, path)) == 1


@pytest.mark.root
def test_retained_messages_supersede_each_other_in_memory_too(disk: Path) -> None:
    store = MessageStore(disk / "q.sqlite", max_messages=1000)
    fill(disk)
    store.put([Message.text("gw/basin/concentration", "0.1", retain=True), *msgs(0, 1)])
    store.put([Message.text("gw/basin/concentration", "0.2", retain=True), *msgs(1, 2)])
    assert texts(store) == ["0", "0.2", "1"]
    store.close()


@pytest.mark.root
def test_the_memory_bound_drops_the_oldest_and_counts_them(disk: Path) -> None:
    store = MessageStore(disk / "q.sqlite", max_messages=100)
    fill(disk)
    dropped = store.append(msgs(0, 130))
    assert dropped == 30
    assert store.dropped == 30
    assert texts(store) == [str(n) for n in range(30, 130)]
    store.close()


@pytest.mark.root
def test_a_read_only_state_directory_starts_the_queue_in_memory_until_it_is_writable(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    clock = Clock()
    source = tmp_path / "state"
    source.mkdir()
    with read_only_bind(source, tmp_path / "ro") as make_writable:
        path = tmp_path / "ro" / "mqtt-queue.sqlite"
        store = MessageStore(path, max_messages=1000, clock=clock)
        assert not store.health.writable
        assert "read-only" in store.health.view().cause
        store.put(msgs(0, 3))
        assert texts(store) == ["0", "1", "2"]
        make_writable()
        clock.now += RETRY_S
        store.put(msgs(3, 4))
        assert store.health.writable
        store.close()
        assert len(warnings_about(caplog, path)) == 1
    db = sqlite3.connect(source / "mqtt-queue.sqlite")
    assert [r[0] for r in db.execute("SELECT payload FROM queue ORDER BY id")] == [
        b"0",
        b"1",
        b"2",
        b"3",
    ]
    db.close()


def test_a_damaged_queue_is_set_aside_and_a_new_one_started(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    path = tmp_path / "mqtt-queue.sqlite"
    path.write_bytes(b"not a database, but what a failing card returned" * 100)
    store = MessageStore(path, max_messages=1000)
    assert store.health.writable
    store.put(msgs(0, 2))
    assert texts(store) == ["0", "1"]
    store.close()
    kept = [p.name for p in tmp_path.iterdir() if ".damaged-" in p.name]
    assert len(kept) == 1
    assert any(r.levelno == logging.ERROR and "damaged" in r.getMessage() for r in caplog.records)


@pytest.mark.root
def test_the_ledger_refuses_flash_writes_on_a_full_disk_and_counts_again_with_room(
    disk: Path, caplog: pytest.LogCaptureFixture
) -> None:
    path = disk / "flash-writes.sqlite"
    ledger = FlashLedger(path)
    ledger.record("pool", "x_span", DAY)
    filler = fill(disk)
    for _ in range(3):
        with pytest.raises(CommandRejectedError) as refused:
            ledger.record("pool", "x_span", DAY)
        assert str(path) in refused.value.reason
        assert "the disk is full" in refused.value.reason
        assert "nothing was written" in refused.value.reason
    assert not ledger.health.writable
    assert ledger.count_today("pool", "x_span", DAY) == 1  # the refused ones are not counted
    assert len(warnings_about(caplog, path)) == 1
    filler.unlink()
    ledger.record("pool", "x_span", DAY)  # each record tries the file afresh
    assert ledger.health.writable
    assert ledger.count_today("pool", "x_span", DAY) == 2
    assert ledger.counts(DAY).totals == {("pool", "x_span"): 2}
    ledger.close()


@pytest.mark.root
def test_a_read_only_ledger_still_shows_its_counts_and_refuses_flash_writes(
    tmp_path: Path,
) -> None:
    source = tmp_path / "state"
    ledger = FlashLedger(source / "flash-writes.sqlite")
    ledger.record("pool", "x_span", DAY)
    ledger.close()
    with read_only_bind(source, tmp_path / "ro") as make_writable:
        ledger = FlashLedger(tmp_path / "ro" / "flash-writes.sqlite")
        assert ledger.counts(DAY).totals == {("pool", "x_span"): 1}
        with pytest.raises(CommandRejectedError, match="read-only"):
            ledger.record("pool", "x_span", DAY)
        assert not ledger.health.writable
        make_writable()
        ledger.record("pool", "x_span", DAY)
        assert ledger.health.writable
        assert ledger.total("pool", "x_span") == 2
        ledger.close()


@pytest.mark.root
def test_the_status_reports_each_file_once_and_the_room_left(disk: Path) -> None:
    status = StorageStatus()
    first = MessageStore(disk / "mqtt-queue.sqlite", max_messages=100)
    status.track(first.health)
    first.close()
    again = MessageStore(disk / "mqtt-queue.sqlite", max_messages=100)  # as after a reload
    status.track(again.health)
    filler = fill(disk)
    again.put(msgs(0, 1))
    [health] = status.files()
    assert not health.writable
    assert health.failures == 1
    [directory] = status.directories()
    assert directory.free_bytes == 0
    assert not directory.read_only
    filler.unlink()
    assert (status.directories()[0].free_bytes or 0) > 0
    again.close()


def test_mqtt_persist_is_a_checked_key() -> None:
    text = "buses:\n  - {name: line1, port: /dev/ttyS9}\nmqtt:\n  persist: %s\n"
    assert parse_config(text % "always", environ={}).mqtt.persist == "always"
    assert (
        parse_config("buses:\n  - {name: line1, port: /dev/ttyS9}\n", environ={}).mqtt.persist
        == "outage"
    )
    with pytest.raises(ConfigProblems) as refused:
        parse_config(text % "sometimes", environ={})
    [problem] = refused.value.problems
    assert problem.key == "mqtt.persist"
    assert problem.line == 4
    assert "'outage' or 'always'" in problem.message


@pytest.mark.root
def test_a_queue_with_nothing_to_write_recovers_when_its_health_is_asked(
    disk: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """Connected with ``persist: outage`` nothing is written: ``/healthz`` tries the file."""
    caplog.set_level(logging.INFO, logger="gateway")
    clock = Clock()
    status = StorageStatus()
    store = MessageStore(disk / "mqtt-queue.sqlite", max_messages=1000, clock=clock)
    status.track(store.health)
    filler = fill(disk)
    ids = store.put(msgs(0, 3))  # an outage on a full disk: in memory
    store.remove(ids)  # sent once the broker was back
    assert not status.files()[0].writable  # the disk is still full
    filler.unlink()
    clock.now += RETRY_S
    assert status.files()[0].writable  # asked, without a write of the queue's own
    assert store.put(msgs(3, 4))[0] > 0  # on disk, on a file opened afresh
    assert texts(store) == ["3"]
    assert len(warnings_about(caplog, disk / "mqtt-queue.sqlite")) == 1
    store.close()
