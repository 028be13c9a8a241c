"""Flash-wear protection: which flash-backed points may be written, and how often.

Flash and EEPROM cells survive some 10,000 to 100,000 writes, so a setpoint written
every poll by a careless automation wears a sensor out within weeks. Three rules guard
against that, decided by :func:`check_flash_write` before anything is sent (the ledger's
counts go to the metrics as :class:`~gateway.publish.state.FlashCounts`):

1. A flash-backed point is written only if the device's
   :class:`~gateway.config.FlashPolicy` allows it by name (the device's ``flash_writes``).
   RAM and volatile points are always free, and are written even when unchanged: a
   repeated write there may be the point (a refresh, a trigger).
2. A flash write of the value the device already holds is skipped, not sent.
3. Each (device, point) has a daily budget of flash writes per UTC day, counted in a
   :class:`FlashLedger` that survives restarts.

Record a write in the ledger *before* sending it: a write that timed out may still have
reached the flash, so attempts are what count.
"""

from __future__ import annotations

import sqlite3
import threading
from dataclasses import dataclass
from datetime import UTC, date, datetime
from enum import StrEnum
from typing import TYPE_CHECKING

from gateway.control.commands import require_writable
from gateway.errors import CommandRejectedError, ConfigError
from gateway.profiles.model import Storage
from gateway.publish.state import FlashCounts

if TYPE_CHECKING:
    from pathlib import Path

    from gateway.config import FlashPolicy
    from gateway.profiles.model import Point


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


class FlashLedger:
    """A persistent count of flash writes per (device, point) and UTC day.

    The database is used from the event loop's thread only; :meth:`counts` hands the
    metrics thread a copy kept in memory beside it.
    """

    def __init__(self, path: Path | None) -> None:
        """Open (or create) the ledger at ``path``; a path that cannot be written raises.

        ``None`` keeps it in memory: for a command-line write that cannot touch flash.
        """
        self.path = path
        try:
            if path is not None:
                path.parent.mkdir(parents=True, exist_ok=True)
            self._db = sqlite3.connect(path or ":memory:", isolation_level=None)
            self._db.executescript(_SCHEMA)
            # Prove the file is writable now, not at the first flash write.
            self._db.execute("BEGIN IMMEDIATE")
            self._db.execute("COMMIT")
        except (OSError, sqlite3.Error) as exc:
            raise ConfigError(
                f"the flash-write ledger {path} cannot be written: {exc}", key="state_dir"
            ) from exc
        self._lock = threading.Lock()
        self._totals = self._load_totals()
        self._day: date | None = None
        self._today: dict[tuple[str, str], int] = {}
        self.load_today(utc_today())

    def _load_totals(self) -> dict[tuple[str, str], int]:
        rows = self._db.execute(
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
        rows = self._db.execute(
            "SELECT device, point, count FROM flash_writes WHERE day = ?", (today.isoformat(),)
        ).fetchall()
        with self._lock:
            self._day = today
            self._today = {(device, point): int(count) for device, point, count in rows}

    def count_today(self, device: str, point: str, today: date) -> int:
        """Flash writes of the point on ``today``."""
        row = self._db.execute(
            "SELECT count FROM flash_writes WHERE device = ? AND point = ? AND day = ?",
            (device, point, today.isoformat()),
        ).fetchone()
        return int(row[0]) if row else 0

    def total(self, device: str, point: str) -> int:
        """Flash writes of the point ever recorded."""
        row = self._db.execute(
            "SELECT COALESCE(SUM(count), 0) FROM flash_writes WHERE device = ? AND point = ?",
            (device, point),
        ).fetchone()
        return int(row[0])

    def totals(self) -> dict[tuple[str, str], int]:
        """Flash writes ever recorded, by (device, point): the source of a metric."""
        return self._load_totals()

    def record(self, device: str, point: str, today: date) -> None:
        """Count one flash write; if it cannot be counted, the write must not be sent."""
        try:
            self._db.execute(
                "INSERT INTO flash_writes (device, point, day, count) VALUES (?, ?, ?, 1) "
                "ON CONFLICT (device, point, day) DO UPDATE SET count = count + 1",
                (device, point, today.isoformat()),
            )
        except sqlite3.Error as exc:
            raise CommandRejectedError(
                f"the flash write cannot be counted in {self.path}: {exc}", point=point
            ) from exc
        key = (device, point)
        with self._lock:
            self._totals[key] = self._totals.get(key, 0) + 1
            if self._day == today:
                self._today[key] = self._today.get(key, 0) + 1
                return
        self.load_today(today)  # a new day (or a test's): its counts come from disk

    def close(self) -> None:
        """Close the database (the counts stay on disk)."""
        self._db.close()


def _holds(current: tuple[int, ...], registers: tuple[int, ...]) -> bool:
    # A string is written only as far as its terminating NUL (codec.encode), while the
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
