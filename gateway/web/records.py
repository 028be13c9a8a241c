"""The records as the page shows them: chosen, newest first, bounded, with the chain's verdict.

``GET /api/records`` reads the record store the running gateway appends to (21 CFR Part 11
§11.10(b), readable copies; the issue's "the page's records view lists them, filters by
device and kind, and prints"). The store's connection belongs to the event loop's thread
and SQLite's objects stay in the thread that made them, so the page reads through a
read-only store of its own on the same file, opened, read and closed in a worker thread
(:func:`read_records`, run with ``asyncio.to_thread``): the chain's check reads every record
and takes a while on a store of years, and the loop goes on polling meanwhile.

Each record becomes one flat row per point it touched, the way a table prints it: who,
via, device, action, each point's value as found and as left. A write's value as left is
in the outcome record that completes it; the view joins the two, so the write's row
reads "as found → as left" and the outcome's row "as found" too.

A verification's form is told what the page cannot know by itself: the point it
compares, that point's unit, the device's acceptance rule and the calibration the
device offers (:func:`verification_form`). Pure but for :func:`read_records`.
"""

from __future__ import annotations

import collections
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import TYPE_CHECKING, Final

from gateway.errors import CommandRejectedError
from gateway.records import Kind, Query, RecordStore
from gateway.records.export import rows
from gateway.web.care import calibration_offer

if TYPE_CHECKING:
    from collections.abc import Iterable, Mapping, Sequence
    from pathlib import Path

    from gateway.profiles.model import Point
    from gateway.records import Record
    from gateway.records.verification import AcceptanceRule

DEFAULT_LIMIT: Final = 500  # records a view sends unless asked for fewer or more
MAX_LIMIT: Final = 5000  # beyond this, `gateway records export` makes the copy
SHORT_HASH: Final = 12  # hex digits of a hash the page shows (the full one in its title)
DEFAULT_METHOD: Final = "DPD"  # the grab sample's analysis most plants use for chlorine
KINDS: Final = frozenset(str(kind) for kind in Kind)


@dataclass(frozen=True, slots=True, kw_only=True)
class RecordsRequest:
    """Which records a view asks for, checked where the query string comes in.

    >>> RecordsRequest.parse(device="pool", kinds=["write,outcome"], limit="20").limit
    20
    """

    query: Query
    limit: int = DEFAULT_LIMIT

    @classmethod
    def parse(
        cls,
        *,
        device: str | None = None,
        kinds: Iterable[str] = (),
        since: str | None = None,
        until: str | None = None,
        limit: str | None = None,
    ) -> RecordsRequest:
        """From the query string; a :class:`CommandRejectedError` saying what is wrong.

        ``kinds``: each ``kind`` given, each a kind or several separated by commas.
        ``since`` and ``until``: ISO 8601 times, UTC unless they carry an offset.
        """
        chosen = sorted({k.strip() for text in kinds for k in text.split(",") if k.strip()})
        unknown = [kind for kind in chosen if kind not in KINDS]
        if unknown:
            raise CommandRejectedError(
                f"no kind of record {', '.join(unknown)}; kinds: {', '.join(sorted(KINDS))}"
            )
        return cls(
            query=Query(
                device=device or None,
                kinds=tuple(chosen),
                since=_time(since, "since"),
                until=_time(until, "until"),
            ),
            limit=_limit(limit),
        )


def _time(text: str | None, name: str) -> datetime | None:
    if not text:
        return None
    try:
        moment = datetime.fromisoformat(text.strip())
    except ValueError:
        msg = f"{name}: {text!r} is not an ISO 8601 time (2025-06-01 or 2025-06-01T08:00Z)"
        raise CommandRejectedError(msg) from None
    return moment if moment.tzinfo is not None else moment.replace(tzinfo=UTC)


def _limit(text: str | None) -> int:
    if text is None or text == "":
        return DEFAULT_LIMIT
    try:
        limit = int(text)
    except ValueError:
        raise CommandRejectedError(f"limit must be a whole number, not {text!r}") from None
    if not 0 <= limit <= MAX_LIMIT:
        msg = f"limit must be 0 to {MAX_LIMIT} (more: gateway records export), not {limit}"
        raise CommandRejectedError(msg)
    return limit


def value_text(value: object) -> str:
    """A value as a record keeps it, as a table cell reads it (the JSON stays beside it)."""
    if value is None:
        return ""
    if isinstance(value, dict):
        if "fault" in value:
            return f"fault: {value['fault']}"
        if "label" in value:
            return str(value["label"])
        if "bits" in value:
            bits = value["bits"]
            return ", ".join(map(str, bits)) if isinstance(bits, list) and bits else "no bit set"
    if isinstance(value, float):
        return f"{value:.7g}"
    return str(value)


def _changes(record: Record) -> list[Mapping[str, object]]:
    points = record.body.get("points")
    return [p for p in points if isinstance(p, dict)] if isinstance(points, list) else []


def _by_point(record: Record | None, field: str) -> dict[str, object]:
    """A record's values of one field (``as_found``, ``as_left``) by point name."""
    if record is None:
        return {}
    return {str(c.get("point")): c.get(field) for c in _changes(record) if c.get(field) is not None}


def record_view(
    record: Record, *, outcome: Record | None = None, write: Record | None = None
) -> dict[str, object]:
    """One record for the page: its fields flat, its points as rows, a write's outcome joined.

    ``outcome``: the record that completes this write (its values as left, its result);
    ``write``: the write this outcome completes (its values as found).
    """
    flat = rows(record)
    first = flat[0]
    left = _by_point(outcome, "as_left")
    found = _by_point(write, "as_found")
    points = []
    for change in _changes(record):
        name = str(change.get("point"))
        as_found = change.get("as_found", found.get(name))
        as_found = found.get(name) if as_found is None else as_found
        as_left = change.get("as_left")
        as_left = left.get(name) if as_left is None else as_left
        points.append(
            {
                "point": name,
                "unit": change.get("unit"),
                "as_found": as_found,
                "sent": change.get("sent"),
                "as_left": as_left,
                "as_found_text": value_text(as_found),
                "sent_text": value_text(change.get("sent")),
                "as_left_text": value_text(as_left),
            }
        )
    data = record.body.get("data")
    return {
        "seq": record.seq,
        "hash": record.hash,
        "time": first["time"],
        "clock_synchronised": record.body.get("clock_synchronised"),
        "kind": record.kind,
        "user": first["user"],
        "via": first["via"],
        "detail": first["detail"],
        "signed": record.body.get("actor", {}).get("signed") is True,
        "reason": first["reason"],
        "device": record.device,
        "serial": first["serial"] or None,
        "action": first["action"],
        "points": points,
        "result": first["result"],
        "note": first["note"],
        "completes": record.body.get("completes"),
        "corrects": record.body.get("corrects"),
        "data": data if isinstance(data, dict) else {},
        "outcome": None
        if outcome is None
        else {"seq": outcome.seq, "result": str(outcome.body.get("result", ""))},
    }


def newest(records: Iterable[Record], limit: int) -> tuple[list[Record], bool]:
    """The ``limit`` newest of ``records`` (oldest first in), newest first out; whether cut."""
    kept: collections.deque[Record] = collections.deque(maxlen=limit or None)
    seen = 0
    for record in records:
        seen += 1
        if limit:
            kept.append(record)
    return list(reversed(kept)), seen > len(kept)


def _joined(store: RecordStore, chosen: Sequence[Record], query: Query) -> list[dict[str, object]]:
    """The views of ``chosen``, each write with its outcome and each outcome with its write."""
    by_seq = {record.seq: record for record in chosen}
    outcomes = {
        int(r.body["completes"]): r
        for r in chosen
        if r.kind == Kind.OUTCOME and isinstance(r.body.get("completes"), int)
    }
    writes = [r for r in chosen if r.kind == Kind.WRITE and r.seq not in outcomes]
    if writes:  # their outcomes were not chosen (a kind filter, the limit): look them up
        later = Query(device=query.device, kinds=(Kind.OUTCOME,), since=_parsed(writes[-1].time))
        wanted = {w.seq for w in writes}
        for record in store.records(later):
            completes = record.body.get("completes")
            if isinstance(completes, int) and completes in wanted:
                outcomes[completes] = record
    views = []
    for record in chosen:
        completes = record.body.get("completes")
        write = None
        if record.kind == Kind.OUTCOME and isinstance(completes, int):
            write = by_seq.get(completes) or store.get(completes)
        views.append(record_view(record, outcome=outcomes.get(record.seq), write=write))
    return views


def _parsed(time: str) -> datetime | None:
    try:
        return datetime.fromisoformat(time)
    except ValueError:
        return None


def head_view(seq: int, digest: str) -> dict[str, object]:
    """The chain's head as the page shows it: its number and the first digits of its hash."""
    return {"seq": seq, "hash": digest, "short": digest[:SHORT_HASH]}


def read_records(path: Path, request: RecordsRequest) -> dict[str, object]:
    """The records ``request`` chooses, newest first, and the whole chain's verdict.

    Blocking (run it in a thread): a read-only store of this thread's own on ``path``,
    closed again. A :class:`~gateway.errors.RecordError` if the file cannot be read.
    """
    store = RecordStore(path, read_only=True)
    try:
        chosen, more = newest(store.records(request.query), request.limit)
        views = _joined(store, chosen, request.query)
        verdict = store.verify()
    finally:
        store.close()
    return {
        "records": views,
        "count": len(views),
        "more": more,  # older records match too: narrow the filters or export them
        "limit": request.limit,
        "head": head_view(verdict.head.seq, verdict.head.hash),
        "verdict": verdict.as_dict(),
    }


def verification_form(
    device: str,
    profile_id: str,
    point: Point,
    *,
    unit: str | None,
    rule: AcceptanceRule | None,
) -> dict[str, object]:
    """What the page's verification form of ``device`` starts from.

    ``unit``: the point's unit as the sensor last reported it (a unit register may change
    it), else the profile's; ``rule``: the device's acceptance rule, ``None`` if it has
    none (the form says so, and the gateway would refuse).
    """
    return {
        "device": device,
        "profile": profile_id,
        "point": point.name,
        "unit": unit if unit is not None else point.unit,
        "method": DEFAULT_METHOD,
        "rule": None if rule is None else rule.as_dict(),
        "calibration": calibration_offer(profile_id),
    }
