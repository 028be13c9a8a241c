"""What the gateway keeps on disk, and whether it can: the files of the state directory.

The MQTT queue, Sparkplug's queue and the flash-write ledger live in ``state_dir``. A disk
that filled up, or a file system the kernel made read-only after an I/O error (what an SD
card's failing controller leads to), must not stop the polling. So each store keeps a
:class:`StoreHealth`: whether its file could be written at the last try, and if not, why,
in a plant engineer's words (:func:`failure_cause`). The store writes it from the event
loop; the metrics and ``/healthz`` read it from their own thread through
:class:`StorageStatus`, which also asks the file system (:func:`directory_condition`)
how much room is left, so a disk that fills up is seen before the first write fails.

The SQLite settings of each store, and why, are in the manual (What survives a power cut).
"""

from __future__ import annotations

import contextlib
import errno
import os
import sqlite3
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Final

if TYPE_CHECKING:
    from collections.abc import Callable, Sequence

RETRY_S: Final = 5.0  # how often a file that cannot be written is tried again

# What SQLite's extended result codes mean for a plant engineer (the primary code is the
# low byte: SQLITE_IOERR_WRITE is 778 = 10 | 3 << 8).
_SQLITE_CAUSES: Final = {
    sqlite3.SQLITE_FULL: "the disk is full",
    sqlite3.SQLITE_READONLY: "the file or its directory is read-only",
    sqlite3.SQLITE_IOERR: "the disk reports an I/O error",
    sqlite3.SQLITE_CANTOPEN: "the file cannot be opened",
    sqlite3.SQLITE_CORRUPT: "the file is damaged",
    sqlite3.SQLITE_NOTADB: "the file is not a database",
    sqlite3.SQLITE_PERM: "permission denied",
}
# SQLite's words where the file system's say more: "disk I/O error" on a file system ext4
# stopped writing, "unable to open database file" for a journal that cannot be created.
_VAGUE: Final = frozenset({sqlite3.SQLITE_IOERR, sqlite3.SQLITE_CANTOPEN, sqlite3.SQLITE_READONLY})
_OS_CAUSES: Final = {
    errno.ENOSPC: "the disk is full",
    errno.EDQUOT: "the disk quota is used up",
    errno.EROFS: "the file system is read-only",
    errno.EACCES: "permission denied (the service user cannot write there)",
    errno.EPERM: "permission denied (the service user cannot write there)",
    errno.EIO: "the disk reports an I/O error",
}


@dataclass(frozen=True, slots=True, kw_only=True)
class DirectoryCondition:
    """What the file system says of a directory: room left, and whether it is read-only."""

    path: Path
    free_bytes: int | None  # for an unprivileged user; None if the directory cannot be asked
    read_only: bool


def directory_condition(path: Path) -> DirectoryCondition:
    """Ask the file system holding ``path`` (or its nearest existing parent); never raises."""
    probe = path
    while not probe.exists() and probe != probe.parent:
        probe = probe.parent
    try:
        stats = os.statvfs(probe)
    except OSError:
        return DirectoryCondition(path=path, free_bytes=None, read_only=False)
    return DirectoryCondition(
        path=path,
        free_bytes=stats.f_bavail * stats.f_frsize,
        read_only=bool(stats.f_flag & os.ST_RDONLY),
    )


def failure_cause(path: Path, exc: BaseException) -> str:
    """Why ``path`` cannot be written, in plain words, with the system's own words after.

    The file system is asked first: SQLite says "disk I/O error" where the kernel had made
    the file system read-only, and "unable to open database file" for a directory that
    cannot be created.
    """
    said = str(exc) or type(exc).__name__
    condition = directory_condition(path.parent)
    if condition.read_only:
        return f"the file system is read-only ({said})"
    if condition.free_bytes == 0:
        return f"the disk is full ({said})"
    if isinstance(exc, sqlite3.Error):
        code = getattr(exc, "sqlite_errorcode", None)
        primary = code & 0xFF if isinstance(code, int) else None
        if primary in _VAGUE and (refused := _write_refused(path.parent)):
            exc = refused  # what the file system says beneath SQLite's "disk I/O error"
        else:
            plain = _SQLITE_CAUSES.get(primary) if primary is not None else None
            return f"{plain} ({said})" if plain else said
    if isinstance(exc, OSError) and exc.errno in _OS_CAUSES:
        return f"{_OS_CAUSES[exc.errno]} ({exc.strerror or said})"
    return said


def open_database(
    path: Path | str, pragmas: Sequence[str], schema: str, *, timeout_s: float = 5.0
) -> sqlite3.Connection:
    """An SQLite file opened in autocommit, its settings and schema applied, or closed again.

    ``timeout_s``: how long a statement waits for another process's lock (SQLite's busy
    timeout). The MQTT queue and the flash-write ledger open their files this way.
    """
    db = sqlite3.connect(path, isolation_level=None, timeout=timeout_s)
    try:
        for pragma in pragmas:
            db.execute(pragma)
        db.executescript(schema)
    except sqlite3.Error:
        db.close()
        raise
    return db


def takes_a_change(path: Path, schema: str, change: str) -> bool:
    """Whether the SQLite file at ``path`` takes ``change`` now (rolled back, nothing kept).

    On a connection of its own (any thread): the rollback journal is written first, which
    a full disk or a read-only file system refuses. A store that failed asks this again
    from the metrics' thread (its :attr:`StoreHealth.probe`), so that its health recovers
    without waiting for its next write. ``schema`` makes a file that could not be made at
    the start.
    """
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        db = sqlite3.connect(path, isolation_level=None, timeout=0.5)
        try:
            db.executescript(schema)
            db.execute("BEGIN IMMEDIATE")
            db.execute(change)
        finally:
            with contextlib.suppress(sqlite3.Error):
                db.execute("ROLLBACK")
            db.close()
    except (OSError, sqlite3.Error):
        return False
    return True


def can_write(directory: Path, min_free_bytes: int) -> bool:
    """Whether ``directory`` has room and takes a new file (one is made and deleted)."""
    room = directory_condition(directory)
    if room.read_only or (room.free_bytes is not None and room.free_bytes < min_free_bytes):
        return False
    return _write_refused(directory) is None


def _write_refused(directory: Path) -> OSError | None:
    """The error of creating a file in ``directory``, if any: the file system's own word.

    ext4 stops writing after an error (``errors=remount-ro``) without the read-only flag
    that ``statvfs`` reports (Linux 6.x: ``emergency_ro``); only a write says so (EROFS).
    """
    try:
        handle, name = tempfile.mkstemp(dir=directory, prefix=".write-probe-")
    except OSError as exc:
        return exc
    os.close(handle)
    with contextlib.suppress(OSError):
        Path(name).unlink()
    return None


@dataclass(frozen=True, slots=True, kw_only=True)
class FileHealth:
    """A store's file as the metrics see it (a copy)."""

    path: Path
    writable: bool
    cause: str  # why not; "" while writable
    meanwhile: str  # what the gateway does while it cannot write it
    since: float | None  # when it stopped being writable (seconds since the epoch)
    failures: int  # how often it stopped being writable since the start


class StoreHealth:
    """Whether one store's file could be written at the last try, and why not.

    Written by its store (the event loop's thread), read by the metrics' thread.
    """

    def __init__(self, path: Path, *, meanwhile: str) -> None:
        """The health of the file at ``path``; writable until a write fails.

        ``meanwhile`` says what its store does while it cannot write (``/healthz``).
        """
        self.path = path
        self.meanwhile = meanwhile
        # Tries the file again from any thread (the metrics'), where its store can: the
        # ledger, which is written only at a flash write, would else look failed for good.
        self.probe: Callable[[], None] | None = None
        self._lock = threading.Lock()
        self._cause = ""
        self._since: float | None = None
        self._failures = 0

    @property
    def writable(self) -> bool:
        """Whether the last write (or opening) succeeded."""
        return self._since is None

    def failed(self, cause: str) -> bool:
        """Note a failure; true at the first of a streak (the one to log loudly)."""
        with self._lock:
            first = self._since is None
            if first:
                self._since = time.time()
                self._failures += 1
            self._cause = cause
            return first

    def recovered(self) -> bool:
        """Note a write that succeeded; true if the file had been failing (to log)."""
        with self._lock:
            was_failing = self._since is not None
            self._since = None
            self._cause = ""
            return was_failing

    def view(self) -> FileHealth:
        """A copy, for another thread."""
        with self._lock:
            return FileHealth(
                path=self.path,
                writable=self._since is None,
                cause=self._cause,
                meanwhile=self.meanwhile,
                since=self._since,
                failures=self._failures,
            )


class StorageStatus:
    """The stores of the state directory, registered at start; read at every scrape.

    Shared by the state's snapshots, not copied: it keeps its own lock.
    """

    def __init__(self) -> None:
        """No store yet."""
        self._lock = threading.Lock()
        self._stores: dict[Path, StoreHealth] = {}

    def track(self, health: StoreHealth) -> None:
        """Report on ``health``'s file from now on.

        It replaces a store of the same file opened before (a reload opens it again).
        """
        with self._lock:
            self._stores[health.path] = health

    def files(self) -> list[FileHealth]:
        """Every store's file, in the order registered (one that failed tried again)."""
        with self._lock:
            stores = list(self._stores.values())
        for store in stores:
            if not store.writable and store.probe is not None:
                store.probe()
        return [store.view() for store in stores]

    def directories(self) -> list[DirectoryCondition]:
        """The condition of each directory that holds a store (normally one: ``state_dir``)."""
        with self._lock:
            directories = dict.fromkeys(path.parent for path in self._stores)
        return [directory_condition(directory) for directory in directories]
