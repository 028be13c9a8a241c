"""Store and forward: MQTT messages kept on disk while the broker is away.

aiomqtt does not buffer: a publish while disconnected raises. So every message that
cannot go out at once is appended here (SQLite in the state directory), in order, and
sent from here when the broker is back, before any newer message. A restart during an
outage loses nothing. The queue is bounded: past the bound the oldest messages that are
not retained are dropped and counted; a retained message supersedes an older retained
one for the same topic (only the last one matters to a subscriber).
"""

from __future__ import annotations

import sqlite3
from typing import TYPE_CHECKING

from gateway.errors import PublishError
from gateway.publish.message import Message

if TYPE_CHECKING:
    from collections.abc import Sequence
    from pathlib import Path

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


class MessageStore:
    """A bounded, persistent FIFO of MQTT messages."""

    def __init__(self, path: Path, *, max_messages: int) -> None:
        """Open (or create) the queue at ``path``; a path that cannot be written raises."""
        self.path = path
        self.max_messages = max_messages
        self.dropped = 0
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            self._db = sqlite3.connect(path, isolation_level=None)
            self._db.executescript(_SCHEMA)
            self._db.execute("PRAGMA journal_mode=WAL")
            self._db.execute("PRAGMA synchronous=NORMAL")
            # Prove the file is writable now, not at the first outage.
            self._db.execute("BEGIN IMMEDIATE")
            self._db.execute("COMMIT")
        except (OSError, sqlite3.Error) as exc:
            raise PublishError(f"the MQTT queue {path} cannot be written: {exc}") from exc
        self._count = int(self._db.execute("SELECT COUNT(*) FROM queue").fetchone()[0])

    def __len__(self) -> int:
        """Messages waiting."""
        return self._count

    def append(self, messages: Sequence[Message]) -> int:
        """Queue messages in order; returns how many old messages the bound dropped."""
        if not messages:
            return 0
        db = self._db
        try:
            db.execute("BEGIN")
            for message in messages:
                if message.retain:
                    self._count -= db.execute(
                        "DELETE FROM queue WHERE retain = 1 AND topic = ?", (message.topic,)
                    ).rowcount
                db.execute(
                    "INSERT INTO queue (topic, payload, qos, retain) VALUES (?, ?, ?, ?)",
                    (message.topic, message.payload, message.qos, int(message.retain)),
                )
            self._count += len(messages)
            dropped = 0
            excess = self._count - self.max_messages
            if excess > 0:
                dropped = db.execute(
                    "DELETE FROM queue WHERE id IN "
                    "(SELECT id FROM queue WHERE retain = 0 ORDER BY id LIMIT ?)",
                    (excess,),
                ).rowcount
                self._count -= dropped
            db.execute("COMMIT")
        except sqlite3.Error as exc:
            db.execute("ROLLBACK")
            raise PublishError(f"cannot queue MQTT messages in {self.path}: {exc}") from exc
        self.dropped += dropped
        return dropped

    def peek(self, limit: int) -> list[tuple[int, Message]]:
        """The oldest ``limit`` messages with their ids, without removing them."""
        rows = self._db.execute(
            "SELECT id, topic, payload, qos, retain FROM queue ORDER BY id LIMIT ?", (limit,)
        ).fetchall()
        return [
            (row[0], Message(topic=row[1], payload=bytes(row[2]), qos=row[3], retain=bool(row[4])))
            for row in rows
        ]

    def remove(self, ids: Sequence[int]) -> None:
        """Forget messages that the broker acknowledged."""
        if not ids:
            return
        removed = self._db.executemany(
            "DELETE FROM queue WHERE id = ?", [(i,) for i in ids]
        ).rowcount
        self._count -= removed

    def close(self) -> None:
        """Close the database (what is queued stays on disk)."""
        self._db.close()
