"""``gateway scan``: find the sensors on a line, with a config snippet for what answered.

Loaded only when the command is run or listed (``cli/root``'s ``LAZY_COMMANDS``): the bus
scan, its progress bar and its table are no part of a running gateway.
"""

from __future__ import annotations

import asyncio
import json
import sys
from typing import TYPE_CHECKING, Annotated

import typer
from rich.markup import escape
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)
from rich.table import Table

from gateway.cli.device import err, fail, out
from gateway.errors import GatewayError
from gateway.line.scan import parse_addresses, scan_formats
from gateway.line.scan import scan as scan_bus

if TYPE_CHECKING:
    from gateway.wire.timing import LineFormat


def scan_command(
    port: Annotated[
        str, typer.Option(help="Serial device, socket://HOST:PORT (RTU) or tcp://HOST:PORT (MBAP).")
    ],
    baudrate: Annotated[int, typer.Option(help="Line speed.")] = 9600,
    parity: Annotated[str, typer.Option(help="N, E or O.")] = "N",
    stopbits: Annotated[int, typer.Option(help="1 or 2.")] = 1,
    addresses: Annotated[
        str, typer.Option(help="Addresses to probe: 1-247, 7, or a list such as 1-10,20.")
    ] = "1-247",
    all_formats: Annotated[
        bool,
        typer.Option(
            "--all-formats",
            help="Also try every baud rate and character format the sensor families support.",
        ),
    ] = False,
    timeout: Annotated[
        float | None,
        typer.Option(
            help="Seconds to wait for a probe's answer (default: its wire time + 40 ms); "
            "raise it for sensors with a digiLine minimum response time."
        ),
    ] = None,
    as_json: Annotated[
        bool, typer.Option("--json", help="Print {devices, config} as JSON, no progress bar.")
    ] = False,
) -> None:
    """Find the sensors on a line and print them with a config snippet; exit 1 if none."""
    try:
        formats = scan_formats(
            baudrate=baudrate, parity=parity, stopbits=stopbits, every=all_formats
        )
        wanted = parse_addresses(addresses)
        with Progress(
            TextColumn("{task.description}"),
            BarColumn(),
            MofNCompleteColumn(),
            TextColumn("found {task.fields[found]}"),
            TimeElapsedColumn(),
            TextColumn("left"),
            TimeRemainingColumn(),
            console=err,
            transient=True,
            disable=as_json or not err.is_terminal,
        ) as progress:
            task = progress.add_task("scanning", total=len(formats) * len(wanted), found=0)

            def advance(fmt: LineFormat, address: int, found: int) -> None:
                progress.update(task, advance=1, description=f"{fmt} #{address}", found=found)

            report = asyncio.run(
                scan_bus(
                    port, formats=formats, addresses=wanted, timeout_s=timeout, progress=advance
                )
            )
    except GatewayError as exc:
        raise fail(exc) from exc
    if as_json:
        sys.stdout.write(json.dumps(report.as_dict(), indent=2, ensure_ascii=False) + "\n")
    elif report.devices:
        table = Table(title=escape(f"Devices on {port}"), show_lines=True)
        for column in ("address", "format", "profile"):
            table.add_column(column, no_wrap=True)
        table.add_column("identification", overflow="fold", ratio=1)
        table.add_column("notes", overflow="fold", ratio=1)
        for device in report.devices:
            profile = device.profile or "-"
            table.add_row(
                str(device.address),
                str(device.line),
                f"{profile} (guess)" if device.guess else profile,
                escape(device.details_text(sep="\n")),
                escape("; ".join(device.notes)),
            )
        out.print(table)
        sys.stdout.write("\n" + report.config_yaml())
    err.print(
        f"{len(report.devices)} device(s); {len(wanted)} address(es) x {len(formats)} "
        f"format(s) in {report.elapsed_s:.1f} s, {report.requests} requests",
        markup=False,
    )
    if report.garbled:
        where = ", ".join(f"{address} at {fmt}" for fmt, address in report.garbled)
        err.print(
            f"broken answers from {where}: another line format? try --all-formats", markup=False
        )
    if not report.devices:
        err.print(f"[bold red]no device answered[/] on {escape(port)}", highlight=False)
        raise typer.Exit(code=1)


def register(app: typer.Typer) -> None:
    """Add ``scan`` to the ``gateway`` command line."""
    app.command("scan")(scan_command)
