"""The ``gateway`` command line: one entry point with sub-commands."""

from __future__ import annotations

import asyncio
import importlib
import json
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Final

import typer
from rich.console import Console
from rich.markup import escape
from typer.core import TyperGroup

from gateway import __version__
from gateway.cli.device import fail
from gateway.cli.run import run_command
from gateway.config import review_config
from gateway.control.link import open_link
from gateway.control.ports import port_advice
from gateway.errors import ConfigError, GatewayError
from gateway.line.engine.devices import DeviceTarget
from gateway.line.samples import Quality, Sample, hex_registers, json_value
from gateway.line.transports.port_names import SystemRoots
from gateway.profiles import Point, PollGroup, builtin_profiles, get_profile
from gateway.publish.console import format_sample
from gateway.wire import codec
from gateway.wire.timing import LineFormat

if TYPE_CHECKING:
    from typer import _click


# What only one command needs (tables, progress bars, the simulator, the bus scan) is
# imported in that command, so that `gateway run` does not hold it in memory for as long
# as the gateway runs. The commands of a module of their own are imported only when one
# of them is run or listed (tests/cli/test_imports.py checks what `gateway run` imports).
LAZY_COMMANDS: Final = {
    "simulate": "gateway.cli.simulate",
    "scan": "gateway.cli.scan",
    "demo": "gateway.cli.demo_command",
    "write": "gateway.cli.write",
    "calibrate": "gateway.cli.calibrate",
    "set-clock": "gateway.cli.operations",
    "measure": "gateway.cli.operations",
    "calibration-log": "gateway.cli.operations",
    "care": "gateway.cli.care",
    "reload": "gateway.cli.reload",
    "users": "gateway.cli.users",
    "records": "gateway.cli.records",
    "verify": "gateway.cli.verify",
}


class LazyCommands(TyperGroup):
    """The ``gateway`` group: the commands of ``LAZY_COMMANDS`` built when asked for.

    Each such module has ``register(app)``, which adds its commands to a Typer app; it
    is imported, and its commands built, the first time one of them is looked up: to run
    it, or to list it in ``gateway --help``.
    """

    def list_commands(self, ctx: _click.Context) -> list[str]:
        """The commands of this module, then the others, in the order they were written."""
        return [*super().list_commands(ctx), *LAZY_COMMANDS]

    def get_command(self, ctx: _click.Context, cmd_name: str) -> _click.Command | None:
        """The command ``cmd_name``, its module imported if it has one of its own."""
        command = super().get_command(ctx, cmd_name)
        if command is not None or cmd_name not in LAZY_COMMANDS:
            return command
        holder = typer.Typer()
        importlib.import_module(LAZY_COMMANDS[cmd_name]).register(holder)
        command = typer.main.get_group(holder).get_command(ctx, cmd_name)
        if command is not None:
            self.add_command(command, cmd_name)
        return command


app = typer.Typer(
    cls=LazyCommands,
    name="gateway",
    help="Polling gateway for RS485 water-quality sensors (Modbus RTU to MQTT and Prometheus).",
    no_args_is_help=True,
    pretty_exceptions_enable=False,
)
profiles_app = typer.Typer(help="List the sensor profiles and show their register maps.")
app.add_typer(profiles_app, name="profiles")

_out = Console(highlight=False, soft_wrap=True)
_err = Console(stderr=True, highlight=False)


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
        raise fail(exc) from exc
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
    from rich.table import Table  # noqa: PLC0415

    table = Table(title="Sensor profiles")
    # Whole ids on any width (an id is what users copy): the other columns fold instead.
    table.add_column("id", no_wrap=True, min_width=max(len(p) for p in profiles))
    for column in ("family", "variant", "points", "manual"):
        table.add_column(column, overflow="fold")
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
        raise fail(exc) from exc
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
    from rich.table import Table  # noqa: PLC0415

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
            escape(_range_text(point)),
            escape(point.description),
        )
    _out.print(table)


def _read_targets(profile_id: str, points: list[str], *, every: bool) -> dict[str, float | None]:
    profile = get_profile(profile_id)
    if points:
        return {profile.point(name).name: None for name in points}
    groups = set(PollGroup) if every else {PollGroup.PROCESS, PollGroup.STATUS, PollGroup.IDENTITY}
    return {p.name: None for p in profile.points if p.group in groups and not p.view}


async def _read(port: str, line_format: LineFormat, target: DeviceTarget) -> list[Sample]:
    async with open_link(port, line_format, target) as link:
        return await link.worker.read_once(target.name)


@app.command()
def read(
    port: Annotated[
        str, typer.Option(help="Serial device, socket://HOST:PORT (RTU) or tcp://HOST:PORT (MBAP).")
    ],
    address: Annotated[int, typer.Option(help="Device address 1..247.", min=1, max=247)],
    profile: Annotated[str, typer.Option(help="Profile id, see 'gateway profiles'.")],
    points: Annotated[
        list[str] | None,
        typer.Argument(
            metavar="[POINT]...", help="Points to read (default: process, status, identity)."
        ),
    ] = None,
    baudrate: Annotated[int, typer.Option(help="Line speed.")] = 9600,
    parity: Annotated[str, typer.Option(help="N, E or O.")] = "N",
    stopbits: Annotated[int, typer.Option(help="1 or 2.")] = 1,
    timeout: Annotated[
        float | None, typer.Option(help="Response timeout in seconds (default: from the profile).")
    ] = None,
    float_order: Annotated[
        str | None, typer.Option(help="ABCD, CDAB, BADC or DCBA (default: the device's).")
    ] = None,
    every: Annotated[bool, typer.Option("--all", help="Read every point of the profile.")] = False,
    as_json: Annotated[
        bool, typer.Option("--json", help="Print a JSON object keyed by point name.")
    ] = False,
) -> None:
    """Read points of one device once, with every timing rule of its manual."""
    try:
        if parity not in {"N", "E", "O"} or stopbits not in {1, 2}:
            raise ConfigError("--parity must be N, E or O and --stopbits 1 or 2")
        order = codec.WordOrder(float_order) if float_order else None
        target = DeviceTarget(
            name=f"address_{address}",
            address=address,
            profile=get_profile(profile),
            intervals=_read_targets(profile, points or [], every=every),
            float_order=order,
            timeout_s=timeout,
        )
        line_format = LineFormat(baudrate=baudrate, parity=parity, stopbits=stopbits)  # type: ignore[arg-type]
        samples = asyncio.run(_read(port, line_format, target))
    except ValueError as exc:
        raise fail(
            ConfigError(f"--float-order {float_order!r}: expected ABCD, CDAB, BADC or DCBA")
        ) from exc
    except GatewayError as exc:
        raise fail(exc) from exc
    # Only a failed read fails the command: a fault the sensor sent (2.0e37, or registers
    # that are not a value) is an answer, and the line worked.
    failed = [s for s in samples if s.quality is Quality.COMMS_ERROR]
    if as_json:
        data = {
            s.point: ({"value": json_value(s.value)} if s.good else {s.quality.value: s.fault})
            | ({"raw": hex_registers(s.raw)} if s.raw else {})
            | {"unit": s.unit}
            for s in samples
        }
        sys.stdout.write(json.dumps(data, indent=2, ensure_ascii=False) + "\n")
    else:
        from rich.table import Table  # noqa: PLC0415

        table = Table(title=escape(f"{profile} at address {address} on {port}"))
        for column in ("point", "value", "unit", "quality"):
            table.add_column(column, overflow="fold")
        for s in samples:
            shown = format_sample(s).split("=", 1)[1]
            value = shown.removesuffix(f" {s.unit}") if s.unit else shown
            table.add_row(s.point, escape(value), escape(s.unit or ""), s.quality.value)
        _out.print(table)
    if failed:
        _err.print(f"[bold red]error:[/] {len(failed)} of {len(samples)} points could not be read")
        raise typer.Exit(code=1)


@app.command("check-config")
def check_config_command(
    config: Annotated[Path, typer.Argument(metavar="FILE", help="The gateway's YAML config.")],
    dev_root: Annotated[
        Path, typer.Option(hidden=True, help="Where /dev is (tests run on a fake tree).")
    ] = Path("/dev"),
) -> None:
    """Check a config and report every problem at once, with its key path and line.

    Warnings (a port named ``/dev/ttyUSB0`` rather than its ``/dev/serial/by-id`` name)
    are printed too; only problems make the exit status non-zero.
    """
    roots = SystemRoots(dev=dev_root)
    problems, warnings = review_config(config, advise=lambda c: port_advice(c, roots))
    for warning in warnings:
        _err.print(f"{config}: warning: {warning}", markup=False)
    if not problems:
        _out.print(f"{config}: OK" + (f" ({len(warnings)} warnings)" if warnings else ""))
        return
    for problem in problems:
        _err.print(f"{config}: {problem}", markup=False)
    _err.print(f"[bold red]{len(problems)} problem{'s' if len(problems) > 1 else ''}[/]")
    raise typer.Exit(code=2)


@app.command()
def run(
    config: Annotated[Path, typer.Option("--config", "-c", help="The gateway's YAML config.")],
    show: Annotated[
        bool | None,
        typer.Option("--print/--no-print", help="Print each poll cycle (default: on a terminal)."),
    ] = None,
) -> None:
    """Poll every configured bus and publish to MQTT and Prometheus until Ctrl-C or SIGTERM.

    SIGHUP (or ``gateway reload``) reads the config again and applies what changed.
    """
    # The same body as a plain run's without typer (cli/run): only reading differs.
    try:
        run_command(config, show=show)
    except GatewayError as exc:
        raise fail(exc) from exc


def main() -> None:
    """Any command line, through typer (``gateway.cli.main`` reads a plain run itself)."""
    app()
