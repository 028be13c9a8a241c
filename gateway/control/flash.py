"""Flash-wear protection: which flash-backed points may be written, and how often.

Flash and EEPROM cells survive some 10,000 to 100,000 writes, so a setpoint written
every poll by a careless automation wears a sensor out within weeks. Three rules guard
against that, decided by :func:`check_flash_write` before anything is sent (the ledger's
counts go to the metrics as :class:`~gateway.shared.state.FlashCounts`):

1. A flash-backed point is written only if the device's
   :class:`~gateway.config.FlashPolicy` allows it by name (the device's ``flash_writes``).
   RAM and volatile points are always free, and are written even when unchanged: a
   repeated write there may be the point (a refresh, a trigger).
2. A flash write of the value the device already holds is skipped, not sent.
3. Each (device, point) has a daily budget of flash writes per UTC day, counted in a
   :class:`FlashLedger` that survives restarts. A wall clock stepped across midnight
   (NTP correcting a Raspberry Pi's boot time, an operator) neither resets a day's count
   nor opens a second budget: the writes of this run since the day's midnight, measured
   back from now on the monotonic clock, count as well (the manual: A clock you can trust).

Record a write in the ledger *before* sending it: a write that timed out may still have
reached the flash, so attempts are what count; and the record is on the disk itself before
the write is sent, so that neither a kill nor a power cut leaves the ledger counting fewer
writes than reached the sensor (it may count one more: a write recorded, then cut off).
"""

from __future__ import annotations

import contextlib
import logging
import sqlite3
import threading
import time
from dataclasses import dataclass
from datetime import UTC, date, datetime
from enum import StrEnum
from pathlib import Path
from typing import TYPE_CHECKING

from gateway.control.commands import require_writable
from gateway.errors import CommandRejectedError, ConfigError
from gateway.profiles.model import Storage
from gateway.shared.state import FlashCounts
from gateway.shared.storage import (
    RETRY_S,
    StoreHealth,
    failure_cause,
    open_database,
    takes_a_change,
)

if TYPE_CHECKING:
    from gateway.config import FlashPolicy
    from gateway.profiles.model import Point


_LOGGER = logging.getLogger(__name__)

LEDGER_FILE = "flash-writes.sqlite"  # in the state directory, beside the MQTT queue


class Action(StrEnum):
    """What to do with a write command."""

    WRITE = "write"
    SKIP = "skip"  # nothing to do: the device holds the value already
    REFUSE = "refuse"


@dataclass(frozen=True, slots=True, kw_only=True)
class Decision:
    """The verdict on one write; ``record`` says it counts against the flash budget."""

    action: Action
    reason: str = ""
    record: bool = False


_FREE = Decision(action=Action.WRITE)
_UNCHANGED = Decision(action=Action.SKIP, reason="unchanged, not written")


def utc_today() -> date:
    """The UTC date that budgets are counted by."""
    return datetime.now(UTC).date()


_SCHEMA = """
CREATE TABLE IF NOT EXISTS flash_writes (
    device TEXT NOT NULL,
    point TEXT NOT NULL,
    day TEXT NOT NULL,
    count INTEGER NOT NULL,
    PRIMARY KEY (device, point, day)
);
"""
# A record is on the disk itself before :meth:`FlashLedger.record` returns, so before the
# write is sent: the rollback journal, and ``synchronous=EXTRA``, which also waits for the
# directory after the journal is deleted (the commit): without it a power cut just after
# the commit could bring the journal back and undo the record of a write that was sent.
# A few disk waits per flash write, of which there are a few a day. The rollback journal,
# not the write-ahead log, also lets the counts be read from a read-only file system.
_PRAGMAS = ("PRAGMA journal_mode=DELETE", "PRAGMA synchronous=EXTRA")
_DAY_S = 86_400.0
_PROBE = "INSERT INTO flash_writes VALUES ('', '', '', 0)"  # a change to roll back
_BUSY_TIMEOUT_S = 2.0  # a `gateway write` beside the running gateway holds it for milliseconds


class FlashLedger:
    """A persistent count of flash writes per (device, point) and UTC day.

    The database is used from the event loop's thread only; :meth:`counts` hands the
    metrics thread a copy kept in memory beside it. A file that cannot be written (a full
    disk, a read-only file system) does not stop the gateway: flash writes are refused,
    with the cause, until a record succeeds again (each is tried on a file opened afresh),
    and :attr:`health` says so meanwhile.
    """

    def __init__(self, path: Path | None) -> None:
        """Open (or create) the ledger at ``path``.

        A path whose directory is a file is a mistake of the config (a ``ConfigError``);
        a file that cannot be written starts the ledger refusing flash writes. ``None``
        keeps it in memory: for a command-line write that cannot touch flash.
        """
        self.path = path
        self.health = StoreHealth(path or Path(":memory:"), meanwhile="flash writes are refused")
        self.health.probe = self.probe  # the metrics' thread tries it again (see probe)
        if path is not None and path.parent.exists() and not path.parent.is_dir():
            raise ConfigError(
                f"the flash-write ledger {path} cannot be written: {path.parent} is not a "
                "directory (set state_dir to a directory)",
                key="state_dir",
            )
        self._db: sqlite3.Connection | None = None
        self._lock = threading.Lock()
        self._probe_at = 0.0
        self._totals: dict[tuple[str, str], int] = {}
        self._day: date | None = None
        self._today: dict[tuple[str, str], int] = {}
        self._run: dict[tuple[str, str], list[float]] = {}  # this run's writes, monotonic
        try:
            self._totals = self._load_totals(self._connection())
        except (OSError, sqlite3.Error) as exc:
            self._failed(exc)
        self.load_today(utc_today())

    def _connection(self) -> sqlite3.Connection:
        """The open database, or the file opened afresh (after a failure, or at first use)."""
        if self._db is not None:
            return self._db
        path = self.path
        if path is not None:
            path.parent.mkdir(parents=True, exist_ok=True)
        db = open_database(path or ":memory:", _PRAGMAS, _SCHEMA, timeout_s=_BUSY_TIMEOUT_S)
        self._db = db
        return db

    def _failed(self, exc: BaseException) -> str:
        """Note the failure (loudly at the first of a streak), close the file; the cause."""
        if self._db is not None and self.path is not None:
            with contextlib.suppress(sqlite3.Error):
                self._db.close()
            self._db = None  # the next use opens it afresh: a file system mounted again
        cause = failure_cause(self.path or Path(), exc)
        if self.health.failed(cause):
            _LOGGER.warning(
                "the flash-write ledger %s cannot be written: %s; flash writes are refused "
                "until it can",
                self.path,
                cause,
            )
        return cause

    def probe(self) -> None:
        """Try a file that failed again, at most every :data:`RETRY_S`.

        ``/healthz`` and the metrics call it (through :attr:`health`), so that the health
        recovers without waiting for a flash write. On a connection of its own (any
        thread), a change that is rolled back: the rollback journal is written first,
        which a full disk or a read-only file system refuses; nothing is counted.
        """
        if self.health.writable or self.path is None:
            return
        now = time.monotonic()
        with self._lock:
            if now < self._probe_at:
                return
            self._probe_at = now + RETRY_S
        if not takes_a_change(self.path, _SCHEMA, _PROBE):
            return
        if self.health.recovered():
            _LOGGER.info("the flash-write ledger %s can be written again", self.path)

    def _load_totals(self, db: sqlite3.Connection) -> dict[tuple[str, str], int]:
        rows = db.execute(
            "SELECT device, point, SUM(count) FROM flash_writes GROUP BY device, point"
        ).fetchall()
        return {(device, point): int(count) for device, point, count in rows}

    def counts(self, today: date) -> FlashCounts:
        """The totals and ``today``'s counts, from memory (any thread)."""
        with self._lock:
            if self._day != today:
                return FlashCounts(day=today, totals=dict(self._totals), today={})
            return FlashCounts(day=today, totals=dict(self._totals), today=dict(self._today))

    def load_today(self, today: date) -> None:
        """Fill the in-memory counts of ``today`` from disk (at start and on a new day)."""
        try:
            rows = (
                self._connection()
                .execute(
                    "SELECT device, point, count FROM flash_writes WHERE day = ?",
                    (today.isoformat(),),
                )
                .fetchall()
            )
        except (OSError, sqlite3.Error) as exc:
            self._failed(exc)
            rows = []  # a record, which is refused meanwhile, would read them again
        with self._lock:
            self._day = today
            self._today = {(device, point): int(count) for device, point, count in rows}

    def count_today(self, device: str, point: str, today: date) -> int:
        """Flash writes of the point on ``today`` (this process's own count if unreadable).

        Never fewer than this run's writes since ``today``'s midnight as the wall clock
        places it now, counted on the monotonic clock: after a step of the wall clock
        across midnight, the writes made before it still count against the day.
        """
        recent = self._since_midnight(device, point, today)
        try:
            row = (
                self._connection()
                .execute(
                    "SELECT count FROM flash_writes WHERE device = ? AND point = ? AND day = ?",
                    (device, point, today.isoformat()),
                )
                .fetchone()
            )
        except (OSError, sqlite3.Error) as exc:
            self._failed(exc)
            with self._lock:
                held = self._today.get((device, point), 0) if self._day == today else 0
            return max(held, recent)
        return max(int(row[0]) if row else 0, recent)

    def _since_midnight(self, device: str, point: str, today: date) -> int:
        """This run's writes of the point since ``today``'s midnight, by the monotonic clock."""
        now = datetime.now(UTC)
        if now.date() != today:
            return 0  # a day the wall clock is not on: the disk's count alone
        midnight = datetime.combine(today, datetime.min.time(), tzinfo=UTC)
        since = time.monotonic() - (now - midnight).total_seconds()
        with self._lock:
            return sum(1 for at in self._run.get((device, point), ()) if at >= since)

    def total(self, device: str, point: str) -> int:
        """Flash writes of the point ever recorded."""
        return self.totals().get((device, point), 0)

    def totals(self) -> dict[tuple[str, str], int]:
        """Flash writes ever recorded, by (device, point): the source of a metric."""
        try:
            return self._load_totals(self._connection())
        except (OSError, sqlite3.Error) as exc:
            self._failed(exc)
            with self._lock:
                return dict(self._totals)

    def record(self, device: str, point: str, today: date) -> None:
        """Count one flash write, on disk; if it cannot be counted, it must not be sent.

        A :class:`CommandRejectedError` with the cause when the file cannot be written.
        """
        try:
            self._connection().execute(
                "INSERT INTO flash_writes (device, point, day, count) VALUES (?, ?, ?, 1) "
                "ON CONFLICT (device, point, day) DO UPDATE SET count = count + 1",
                (device, point, today.isoformat()),
            )
        except (OSError, sqlite3.Error) as exc:
            cause = self._failed(exc)
            raise CommandRejectedError(
                f"the flash write cannot be counted: the flash-write ledger {self.path} cannot "
                f"be written ({cause}); flash writes are refused until it can, so nothing was "
                "written",
                point=point,
            ) from exc
        if self.health.recovered():
            _LOGGER.info("the flash-write ledger %s can be written again", self.path)
        key = (device, point)
        with self._lock:
            self._totals[key] = self._totals.get(key, 0) + 1
            if abs((datetime.now(UTC).date() - today).days) <= 1:  # dated by the wall clock
                now = time.monotonic()  # a day back is as far as a midnight can be
                run = [at for at in self._run.get(key, ()) if at > now - _DAY_S]
                self._run[key] = [*run, now]
            if self._day == today:
                self._today[key] = self._today.get(key, 0) + 1
                return
        self.load_today(today)  # a new day (or a test's): its counts come from disk

    def close(self) -> None:
        """Close the database (the counts stay on disk)."""
        if self._db is not None:
            self._db.close()
            self._db = None


def _holds(current: tuple[int, ...], registers: tuple[int, ...]) -> bool:
    # A string is written only as far as its terminating NUL (encoding.encode), while the
    # whole field is read: the device holds the text if the read starts with the write.
    return len(current) >= len(registers) and tuple(current[: len(registers)]) == registers


def check_flash_write(
    point: Point,
    device: str,
    *,
    policy: FlashPolicy,
    ledger: FlashLedger,
    current: tuple[int, ...] | None,
    registers: tuple[int, ...],
    today: date,
) -> Decision:
    """Decide whether ``registers`` may be written to ``point`` of ``device`` now.

    ``current`` is what the device holds, if known (``None`` writes without comparing).
    On :attr:`Action.WRITE` with ``record`` set, call :meth:`FlashLedger.record` first.
    """
    if require_writable(point).storage is not Storage.FLASH:
        return _FREE
    if point.name not in policy.allowed:
        return Decision(
            action=Action.REFUSE,
            reason=(
                f"flash-backed point not allowed for device {device} "
                "(add it to the device's flash_writes)"
            ),
        )
    if current is not None and _holds(current, registers):
        return _UNCHANGED
    if ledger.count_today(device, point.name, today) >= policy.daily_budget:
        return Decision(
            action=Action.REFUSE,
            reason=(
                f"budget of {policy.daily_budget} writes per day for {device}/{point.name} is spent"
            ),
        )
    return Decision(action=Action.WRITE, record=True)
