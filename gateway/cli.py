"""The ``gateway`` command line: one entry point with sub-commands."""

from __future__ import annotations

import json
import sys
from typing import Annotated

import typer
from rich.console import Console
from rich.table import Table

from gateway import __version__
from gateway.errors import GatewayError
from gateway.profiles import Point, builtin_profiles, get_profile

app = typer.Typer(
    name="gateway",
    help="Polling gateway for RS485 water-quality sensors (Modbus RTU to MQTT and Prometheus).",
    no_args_is_help=True,
    pretty_exceptions_enable=False,
)
profiles_app = typer.Typer(help="List the sensor profiles and show their register maps.")
app.add_typer(profiles_app, name="profiles")

_out = Console(highlight=False, soft_wrap=True)
_err = Console(stderr=True, highlight=False)


def _fail(exc: GatewayError) -> typer.Exit:
    _err.print(f"[bold red]error:[/] {exc}")
    return typer.Exit(code=2)


@app.callback(invoke_without_command=True)
def _root(
    version: Annotated[
        bool, typer.Option("--version", help="Print the version and exit.", is_eager=True)
    ] = False,
) -> None:
    if version:
        _out.print(__version__)
        raise typer.Exit


@profiles_app.callback(invoke_without_command=True)
def profiles_list(
    ctx: typer.Context,
    as_json: Annotated[bool, typer.Option("--json", help="Print JSON instead of a table.")] = False,
) -> None:
    """List every profile id with its family and variant."""
    if ctx.invoked_subcommand is not None:
        return
    try:
        profiles = builtin_profiles()
    except GatewayError as exc:
        raise _fail(exc) from exc
    if as_json:
        rows = [
            {
                "id": p.id,
                "family": p.family,
                "title": p.title,
                "points": len(p.points),
                "spec": p.spec,
            }
            for p in sorted(profiles.values(), key=lambda p: p.id)
        ]
        sys.stdout.write(json.dumps(rows, indent=2, ensure_ascii=False) + "\n")
        return
    table = Table(title="Sensor profiles")
    for column in ("id", "family", "variant", "points", "manual"):
        table.add_column(column)
    for p in sorted(profiles.values(), key=lambda p: p.id):
        table.add_row(p.id, p.family, p.title, str(len(p.points)), p.spec)
    _out.print(table)


def _range_text(point: Point) -> str:
    fmt = point.format
    if fmt.minimum is None and fmt.maximum is None:
        return ""
    return f"{fmt.minimum:g} .. {fmt.maximum:g}"


@profiles_app.command("show")
def profiles_show(
    profile_id: Annotated[
        str, typer.Argument(metavar="ID", help="Profile id, see 'gateway profiles'.")
    ],
    as_json: Annotated[
        bool, typer.Option("--json", help="Print the points as a JSON list.")
    ] = False,
) -> None:
    """Print a profile's register map as a table, or its points as JSON."""
    try:
        profile = get_profile(profile_id)
    except GatewayError as exc:
        raise _fail(exc) from exc
    if as_json:
        points = [point.as_dict() for point in profile.points]
        sys.stdout.write(json.dumps(points, indent=2, ensure_ascii=False) + "\n")
        return
    timing = profile.timing
    _out.print(f"[bold]{profile.title}[/] ({profile.id}), manual {profile.spec}")
    _out.print(
        f"floats {profile.float_order.value}"
        + (" with fault values 1e37..9e37" if profile.float_faults else "")
        + f"; inter-frame gap >= {timing.min_gap_s * 1000:g} ms and 3.5 characters"
        + f"; device processing <= {timing.processing_time_s * 1000:g} ms"
        + f"; post-write wait {timing.post_write_wait_s * 1000:g} ms"
        + "".join(
            f", {r.wait_s * 1000:g} ms after 0x{r.first:04X}..0x{r.last:04X}"
            for r in timing.post_write_waits
        )
    )
    if profile.serial is not None:
        s = profile.serial
        _out.print(
            f"factory serial settings: address {s.address}, {s.baudrate} baud, "
            f"{s.parity or '?'}{s.stopbits or '?'}"
        )
    table = Table(show_lines=False)
    for column in (
        "address",
        "name",
        "type",
        "regs",
        "access",
        "unit",
        "group",
        "storage",
        "range",
        "meaning",
    ):
        table.add_column(column, overflow="fold")
    for point in profile.points:
        unit = point.unit if point.unit is not None else f"from {point.unit_from}"
        table.add_row(
            f"0x{point.address:04X}",
            point.name,
            point.dtype.value,
            str(point.count),
            point.access.value,
            unit,
            point.group.value,
            point.storage.value if point.storage else "",
            _range_text(point),
            point.description,
        )
    _out.print(table)


def main() -> None:
    """Run the command line."""
    app()
