"""The record store: an append-only, hash-chained SQLite file in the state directory.

Apart from the MQTT queue and the flash-write ledger (``records.sqlite``), since it is
kept for years and handed to auditors. One table of records, each its canonical JSON,
the hash it links to and its own hash (:mod:`gateway.records.chain`); triggers refuse an
``UPDATE`` or a ``DELETE`` so that no code path of the gateway, nor a slip at the
``sqlite3`` prompt, rewrites one; what a determined hand does to the file anyway,
``gateway records verify`` names.

An append is one transaction that reads the newest record and adds the next
(``BEGIN IMMEDIATE``: a second process appending at the same time waits, and the
numbers stay without gaps), committed with ``synchronous=EXTRA`` before the call
returns: the record is on the disk before the act it records is done. A record that
cannot be written raises :class:`~gateway.errors.RecordError`, and the act is refused.

Used from the event loop's thread (an append costs one fsync, a few milliseconds; writes
to sensors are rare, and compensation feeds are counted per day, not recorded one by
one); :attr:`RecordStore.head` is a copy any thread may read (the metrics).
"""

from __future__ import annotations

import contextlib
import json
import logging
import sqlite3
import threading
import time
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING, Final

from gateway.errors import RecordError
from gateway.records.chain import EMPTY, Head, Row, Verdict, canonical, link, verify
from gateway.records.model import Entry, Record
from gateway.shared.storage import (
    RETRY_S,
    StoreHealth,
    failure_cause,
    open_database,
    takes_a_change,
)

if TYPE_CHECKING:
    from collections.abc import Callable, Collection, Iterator

_LOGGER = logging.getLogger(__name__)

RECORDS_FILE: Final = "records.sqlite"  # in the state directory
_PRAGMAS: Final = ("PRAGMA journal_mode=DELETE", "PRAGMA synchronous=EXTRA")
_BUSY_TIMEOUT_S: Final = 5.0  # an export reading beside the running gateway
_SCHEMA: Final = """
CREATE TABLE IF NOT EXISTS records (
    seq INTEGER PRIMARY KEY,
    time TEXT NOT NULL,
    kind TEXT NOT NULL,
    device TEXT,
    body TEXT NOT NULL,
    previous TEXT NOT NULL,
    hash TEXT NOT NULL
);
CREATE INDEX IF NOT EXISTS records_device ON records (device, seq);
CREATE TRIGGER IF NOT EXISTS records_never_updated BEFORE UPDATE ON records
BEGIN SELECT RAISE(ABORT, 'records are append-only: a correction is a new record'); END;
CREATE TRIGGER IF NOT EXISTS records_never_deleted BEFORE DELETE ON records
BEGIN SELECT RAISE(ABORT, 'records are append-only: nothing is deleted'); END;
"""
# A change the probe rolls back (a record number no record has).
_PROBE: Final = (
    "INSERT INTO records (seq, time, kind, body, previous, hash) VALUES (-1, '', '', '', '', '')"
)


@dataclass(frozen=True, slots=True, kw_only=True)
class Query:
    """Which records to read: by device, kinds and UTC time (ISO 8601 text compares)."""

    device: str | None = None
    kinds: Collection[str] = ()
    since: datetime | None = None
    until: datetime | None = None


def _synchronised_now() -> bool:
    from gateway.shared.host_clock import HostClock  # noqa: PLC0415 - the default only

    return HostClock().status().synchronised


class RecordStore:
    """The records of one gateway (its state directory), appended and read."""

    def __init__(
        self,
        path: Path,
        *,
        clock_synchronised: Callable[[], bool] = _synchronised_now,
        now: Callable[[], datetime] = lambda: datetime.now(UTC),
        read_only: bool = False,
    ) -> None:
        """Open (or, unless ``read_only``, create) the store at ``path``.

        ``clock_synchronised`` says whether the host clock is synchronised at each record
        (the running gateway's :class:`~gateway.shared.host_clock.HostClock`); ``now``
        dates them.
        """
        self.path = path
        self.read_only = read_only
        self.health = StoreHealth(path, meanwhile="writes to sensors are refused")
        self.health.probe = self.probe  # the metrics' thread tries it again (see probe)
        self._probe_at = 0.0
        self._clock_synchronised = clock_synchronised
        self._now = now
        self._lock = threading.Lock()
        self._listeners: list[Callable[[Record], None]] = []
        self._db_open: sqlite3.Connection | None = None
        self._head = EMPTY
        try:
            self._head = self._read_head()
        except RecordError as exc:
            if read_only:
                raise
            # Polling goes on; writes to sensors are refused until the file can be written.
            _LOGGER.warning("%s; writes to sensors are refused until it can", exc)

    @property
    def _db(self) -> sqlite3.Connection:
        """The open file, opened afresh after a failure (a file system mounted again)."""
        if self._db_open is None:
            self._db_open = self._open()
        return self._db_open

    def _open(self) -> sqlite3.Connection:
        path = self.path
        try:
            if self.read_only:
                if not path.is_file():
                    msg = (
                        f"there are no records at {path}: no change has been recorded in "
                        "this state directory (is state_dir the running gateway's?)"
                    )
                    raise RecordError(msg)
                return sqlite3.connect(
                    f"file:{path}?mode=ro",
                    uri=True,
                    isolation_level=None,
                    timeout=_BUSY_TIMEOUT_S,
                )
            path.parent.mkdir(parents=True, exist_ok=True)
            return open_database(path, _PRAGMAS, _SCHEMA, timeout_s=_BUSY_TIMEOUT_S)
        except (OSError, sqlite3.Error) as exc:
            cause = failure_cause(path, exc)
            self.health.failed(cause)
            msg = f"the record store {path} cannot be opened: {cause}"
            raise RecordError(msg) from exc

    def probe(self) -> None:
        """Try a store that failed again, at most every :data:`RETRY_S`.

        ``/healthz`` and the metrics call it (through :attr:`health`), so that the health
        recovers without waiting for the next write to a sensor. On a connection of its
        own (any thread), a record added and rolled back: the rollback journal is written
        first, which a full disk or a read-only file system refuses; nothing is recorded.
        """
        if self.health.writable or self.read_only:
            return
        now = time.monotonic()
        with self._lock:
            if now < self._probe_at:
                return
            self._probe_at = now + RETRY_S
        if not takes_a_change(self.path, _SCHEMA, _PROBE):
            return
        # The append that failed closed its connection: the next opens the file afresh.
        if self.health.recovered():
            _LOGGER.info("the record store %s can be written again", self.path)

    def close(self) -> None:
        """Close the file (the records stay, of course)."""
        if self._db_open is not None:
            with contextlib.suppress(sqlite3.Error):
                self._db_open.close()
            self._db_open = None

    def _read_head(self) -> Head:
        db = self._db
        try:
            row = db.execute("SELECT seq, hash FROM records ORDER BY seq DESC LIMIT 1").fetchone()
        except sqlite3.Error as exc:
            msg = f"the record store {self.path} cannot be read: {failure_cause(self.path, exc)}"
            raise RecordError(msg) from exc
        return EMPTY if row is None else Head(seq=int(row[0]), hash=str(row[1]))

    @property
    def head(self) -> Head:
        """The newest record's number and hash (any thread)."""
        with self._lock:
            return self._head

    def listen(self, listener: Callable[[Record], None]) -> None:
        """Call ``listener`` with every record appended from now on (MQTT, the page)."""
        self._listeners.append(listener)

    def append(self, entry: Entry) -> Record:
        """Add ``entry`` as the next record, on the disk when this returns.

        A :class:`RecordError` with the cause if it cannot be written: the caller must
        then not do what it was going to record.
        """
        if self.read_only:
            msg = f"the record store {self.path} was opened to read only"
            raise RecordError(msg)
        self.catch_up()  # another process's records first, so that listeners see all, in order
        moment = self._now().astimezone(UTC)
        try:
            synchronised = self._clock_synchronised()
        except OSError:
            synchronised = False
        try:
            try:
                seq, body, digest = self._insert(entry, moment, synchronised=synchronised)
            except sqlite3.Error:
                # A connection opened before the file system was mounted again (after an
                # I/O error, or a repair) fails at once: one more try on a fresh one.
                self.close()
                seq, body, digest = self._insert(entry, moment, synchronised=synchronised)
        except RecordError:
            raise
        except (OSError, sqlite3.Error) as exc:
            cause = failure_cause(self.path, exc)
            self.close()
            if self.health.failed(cause):
                _LOGGER.warning(
                    "the record store %s cannot be written: %s; writes to sensors are "
                    "refused until it can",
                    self.path,
                    cause,
                )
            msg = (
                f"the record store {self.path} cannot be written ({cause}): writes to sensors "
                "are refused until it can, so nothing was written"
            )
            raise RecordError(msg) from exc
        if self.health.recovered():
            _LOGGER.info("the record store %s can be written again", self.path)
        record = Record(seq=seq, hash=digest, body=body)
        with self._lock:
            self._head = Head(seq=seq, hash=digest)
        self._tell(record)
        return record

    def _insert(
        self, entry: Entry, moment: datetime, *, synchronised: bool
    ) -> tuple[int, dict[str, object], str]:
        """One transaction: read the newest record, add the next; its number, body, hash."""
        db = self._db
        db.execute("BEGIN IMMEDIATE")
        try:
            newest = db.execute(
                "SELECT seq, hash FROM records ORDER BY seq DESC LIMIT 1"
            ).fetchone()
            previous = EMPTY if newest is None else Head(seq=int(newest[0]), hash=newest[1])
            seq = previous.seq + 1
            body = entry.body(seq=seq, time=moment, clock_synchronised=synchronised)
            text = canonical(body)
            digest = link(previous.hash, text)
            db.execute(
                "INSERT INTO records (seq, time, kind, device, body, previous, hash) "
                "VALUES (?, ?, ?, ?, ?, ?, ?)",
                (
                    seq,
                    body["time"],
                    str(entry.kind),
                    None if entry.device is None else entry.device.name,
                    text,
                    previous.hash,
                    digest,
                ),
            )
            db.execute("COMMIT")
        except BaseException:
            with contextlib.suppress(sqlite3.Error):
                db.execute("ROLLBACK")
            raise
        return seq, body, digest

    def catch_up(self) -> list[Record]:
        """The records another process appended since this one's head, told to the listeners.

        The command line appends beside the running gateway (``gateway records correct``,
        a verification without one): the gateway's head, its MQTT messages and the page
        follow at its next look (a few seconds).
        """
        try:
            cursor = self._db.execute(
                "SELECT seq, hash, body FROM records WHERE seq > ? ORDER BY seq",
                (self.head.seq,),
            )
            found = [
                Record(seq=int(seq), hash=str(digest), body=json.loads(body))
                for seq, digest, body in cursor
            ]
        except (sqlite3.Error, RecordError) as exc:  # a store that cannot be read now
            _LOGGER.debug("the record store %s was not read: %s", self.path, exc)
            return []
        for record in found:
            with self._lock:
                self._head = Head(seq=record.seq, hash=record.hash)
            self._tell(record)
        return found

    def _tell(self, record: Record) -> None:
        for listener in self._listeners:
            try:
                listener(record)
            except Exception:  # a listener's bug must not undo a record on disk
                _LOGGER.exception("a listener of the records failed on record %d", record.seq)

    def rows(self) -> Iterator[Row]:
        """Every stored row in order of number, as the chain checks them."""
        cursor = self._db.execute("SELECT seq, body, previous, hash FROM records ORDER BY seq")
        for seq, body, previous, digest in cursor:
            yield Row(int(seq), str(body), str(previous), str(digest))

    def verify(self, expected_head: Head | None = None) -> Verdict:
        """Check the whole chain (and a head kept elsewhere): see :func:`chain.verify`."""
        try:
            return verify(self.rows(), expected_head=expected_head)
        except sqlite3.Error as exc:
            msg = f"the record store {self.path} cannot be read: {failure_cause(self.path, exc)}"
            raise RecordError(msg) from exc

    def records(self, query: Query | None = None) -> Iterator[Record]:
        """The records that match ``query``, oldest first."""
        query = query or Query()
        clauses: list[str] = []
        values: list[object] = []
        if query.device is not None:
            clauses.append("device = ?")
            values.append(query.device)
        if query.kinds:
            clauses.append(f"kind IN ({', '.join('?' for _ in query.kinds)})")
            values.extend(query.kinds)
        if query.since is not None:
            clauses.append("time >= ?")
            values.append(query.since.astimezone(UTC).isoformat(timespec="milliseconds"))
        if query.until is not None:
            clauses.append("time <= ?")
            values.append(query.until.astimezone(UTC).isoformat(timespec="milliseconds"))
        where = f" WHERE {' AND '.join(clauses)}" if clauses else ""
        try:
            cursor = self._db.execute(
                f"SELECT seq, hash, body FROM records{where} ORDER BY seq",  # noqa: S608 - fixed clauses
                values,
            )
            for seq, digest, body in cursor:
                yield Record(seq=int(seq), hash=str(digest), body=json.loads(body))
        except sqlite3.Error as exc:
            msg = f"the record store {self.path} cannot be read: {failure_cause(self.path, exc)}"
            raise RecordError(msg) from exc

    def get(self, seq: int) -> Record | None:
        """The record of that number, if there is one."""
        row = self._db.execute("SELECT hash, body FROM records WHERE seq = ?", (seq,)).fetchone()
        return None if row is None else Record(seq=seq, hash=str(row[0]), body=json.loads(row[1]))


def records_path(state_dir: Path) -> Path:
    """The record store's file in a state directory."""
    return Path(state_dir) / RECORDS_FILE
