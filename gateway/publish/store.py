"""Store and forward: MQTT messages kept on disk until the broker acknowledged them.

aiomqtt does not buffer: a publish while disconnected raises. So messages are appended
here (SQLite in the state directory), in order, and sent from here, before any newer
message; one leaves only once the broker acknowledged it (:meth:`MessageStore.remove`).
What was written survives a kill or a crash of the process and a restart. The queue is
bounded: past the bound the oldest messages that are not retained are dropped and
counted; a retained message supersedes an older retained one for the same topic (only the
last one matters to a subscriber).

A full disk or a read-only file system does not stop the queue: what cannot be written
waits in memory (at most :data:`MEMORY_MAX` messages), in order behind what is on disk,
the failure is logged once with the path and the cause and kept in :attr:`health`, and
every :data:`RETRY_S` the file is opened afresh and what waited in memory is written
(a file system that was unmounted, checked and mounted again is then the one written).

The settings, and why (the manual: What survives a power cut): the write-ahead log
(``journal_mode=WAL``) with ``synchronous=NORMAL``: a commit is one write of the log,
without waiting for the disk, which a kill of the process never loses and a power cut
never turns into a damaged file; what the disk had not been given yet is lost at a power
cut, so a thread of the store's own checkpoints every :data:`CHECKPOINT_S`, which makes
the disk hold everything committed until then, outside the event loop.
"""

from __future__ import annotations

import contextlib
import logging
import sqlite3
import threading
import time
from collections import OrderedDict
from datetime import UTC, datetime
from typing import TYPE_CHECKING, Final

from gateway.errors import PublishError
from gateway.publish.message import Message
from gateway.shared.storage import (
    RETRY_S,
    StoreHealth,
    can_write,
    failure_cause,
    open_database,
)

if TYPE_CHECKING:
    from collections.abc import Callable, Iterable, Sequence
    from pathlib import Path

_LOGGER = logging.getLogger(__name__)

MEMORY_MAX: Final = 10_000  # messages kept in memory while the file cannot be written
MIN_FREE_BYTES: Final = 256 * 1024  # room a full disk must have again before it is tried
CHECKPOINT_S: Final = 2.0  # the longest a commit waits to be on the disk itself
WAL_LIMIT_BYTES: Final = 4 * 1024 * 1024  # the log is cut back to this after a checkpoint

_SCHEMA = """
CREATE TABLE IF NOT EXISTS queue (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    topic TEXT NOT NULL,
    payload BLOB NOT NULL,
    qos INTEGER NOT NULL,
    retain INTEGER NOT NULL
);
CREATE INDEX IF NOT EXISTS queue_retained_topic ON queue (topic) WHERE retain = 1;
"""
_PRAGMAS = (
    "PRAGMA journal_mode=WAL",
    "PRAGMA synchronous=NORMAL",
    # The checkpointer thread does it; SQLite's own (at 1000 pages, some 4 MB of log) only
    # if a flood of writes keeps the thread's from ever completing.
    "PRAGMA wal_autocheckpoint=1000",
    f"PRAGMA journal_size_limit={WAL_LIMIT_BYTES}",
)
_DAMAGED = frozenset({sqlite3.SQLITE_CORRUPT, sqlite3.SQLITE_NOTADB})
_INSERT = "INSERT INTO queue (id, topic, payload, qos, retain) VALUES (?, ?, ?, ?, ?)"
_Row = tuple[int, str, bytes, int, int]


class MessageStore:
    """A bounded, persistent FIFO of MQTT messages, kept in memory while the disk fails.

    Each message gets an id (:meth:`put`) by which it is removed once acknowledged. Ids
    only grow: one is never given twice, not even across restarts.
    """

    def __init__(
        self,
        path: Path,
        *,
        max_messages: int,
        retry_s: float = RETRY_S,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        """Open (or create) the queue at ``path``.

        A path whose directory is a file is a mistake of the config, and raises; a file
        that cannot be written (full, read-only, not allowed) starts the queue in memory.
        """
        self.path = path
        self.max_messages = max_messages
        self.dropped = 0
        self.health = StoreHealth(path, meanwhile="messages wait in memory")
        self.health.probe = self._probe
        self._retry_s = retry_s
        self._clock = clock
        self._retry_at = 0.0
        self._probe_at = 0.0
        self._reopen = False  # the probe found the directory writable again
        self._db: sqlite3.Connection | None = None
        self._next_id = 1
        self._disk = 0  # messages on disk, not counting those removed but not yet deleted
        # While the file cannot be written: the newer messages, by id (negative: they are
        # renumbered once written to disk), the retained one of each topic, and the ids on
        # disk that were removed (acknowledged) but could not be deleted.
        self._memory: OrderedDict[int, Message] = OrderedDict()
        self._retained: dict[str, int] = {}
        self._gone: set[int] = set()
        self._last_memory_id = 0
        self._renumbered: dict[int, int] = {}  # an id from memory -> its id on disk
        self._checkpoints = _Checkpointer(path)
        if path.parent.exists() and not path.parent.is_dir():
            raise PublishError(
                f"the MQTT queue {path} cannot be written: {path.parent} is not a directory "
                "(set state_dir to a directory)"
            )
        try:
            self._open()
        except (OSError, sqlite3.Error) as exc:
            self._failed(exc)
        self._checkpoints.start()

    def __len__(self) -> int:
        """Messages waiting."""
        return self._disk + len(self._memory)

    # --- the queue ----------------------------------------------------------------------

    def append(self, messages: Sequence[Message]) -> int:
        """Queue messages in order; returns how many old messages the bound dropped."""
        dropped = self.dropped
        self.put(messages)
        return self.dropped - dropped

    def put(self, messages: Sequence[Message]) -> list[int]:
        """Queue messages in order; their ids (for :meth:`remove`), in the same order."""
        if not messages:
            return []
        self._retry_if_due()
        if self._db is not None and self.health.writable:
            try:
                return self._put_on_disk(self._db, messages)
            except sqlite3.Error as exc:
                self._failed(exc)
        return self._put_in_memory(messages)

    def peek(self, limit: int) -> list[tuple[int, Message]]:
        """The oldest ``limit`` messages with their ids, without removing them."""
        self._retry_if_due()
        found: list[tuple[int, Message]] = []
        if self._db is not None and self._disk:
            try:
                found = self._peek_disk(self._db, limit)
            except sqlite3.Error as exc:
                self._failed(exc)  # what is on disk waits until it can be read again
        for key, message in self._memory.items():
            if len(found) >= limit:
                break
            found.append((key, message))
        return found

    def remove(self, ids: Iterable[int]) -> None:
        """Forget messages that the broker acknowledged."""
        self._retry_if_due()
        on_disk: list[int] = []
        for key in ids:
            if key < 0 and (moved := self._renumbered.pop(key, None)) is not None:
                key = moved  # noqa: PLW2901 - the same message, written to disk since
            if key < 0:
                self._forget_in_memory(key)
            else:
                on_disk.append(key)
        if not on_disk:
            return
        if self._db is not None and self.health.writable:
            try:
                self._disk -= self._delete(self._db, on_disk)
            except sqlite3.Error as exc:
                self._failed(exc)
            else:
                return
        self._forget_on_disk(self._db, on_disk)

    def retry(self) -> None:
        """Try the file again if it failed and the retry is due (cheap otherwise).

        For a user that writes nothing for a while (``mqtt.persist: outage`` while
        connected): the health must not stay failed once the disk has room again.
        """
        self._retry_if_due()

    def close(self) -> None:
        """Close the database; what waits in memory is written if the file allows it now."""
        self._checkpoints.stop()
        if self._memory or self._gone:
            self._retry_at = 0.0
            self._retry_if_due()
        if self._memory:
            _LOGGER.error(
                "%d MQTT messages kept in memory are lost: %s cannot be written (%s)",
                len(self._memory),
                self.path,
                self.health.view().cause,
            )
        if self._db is not None:
            with contextlib.suppress(sqlite3.Error):
                self._db.close()
            self._db = None

    # --- on disk ------------------------------------------------------------------------

    def _open(self) -> None:
        """Open the file afresh: the queue on disk, its count, and the next id."""
        self.path.parent.mkdir(parents=True, exist_ok=True)
        try:
            db = open_database(self.path, _PRAGMAS, _SCHEMA)
        except sqlite3.DatabaseError as exc:
            if getattr(exc, "sqlite_errorcode", None) not in _DAMAGED:
                raise
            _set_aside(self.path, exc)
            db = open_database(self.path, _PRAGMAS, _SCHEMA)
        try:
            # Prove the file is writable now, not at the first outage.
            db.execute("BEGIN IMMEDIATE")
            db.execute("COMMIT")
            count, last = db.execute("SELECT COUNT(*), MAX(id) FROM queue").fetchone()
            used = db.execute("SELECT seq FROM sqlite_sequence WHERE name = 'queue'").fetchone()
        except sqlite3.Error:
            db.close()
            raise
        self._db = db
        self._disk = int(count)
        self._next_id = max(int(last or 0), int(used[0]) if used else 0) + 1

    def _put_on_disk(self, db: sqlite3.Connection, messages: Sequence[Message]) -> list[int]:
        first = self._next_id
        ids = list(range(first, first + len(messages)))
        # A retained message superseded within the batch is not written at all.
        latest = {m.topic: i for i, m in enumerate(messages) if m.retain}
        rows = [
            (key, m.topic, m.payload, m.qos, int(m.retain))
            for i, (key, m) in enumerate(zip(ids, messages, strict=True))
            if not m.retain or latest[m.topic] == i
        ]
        try:
            db.execute("BEGIN")
            superseded = 0
            if latest:
                superseded = db.executemany(
                    "DELETE FROM queue WHERE retain = 1 AND topic = ?", [(t,) for t in latest]
                ).rowcount
            db.executemany(_INSERT, rows)
            count = self._disk - superseded + len(rows)
            dropped = self._bound(db, count)
            db.execute("COMMIT")
        except sqlite3.Error:
            _rollback(db)
            raise
        self._next_id = first + len(messages)
        self._disk = count - dropped
        self.dropped += dropped
        self._checkpoints.written()
        return ids

    def _bound(self, db: sqlite3.Connection, count: int) -> int:
        """Drop the oldest messages that are not retained beyond the bound (in a transaction)."""
        excess = count - self.max_messages
        if excess <= 0:
            return 0
        return int(
            db.execute(
                "DELETE FROM queue WHERE id IN "
                "(SELECT id FROM queue WHERE retain = 0 ORDER BY id LIMIT ?)",
                (excess,),
            ).rowcount
        )

    def _peek_disk(self, db: sqlite3.Connection, limit: int) -> list[tuple[int, Message]]:
        query = "SELECT id, topic, payload, qos, retain FROM queue ORDER BY id"
        rows: Iterable[_Row]
        if self._gone:  # removed but not deleted: skipped, however many
            rows = (row for row in db.execute(query) if row[0] not in self._gone)
        else:
            rows = db.execute(f"{query} LIMIT ?", (limit,))
        found = []
        for key, topic, payload, qos, retain in rows:
            found.append(
                (key, Message(topic=topic, payload=bytes(payload), qos=qos, retain=bool(retain)))
            )
            if len(found) >= limit:
                break
        return found

    def _delete(self, db: sqlite3.Connection, ids: Sequence[int]) -> int:
        """Delete rows in one transaction; how many there were."""
        try:
            db.execute("BEGIN")
            removed = db.executemany("DELETE FROM queue WHERE id = ?", [(i,) for i in ids]).rowcount
            db.execute("COMMIT")
        except sqlite3.Error:
            _rollback(db)
            raise
        self._checkpoints.written()
        return int(removed)

    def _forget_on_disk(self, db: sqlite3.Connection | None, ids: Sequence[int]) -> None:
        """Rows acknowledged that cannot be deleted now: skipped until they can be."""
        fresh = [i for i in ids if i not in self._gone]
        if not fresh:
            return
        there = fresh  # unreadable: assumed there (deleted once the file can be written)
        if db is not None:
            marks = ",".join("?" * len(fresh))
            query = f"SELECT id FROM queue WHERE id IN ({marks})"  # noqa: S608 - placeholders
            with contextlib.suppress(sqlite3.Error):
                there = [row[0] for row in db.execute(query, fresh)]
        self._gone.update(there)
        self._disk = max(0, self._disk - len(there))

    # --- in memory, while the file cannot be written -------------------------------------

    def _put_in_memory(self, messages: Sequence[Message]) -> list[int]:
        ids = []
        memory = self._memory
        for message in messages:
            self._last_memory_id -= 1
            key = self._last_memory_id
            ids.append(key)
            if message.retain:
                older = self._retained.get(message.topic)
                if older is not None:
                    memory.pop(older, None)
                self._retained[message.topic] = key
            memory[key] = message
        self._bound_memory()
        return ids

    def _bound_memory(self) -> None:
        """The oldest non-retained messages go first, then the oldest of all if need be."""
        memory = self._memory
        excess = len(memory) - min(self.max_messages, MEMORY_MAX)
        if excess <= 0:
            return
        victims = [k for k, m in memory.items() if not m.retain][:excess]
        if len(victims) < excess:
            chosen = set(victims)
            victims += [k for k in memory if k not in chosen][: excess - len(victims)]
        for key in victims:
            self._forget_in_memory(key)
        self.dropped += len(victims)

    def _forget_in_memory(self, key: int) -> None:
        message = self._memory.pop(key, None)
        if message is not None and message.retain and self._retained.get(message.topic) == key:
            del self._retained[message.topic]

    # --- failure and recovery ------------------------------------------------------------

    def _failed(self, exc: BaseException) -> None:
        """Note the failure: loudly at the first of a streak; try again in a while."""
        cause = failure_cause(self.path, exc)
        self._retry_at = self._clock() + self._retry_s
        if self.health.failed(cause):
            _LOGGER.warning(
                "the MQTT queue %s cannot be written: %s; messages wait in memory (at most "
                "%d) and it is tried again every %.0f s",
                self.path,
                cause,
                min(self.max_messages, MEMORY_MAX),
                self._retry_s,
            )
        else:
            _LOGGER.debug("the MQTT queue %s still cannot be written: %s", self.path, cause)

    def _probe(self) -> None:
        """From any thread (the metrics'): a failed file with nothing waiting in memory.

        Nothing may be written for a long time (``persist: outage`` while connected,
        Sparkplug while the host is online), and the health must not stay failed once
        the disk has room again: the directory is tried, and the file is opened afresh
        at its next use in the event loop's thread.
        """
        if self.health.writable or self._reopen or self._memory or self._gone:
            return
        now = self._clock()
        if now < self._probe_at:
            return
        self._probe_at = now + self._retry_s
        if can_write(self.path.parent, MIN_FREE_BYTES):
            self._reopen = True
            if self.health.recovered():
                _LOGGER.info("the MQTT queue %s can be written again", self.path)

    def _retry_if_due(self) -> None:
        """Open the file afresh and write what waited in memory, at most every ``retry_s``."""
        if self._reopen:
            self._reopen = False  # the probe found the directory writable: open it now
        elif self.health.writable or self._clock() < self._retry_at:
            return
        else:
            self._retry_at = self._clock() + self._retry_s
            if not can_write(self.path.parent, MIN_FREE_BYTES):
                # Not yet: a write might still fit where SQLite reuses its log (or change
                # nothing at all), and the next fail again: a recovery and a failure
                # logged every few seconds.
                return
        if self._db is not None:
            with contextlib.suppress(sqlite3.Error):
                self._db.close()
            self._db = None
        try:
            self._open()
            assert self._db is not None  # noqa: S101 - _open sets it or raises
            self._write_back(self._db)
        except (OSError, sqlite3.Error) as exc:
            if self._db is not None:  # opened, but not writable: still read from
                gone = self._gone
                self._gone = set()
                self._forget_on_disk(self._db, list(gone))
            self._failed(exc)
            return
        waited = len(self._memory)
        self._memory.clear()
        self._retained.clear()
        self._gone.clear()
        self._checkpoints.written()
        if self.health.recovered() or waited:
            _LOGGER.info(
                "the MQTT queue %s can be written again; %d messages moved from memory to it",
                self.path,
                waited,
            )

    def _write_back(self, db: sqlite3.Connection) -> None:
        """Delete what was acknowledged and append what waited in memory, in one transaction."""
        memory = list(self._memory.items())
        first = self._next_id
        try:
            db.execute("BEGIN")
            deleted = db.executemany(
                "DELETE FROM queue WHERE id = ?", [(i,) for i in self._gone]
            ).rowcount
            retained = [(m.topic,) for _, m in memory if m.retain]
            superseded = db.executemany(
                "DELETE FROM queue WHERE retain = 1 AND topic = ?", retained
            ).rowcount
            db.executemany(
                _INSERT,
                [
                    (first + n, m.topic, m.payload, m.qos, int(m.retain))
                    for n, (_, m) in enumerate(memory)
                ],
            )
            count = self._disk - deleted - superseded + len(memory)
            dropped = self._bound(db, count)
            db.execute("COMMIT")
        except sqlite3.Error:
            _rollback(db)
            raise
        self._renumbered.update({key: first + n for n, (key, _) in enumerate(memory)})
        self._next_id = first + len(memory)
        self._disk = count - dropped
        self.dropped += dropped


def _rollback(db: sqlite3.Connection) -> None:
    # SQLite rolls back by itself on some errors (a full disk): then there is none to end.
    if db.in_transaction:
        with contextlib.suppress(sqlite3.Error):
            db.execute("ROLLBACK")


def _set_aside(path: Path, exc: sqlite3.Error) -> None:
    """A damaged queue is kept for a post-mortem under another name, and a new one started."""
    stamp = datetime.now(UTC).strftime("%Y%m%dT%H%M%SZ")
    for suffix in ("", "-wal", "-shm"):
        old = path.with_name(path.name + suffix)
        if old.exists():
            old.rename(path.with_name(f"{path.name}.damaged-{stamp}{suffix}"))
    _LOGGER.error(
        "the MQTT queue %s is damaged (%s): kept as %s.damaged-%s, a new one started; "
        "its messages are not sent",
        path,
        exc,
        path.name,
        stamp,
    )


class _Checkpointer:
    """A thread that makes the disk hold what was committed, every :data:`CHECKPOINT_S`.

    A checkpoint copies the log into the database and waits for the disk twice (SQLite's
    ``synchronous=NORMAL``); on an SD card that can take a good part of a second, which
    the event loop must not wait for. It runs only after something was written, on its
    own connection, and never holds up a writer (``PASSIVE``).
    """

    def __init__(self, path: Path, interval_s: float = CHECKPOINT_S) -> None:
        self._path = path
        self._interval_s = interval_s
        self._dirty = threading.Event()
        self._stopping = threading.Event()
        self._thread = threading.Thread(
            target=self._run, name=f"checkpoint[{path.name}]", daemon=True
        )

    def start(self) -> None:
        self._thread.start()

    def written(self) -> None:
        self._dirty.set()

    def stop(self) -> None:
        self._stopping.set()
        self._dirty.set()
        self._thread.join(timeout=2.0)

    def _run(self) -> None:
        while not self._stopping.wait(self._interval_s):
            if not self._dirty.is_set():
                continue
            self._dirty.clear()
            try:
                # mode=rw: a file that is not there is not created here.
                uri = f"{self._path.resolve().as_uri()}?mode=rw"
                db = sqlite3.connect(uri, uri=True, isolation_level=None, timeout=1.0)
                try:
                    db.execute("PRAGMA wal_checkpoint(PASSIVE)")
                finally:
                    db.close()
            except sqlite3.Error as exc:  # the store itself notes what fails
                _LOGGER.debug("checkpoint of %s: %s", self._path, exc)
