"""The hash chain: a byte changed, a record removed, a record inserted, each named.

The tampering is done as a determined hand would do it, on the SQLite file itself: the
append-only triggers dropped first, rows updated, deleted and inserted, hashes computed
again where that hides more. ``gateway records verify`` must name the first record
touched, and exit 1.
"""

from __future__ import annotations

import itertools
import json
import sqlite3
from datetime import UTC, datetime, timedelta
from typing import TYPE_CHECKING

import pytest
from typer.testing import CliRunner

from gateway.cli.root import app
from gateway.errors import RecordError
from gateway.records import Actor, Entry, Head, Kind, RecordStore, Result, Via, records_path
from gateway.records.chain import GENESIS, Row, canonical, link, verify

if TYPE_CHECKING:
    from pathlib import Path

OPERATOR = Actor(user="alice", via=Via.CLI, reason="weekly check")
START = datetime(2026, 12, 2, 8, 0, tzinfo=UTC)


def filled(state_dir: Path, count: int = 6) -> RecordStore:
    """A store of ``count`` records, one a minute."""
    moments = iter(START + timedelta(minutes=i) for i in range(1000))
    store = RecordStore(
        records_path(state_dir), clock_synchronised=lambda: True, now=lambda: next(moments)
    )
    for number in range(1, count + 1):
        store.append(
            Entry(kind=Kind.RELOAD, actor=OPERATOR, action=f"act {number}", result=Result.DONE)
        )
    return store


def tamper(state_dir: Path, *statements: str | tuple[str, tuple[object, ...]]) -> None:
    """Run SQL on the store's file with the guard triggers dropped."""
    db = sqlite3.connect(records_path(state_dir), isolation_level=None)
    try:
        db.execute("DROP TRIGGER records_never_updated")
        db.execute("DROP TRIGGER records_never_deleted")
        for statement in statements:
            if isinstance(statement, tuple):
                db.execute(*statement)
            else:
                db.execute(statement)
    finally:
        db.close()


def verify_cli(state_dir: Path, *extra: str) -> tuple[int, str]:
    result = CliRunner().invoke(app, ["records", "verify", "--state-dir", str(state_dir), *extra])
    return result.exit_code, result.output


def test_an_intact_chain_numbered_from_1_without_gaps(tmp_path: Path) -> None:
    store = filled(tmp_path)
    verdict = store.verify()
    assert verdict.intact
    assert verdict.checked == 6
    assert store.head.seq == 6
    assert [record.seq for record in store.records()] == [1, 2, 3, 4, 5, 6]
    rows = list(store.rows())
    assert rows[0].previous == GENESIS
    for before, after in itertools.pairwise(rows):
        assert after.previous == before.hash
        assert after.hash == link(before.hash, after.body)
    # The content is the canonical JSON of the body, with its number and time inside.
    body = json.loads(rows[2].body)
    assert canonical(body) == rows[2].body
    assert body["seq"] == 3
    assert body["time"] == "2026-12-02T08:02:00.000+00:00"
    assert body["actor"] == {
        "user": "alice",
        "via": "cli",
        "detail": "",
        "reason": "weekly check",
        "signed": False,
    }
    code, said = verify_cli(tmp_path)
    assert code == 0
    assert f"intact: 6 records, head 6:{store.head.hash}" in said


def test_the_store_refuses_an_update_and_a_delete(tmp_path: Path) -> None:
    filled(tmp_path, 2)
    db = sqlite3.connect(records_path(tmp_path), isolation_level=None)
    with pytest.raises(sqlite3.IntegrityError, match="append-only"):
        db.execute("UPDATE records SET body = '{}' WHERE seq = 1")
    with pytest.raises(sqlite3.IntegrityError, match="append-only"):
        db.execute("DELETE FROM records WHERE seq = 2")
    db.close()
    assert RecordStore(records_path(tmp_path)).verify().intact


def test_a_byte_changed_is_named(tmp_path: Path) -> None:
    store = filled(tmp_path)
    body = store.get(4).body  # type: ignore[union-attr]
    text = canonical(body).replace('"act 4"', '"act 5"')  # one character
    tamper(tmp_path, ("UPDATE records SET body = ? WHERE seq = 4", (text,)))
    verdict = RecordStore(records_path(tmp_path), read_only=True).verify()
    assert (verdict.broken_at, verdict.checked) == (4, 3)
    assert "record 4 was changed" in verdict.problem
    code, said = verify_cli(tmp_path)
    assert code == 1
    assert "BROKEN at record 4: record 4 was changed" in said


def test_a_byte_changed_with_its_hash_computed_again_is_named(tmp_path: Path) -> None:
    store = filled(tmp_path)
    rows = list(store.rows())
    text = rows[3].body.replace('"act 4"', '"act 9"')
    tamper(
        tmp_path,
        ("UPDATE records SET body = ?, hash = ? WHERE seq = 4", (text, link(rows[2].hash, text))),
    )
    verdict = RecordStore(records_path(tmp_path)).verify()
    assert verdict.broken_at == 4
    assert "record 4 was changed or replaced" in verdict.problem


def test_a_record_removed_is_named(tmp_path: Path) -> None:
    filled(tmp_path)
    tamper(tmp_path, "DELETE FROM records WHERE seq = 3")
    verdict = RecordStore(records_path(tmp_path)).verify()
    assert (verdict.broken_at, verdict.problem) == (3, "record 3 was removed")
    code, said = verify_cli(tmp_path)
    assert code == 1
    assert "record 3 was removed" in said


def test_a_record_removed_and_the_rest_renumbered_is_named(tmp_path: Path) -> None:
    filled(tmp_path)
    tamper(
        tmp_path,
        "DELETE FROM records WHERE seq = 3",
        *(("UPDATE records SET seq = ? WHERE seq = ?", (n - 1, n)) for n in range(4, 7)),
    )
    verdict = RecordStore(records_path(tmp_path)).verify()
    assert verdict.broken_at == 3
    assert verdict.problem.startswith("record 3 was removed: record 4 is now number 3")


def test_a_record_inserted_is_named(tmp_path: Path) -> None:
    """A forged record 3 linked properly to record 2; the old 3 to 6 moved up by one."""
    store = filled(tmp_path)
    rows = list(store.rows())
    forged = json.loads(rows[2].body) | {"action": "a write that never was"}
    text = canonical(forged)
    tamper(
        tmp_path,
        *(("UPDATE records SET seq = ? WHERE seq = ?", (n + 1, n)) for n in range(6, 2, -1)),
        (
            (
                "INSERT INTO records (seq, time, kind, device, body, previous, hash) "
                "VALUES (3, ?, 'reload', NULL, ?, ?, ?)"
            ),
            (forged["time"], text, rows[1].hash, link(rows[1].hash, text)),
        ),
    )
    verdict = RecordStore(records_path(tmp_path)).verify()
    assert verdict.broken_at == 3
    assert verdict.problem.startswith("record 3 was inserted")
    code, said = verify_cli(tmp_path)
    assert code == 1
    assert "BROKEN at record 3: record 3 was inserted" in said


def test_the_newest_records_cut_off_are_named_by_a_head_kept_elsewhere(tmp_path: Path) -> None:
    store = filled(tmp_path)
    kept = store.head  # as {base}/records/head published it
    tamper(tmp_path, "DELETE FROM records WHERE seq >= 5")
    assert RecordStore(records_path(tmp_path)).verify().intact  # the store alone cannot see it
    verdict = RecordStore(records_path(tmp_path)).verify(kept)
    assert verdict.broken_at == 5
    assert "records after 4 were removed" in verdict.problem
    code, said = verify_cli(tmp_path, "--head", str(kept))
    assert code == 1
    assert "BROKEN at record 5" in said


def test_a_chain_rebuilt_from_a_change_is_named_by_a_head_kept_elsewhere(tmp_path: Path) -> None:
    store = filled(tmp_path)
    kept = store.head
    rows = list(store.rows())
    previous = rows[1].hash
    statements: list[str | tuple[str, tuple[object, ...]]] = []
    for row in rows[2:]:  # record 3 changed, every hash after it computed again
        text = row.body.replace('"act 3"', '"act 0"')
        digest = link(previous, text)
        statements.append(
            (
                "UPDATE records SET body = ?, previous = ?, hash = ? WHERE seq = ?",
                (text, previous, digest, row.seq),
            )
        )
        previous = digest
    tamper(tmp_path, *statements)
    assert RecordStore(records_path(tmp_path)).verify().intact
    verdict = RecordStore(records_path(tmp_path)).verify(kept)
    assert verdict.broken_at == 6
    assert "rewritten" in verdict.problem


def test_the_first_record_must_start_the_chain() -> None:
    text = canonical({"seq": 1})
    verdict = verify([Row(1, text, "f" * 64, link("f" * 64, text))])
    assert verdict.broken_at == 1
    assert "does not start a chain" in verdict.problem


def test_a_head_is_seq_and_64_hex_digits() -> None:
    head = Head.parse(f"12:{'A' * 64}")
    assert (head.seq, head.hash) == (12, "a" * 64)
    for wrong in ("12", "x:" + "a" * 64, "3:abc"):
        with pytest.raises(ValueError, match="SEQ:HASH"):
            Head.parse(wrong)


def test_no_store_is_a_clear_error(tmp_path: Path) -> None:
    with pytest.raises(RecordError, match="there are no records at"):
        RecordStore(records_path(tmp_path / "nowhere"), read_only=True)
    code, said = verify_cli(tmp_path / "nowhere")
    assert code == 2
    assert "there are no records" in said


def test_a_correction_is_a_new_record_pointing_to_the_old_which_stays(tmp_path: Path) -> None:
    store = filled(tmp_path, 3)
    before = store.get(2)
    result = CliRunner().invoke(
        app,
        ["records", "correct", "2", "--state-dir", str(tmp_path), "--reason", "wrong basin"],
    )
    assert result.exit_code == 0, result.output
    assert "record 4 corrects record 2" in result.output
    again = RecordStore(records_path(tmp_path))
    correction = again.get(4)
    assert correction is not None
    assert correction.body["kind"] == "correction"
    assert correction.body["corrects"] == 2
    assert correction.body["note"] == "wrong basin"
    assert correction.body["actor"]["via"] == "cli"
    assert again.get(2) == before  # untouched
    assert again.verify().intact
    missing = CliRunner().invoke(
        app, ["records", "correct", "9", "--state-dir", str(tmp_path), "--reason", "x"]
    )
    assert missing.exit_code == 2
    assert "there is no record 9 (the newest is 4)" in missing.output


def test_records_another_process_appended_reach_the_listeners_in_order(tmp_path: Path) -> None:
    gateway_store = filled(tmp_path, 2)
    told: list[int] = []
    gateway_store.listen(lambda record: told.append(record.seq))
    command_line = RecordStore(records_path(tmp_path))
    entry = Entry(kind=Kind.CORRECTION, actor=OPERATOR, action="fix", result=Result.NOTED)
    command_line.append(entry)
    command_line.append(entry)
    assert [r.seq for r in gateway_store.catch_up()] == [3, 4]
    assert gateway_store.head == command_line.head
    command_line.append(entry)
    gateway_store.append(entry)  # its own append tells record 5 first, then 6
    assert told == [3, 4, 5, 6]
    assert gateway_store.catch_up() == []
