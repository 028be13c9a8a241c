"""``gateway records verify|export|correct``: the store checked, copied, and corrected.

Both read the store in the config's state directory (``--config``, or ``--state-dir``),
opened to read only, so they run beside a running gateway. ``verify`` exits 0 when the
chain is intact and 1 naming the first record changed, removed or inserted; ``--head
SEQ:HASH`` also checks a head kept elsewhere (the retained ``{base}/records/head``).
``correct`` adds a record that points to the one it corrects (nothing is ever edited or
deleted); beside a running gateway, which publishes it at its next look.
"""

from __future__ import annotations

import json
import sys
from datetime import UTC, datetime
from pathlib import Path
from typing import Annotated, Final

import typer

from gateway.app import state_directory
from gateway.cli.device import err, fail, out
from gateway.config import load_config
from gateway.errors import ConfigError, GatewayError, RecordError
from gateway.records import DeviceRef, Entry, Head, Kind, Query, RecordStore, Result, records_path
from gateway.records.actor import command_line_actor
from gateway.records.export import FORMATS, export

records_app = typer.Typer(help="The records of every change to a sensor: verify, export, correct.")

DEFAULT_CONFIG: Final = Path("/etc/rs485-gateway/gateway.yaml")  # deploy/systemd's

ConfigOption = Annotated[
    Path | None,
    typer.Option("--config", "-c", help="The gateway's YAML config (its state_dir)."),
]
StateDirOption = Annotated[
    Path | None,
    typer.Option("--state-dir", help="The state directory itself (instead of --config)."),
]


def _store(config: Path | None, state_dir: Path | None) -> RecordStore:
    if state_dir is None:
        settings = load_config(config if config is not None else DEFAULT_CONFIG)
        state_dir = state_directory(settings)
    return RecordStore(records_path(state_dir), read_only=True)


def _time(text: str | None, option: str) -> datetime | None:
    if text is None:
        return None
    try:
        moment = datetime.fromisoformat(text)
    except ValueError as exc:
        raise ConfigError(f"{text!r} is not an ISO 8601 date or time", key=option) from exc
    return moment if moment.tzinfo is not None else moment.replace(tzinfo=UTC)


@records_app.command("verify")
def verify(
    config: ConfigOption = None,
    state_dir: StateDirOption = None,
    head: Annotated[
        str | None,
        typer.Option(
            "--head", help="A head kept elsewhere, SEQ:HASH: the store must still hold it."
        ),
    ] = None,
    as_json: Annotated[bool, typer.Option("--json", help="Print the verdict as JSON.")] = False,
) -> None:
    """Check the hash chain; exit 1 naming the first record changed, removed or inserted."""
    try:
        expected = Head.parse(head) if head is not None else None
    except ValueError as exc:
        raise fail(ConfigError(str(exc), key="--head")) from exc
    try:
        store = _store(config, state_dir)
        try:
            verdict = store.verify(expected)
        finally:
            store.close()
    except GatewayError as exc:
        raise fail(exc) from exc
    if as_json:
        sys.stdout.write(json.dumps(verdict.as_dict()) + "\n")
    elif verdict.intact:
        out.print(
            f"intact: {verdict.checked} records, head {verdict.head.seq}:{verdict.head.hash}",
            markup=False,
        )
    else:
        err.print(f"BROKEN at record {verdict.broken_at}: {verdict.problem}", markup=False)
        if verdict.checked:
            err.print(
                f"records 1 to {verdict.head.seq} are intact "
                f"(head {verdict.head.seq}:{verdict.head.hash})",
                markup=False,
            )
    raise typer.Exit(code=0 if verdict.intact else 1)


@records_app.command("export")
def export_records(
    config: ConfigOption = None,
    state_dir: StateDirOption = None,
    fmt: Annotated[str, typer.Option("--format", help=f"One of {', '.join(FORMATS)}.")] = "csv",
    device: Annotated[str | None, typer.Option(help="Only this device's records.")] = None,
    kind: Annotated[
        list[str] | None, typer.Option(help="Only records of this kind (repeat for several).")
    ] = None,
    since: Annotated[str | None, typer.Option(help="From this UTC time (ISO 8601).")] = None,
    until: Annotated[str | None, typer.Option(help="Up to this UTC time (ISO 8601).")] = None,
    output: Annotated[
        Path | None, typer.Option("--output", "-o", help="Write to this file, not stdout.")
    ] = None,
) -> None:
    """Every field of the records chosen, the hashes, and the whole chain's verdict at the end."""
    if fmt not in FORMATS:
        raise fail(ConfigError(f"{fmt!r} is not one of {', '.join(FORMATS)}", key="--format"))
    try:
        query = Query(
            device=device,
            kinds=tuple(kind or ()),
            since=_time(since, "--since"),
            until=_time(until, "--until"),
        )
        store = _store(config, state_dir)
        try:
            chosen = list(store.records(query))
            verdict = store.verify()
        finally:
            store.close()
    except GatewayError as exc:
        raise fail(exc) from exc
    text = export(chosen, verdict, fmt)
    if output is None:
        sys.stdout.write(text)
    else:
        try:
            output.write_text(text, encoding="utf-8")
        except OSError as exc:
            raise fail(RecordError(f"cannot write {output}: {exc}")) from exc
        err.print(f"{len(chosen)} records written to {output}", markup=False)
    if not verdict.intact:
        err.print(f"the chain is BROKEN at record {verdict.broken_at}: {verdict.problem}")
        raise typer.Exit(code=1)


@records_app.command("correct")
def correct(
    seq: Annotated[int, typer.Argument(help="The number of the record to correct.")],
    reason: Annotated[str, typer.Option(help="What was wrong, and what is right (required).")],
    config: ConfigOption = None,
    state_dir: StateDirOption = None,
) -> None:
    """Add a correction of a record: a new record that points to it; the old one stays."""
    if not reason.strip():
        raise fail(ConfigError("say what is corrected", key="--reason"))
    try:
        if state_dir is None:
            state_dir = state_directory(
                load_config(config if config is not None else DEFAULT_CONFIG)
            )
        store = RecordStore(records_path(state_dir))
        try:
            corrected = store.get(seq)
            if corrected is None:
                raise RecordError(f"there is no record {seq} (the newest is {store.head.seq})")
            device = corrected.body.get("device")
            record = store.append(
                Entry(
                    kind=Kind.CORRECTION,
                    actor=command_line_actor(reason),
                    device=DeviceRef.from_dict(device) if isinstance(device, dict) else None,
                    action=f"correction of record {seq} ({corrected.kind})",
                    result=Result.NOTED,
                    note=reason.strip(),
                    corrects=seq,
                )
            )
        finally:
            store.close()
    except GatewayError as exc:
        raise fail(exc) from exc
    out.print(f"record {record.seq} corrects record {seq}; head {store.head}", markup=False)


def register(app: typer.Typer) -> None:
    """Add ``gateway records`` to the command line."""
    app.add_typer(records_app, name="records")
