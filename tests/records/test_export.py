"""Readable copies: CSV, JSON and the printable HTML, each with every field and the verdict."""

from __future__ import annotations

import csv
import io
import json
import re
import sqlite3
from typing import TYPE_CHECKING

from typer.testing import CliRunner

from gateway.cli.root import app
from gateway.records import (
    Actor,
    DeviceRef,
    Entry,
    Kind,
    PointChange,
    RecordStore,
    Result,
    Via,
    records_path,
)
from gateway.records.export import CSV_COLUMNS

if TYPE_CHECKING:
    from pathlib import Path

ALICE = Actor(user="alice", via=Via.PAGE, detail="192.0.2.7", reason="new cap", signed=True)
BASIN = DeviceRef(name="basin", profile="reiss-m0c", bus="line1", address=10, serial="R-77")


def fill(state_dir: Path) -> RecordStore:
    store = RecordStore(records_path(state_dir), clock_synchronised=lambda: True)
    store.append(
        Entry(
            kind=Kind.WRITE,
            actor=ALICE,
            device=BASIN,
            action="write x_span",
            result=Result.PENDING,
            points=(
                PointChange(
                    point="x_span", unit="nA", as_found=54.2, sent=55.0, registers=(0, 0x425C)
                ),
            ),
        )
    )
    store.append(
        Entry(
            kind=Kind.OUTCOME,
            actor=ALICE,
            device=BASIN,
            action="write x_span",
            result=Result.DONE,
            points=(PointChange(point="x_span", unit="nA", as_left=55.0),),
            completes=1,
        )
    )
    for day, span in enumerate((60.0, 57.5, 55.0, 52.0), start=1):
        store.append(
            Entry(
                kind=Kind.HISTORY,
                actor=Actor(user="gateway", via=Via.GATEWAY),
                device=BASIN,
                action="calibration history entry",
                result=Result.NOTED,
                data={
                    "entry": {"x_zero": 0.5, "x_span": span, "stamp": f"2026-11-0{day}T08:00:00"}
                },
            )
        )
    store.append(Entry(kind=Kind.RELOAD, actor=ALICE, action="reload", result=Result.DONE))
    return store


def export(state_dir: Path, *args: str) -> tuple[int, str]:
    result = CliRunner().invoke(app, ["records", "export", "--state-dir", str(state_dir), *args])
    return result.exit_code, result.output


def test_csv_has_every_field_and_ends_with_the_verdict(tmp_path: Path) -> None:
    store = fill(tmp_path)
    code, text = export(tmp_path, "--format", "csv")
    assert code == 0
    *table, verdict = text.rstrip("\n").split("\n")
    rows = list(csv.DictReader(io.StringIO("\n".join(table))))
    assert tuple(rows[0]) == CSV_COLUMNS
    assert len(rows) == 7
    write = rows[0]
    assert (write["seq"], write["user"], write["via"], write["signed"]) == (
        "1",
        "alice",
        "page",
        "true",
    )
    assert (write["device"], write["serial"], write["point"]) == ("basin", "R-77", "x_span")
    assert (write["as_found"], write["sent"], write["registers"]) == (
        "54.2",
        "55.0",
        "0x0000 0x425C",
    )
    assert write["hash"] == store.get(1).hash  # type: ignore[union-attr]
    assert rows[1]["as_left"] == "55.0"
    assert rows[1]["completes"] == "1"
    assert verdict == f"# chain intact: 7 records, head 7:{store.head.hash}"


def test_json_filters_by_device_and_kind_and_keeps_the_whole_chains_verdict(
    tmp_path: Path,
) -> None:
    fill(tmp_path)
    code, text = export(tmp_path, "--format", "json", "--device", "basin", "--kind", "write")
    assert code == 0
    document = json.loads(text)
    assert [r["seq"] for r in document["records"]] == [1]
    assert document["verdict"]["intact"] is True
    assert document["verdict"]["checked"] == 7  # the verdict is of the whole store


def test_html_is_a_printable_report_with_the_slopes_history(tmp_path: Path) -> None:
    fill(tmp_path)
    code, text = export(tmp_path, "--format", "html")
    assert code == 0
    assert text.startswith("<!doctype html>")
    assert '<section class="device"><h2>basin</h2>' in text
    assert "page-break-before: always" in text
    [plot] = re.findall(r"<svg class=\"plot\".*?</svg>", text)
    assert plot.count("<circle") == 4
    assert "4 calibrations" in plot
    assert ">2026-11-01<" in plot
    assert ">2026-11-04<" in plot
    assert "chain intact: 7 records" in text


def test_an_export_of_a_broken_chain_says_so_and_exits_1(tmp_path: Path) -> None:
    fill(tmp_path)
    db = sqlite3.connect(records_path(tmp_path), isolation_level=None)
    db.execute("DROP TRIGGER records_never_deleted")
    db.execute("DELETE FROM records WHERE seq = 2")
    db.close()
    code, text = export(tmp_path, "--format", "csv")
    assert code == 1
    assert "# chain BROKEN at record 2: record 2 was removed" in text
