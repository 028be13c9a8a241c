"""The hash chain over the records, and the check that names the first one broken.

Each record is stored as its canonical JSON (keys sorted, no spaces, UTF-8) beside the
SHA-256 of the previous record's hash and that text. Sequence numbers start at 1 and have
no gaps. So a byte changed in a record breaks its own hash, a record taken out leaves a
gap (or, renumbered, a link to a predecessor that is not there), and a record put in
links to a hash its successor does not link to. :func:`verify` walks the chain once and
names the first such record; what it cannot see from the store alone (the newest records
cut off) a head kept elsewhere shows: ``gateway records verify --head SEQ:HASH`` and the
retained ``{base}/records/head`` on MQTT.

Pure: rows in, a verdict out.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from typing import TYPE_CHECKING, Final

if TYPE_CHECKING:
    from collections.abc import Iterable, Mapping

GENESIS: Final = "0" * 64  # the "previous hash" of record 1


def canonical(body: Mapping[str, object]) -> str:
    """The one text of a record's content that its hash is taken over."""
    return json.dumps(body, sort_keys=True, separators=(",", ":"), ensure_ascii=False)


def link(previous: str, text: str) -> str:
    """The hash of a record: SHA-256 over the previous record's hash and its canonical text."""
    return hashlib.sha256(f"{previous}\n{text}".encode()).hexdigest()


@dataclass(frozen=True, slots=True)
class Row:
    """One stored record: its number, its canonical text, the hash it links to, its hash."""

    seq: int
    body: str
    previous: str
    hash: str


@dataclass(frozen=True, slots=True, kw_only=True)
class Head:
    """The newest record's number and hash: what a copy kept elsewhere compares with."""

    seq: int
    hash: str

    def __str__(self) -> str:
        """``SEQ:HASH``, the form ``--head`` takes."""
        return f"{self.seq}:{self.hash}"

    @classmethod
    def parse(cls, text: str) -> Head:
        """``SEQ:HASH`` back into a head (a ValueError saying what is wrong)."""
        seq, sep, digest = text.strip().partition(":")
        if not sep or not seq.isdigit() or len(digest) != 64:  # noqa: PLR2004 - SHA-256 in hex
            msg = f"a head is SEQ:HASH (a record number and 64 hex digits), not {text!r}"
            raise ValueError(msg)
        return cls(seq=int(seq), hash=digest.lower())


EMPTY: Final = Head(seq=0, hash=GENESIS)


@dataclass(frozen=True, slots=True, kw_only=True)
class Verdict:
    """What the check found: the records checked, the head, and the first break if any."""

    checked: int
    head: Head
    broken_at: int | None = None  # the number of the first record changed, removed or put in
    problem: str = ""

    @property
    def intact(self) -> bool:
        """Whether nothing was changed, removed or inserted."""
        return self.broken_at is None

    def as_dict(self) -> dict[str, object]:
        """JSON-ready: the export's last line and the command's ``--json``."""
        return {
            "intact": self.intact,
            "checked": self.checked,
            "head": {"seq": self.head.seq, "hash": self.head.hash},
            "broken_at": self.broken_at,
            "problem": self.problem or None,
        }


def _body_seq(text: str) -> int | None:
    try:
        body = json.loads(text)
    except ValueError:
        return None
    seq = body.get("seq") if isinstance(body, dict) else None
    return seq if isinstance(seq, int) else None


def verify(rows: Iterable[Row], *, expected_head: Head | None = None) -> Verdict:
    """Walk the chain in order of number; the first record that breaks it, named.

    ``expected_head``: a head kept elsewhere (published earlier): the store must still
    hold that record with that hash, else records at or before it were rewritten or
    removed since.
    """
    previous = EMPTY
    hashes: dict[int, str] = {0: GENESIS}
    checked = 0
    for row in rows:
        problem = _break(row, previous)
        if problem is not None:
            at, said = problem
            return Verdict(checked=checked, head=previous, broken_at=at, problem=said)
        previous = Head(seq=row.seq, hash=row.hash)
        hashes[row.seq] = row.hash
        checked += 1
    if expected_head is not None and expected_head.seq > 0:
        held = hashes.get(expected_head.seq)
        if held is None:
            return Verdict(
                checked=checked,
                head=previous,
                broken_at=previous.seq + 1,
                problem=f"the head kept elsewhere is record {expected_head.seq}, but the store "
                f"ends at {previous.seq}: the records after {previous.seq} were removed",
            )
        if held != expected_head.hash:
            return Verdict(
                checked=checked,
                head=previous,
                broken_at=expected_head.seq,
                problem=f"record {expected_head.seq} is not the one whose hash was kept "
                "elsewhere: it, or a record before it, was rewritten and the chain rebuilt",
            )
    return Verdict(checked=checked, head=previous)


def _break(row: Row, previous: Head) -> tuple[int, str] | None:  # noqa: PLR0911 - one per kind of break
    """Where and how ``row`` breaks the chain after ``previous``; ``None`` if it holds.

    In this order: a record whose content does not match its own hash was changed; a
    record whose number inside is not its number in the store was renumbered, after
    records put in before it (inside lower) or taken out (inside higher); a gap is a
    record removed; a record that links to another hash than its predecessor's follows a
    predecessor that was changed and its hash computed again.
    """
    expected = previous.seq + 1
    if link(row.previous, row.body) != row.hash:
        return row.seq, f"record {row.seq} was changed: its content does not match its hash"
    inside = _body_seq(row.body)
    if inside is None:
        return row.seq, f"record {row.seq} was changed: it holds no record number"
    if inside < row.seq:
        return inside, (
            f"record {inside} was inserted: the record that was number {inside} is now "
            f"number {row.seq}, the records after it renumbered"
        )
    if inside > row.seq:
        return row.seq, (
            f"record {row.seq} was removed: record {inside} is now number {row.seq}, the "
            "records after it renumbered"
        )
    if row.seq > expected:
        if row.seq == expected + 1:
            return expected, f"record {expected} was removed"
        return expected, f"records {expected} to {row.seq - 1} were removed"
    if row.seq < expected:
        return row.seq, f"record {row.seq} appears twice: one was inserted"
    if row.previous != previous.hash and previous.seq == 0:
        return row.seq, (
            f"record {row.seq} does not start a chain: it links to a record before it, "
            "which this store does not hold (the store was replaced or cut at its start)"
        )
    if row.previous != previous.hash:
        return previous.seq, (
            f"record {previous.seq} was changed or replaced and its hash computed again: "
            f"record {row.seq} links to another record {previous.seq}"
        )
    return None
