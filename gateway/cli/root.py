"""The ``gateway`` command line: one entry point with sub-commands."""

from __future__ import annotations

import asyncio
import importlib
import json
import signal
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

    from gateway.simulator import SimulationSettings

# What only one command needs (tables, progress bars, the simulator, the bus scan) is
# imported in that command, so that `gateway run` does not hold it in memory for as long
# as the gateway runs. The commands of a module of their own are imported only when one
# of them is run or listed (tests/cli/test_imports.py checks what `gateway run` imports).
LAZY_COMMANDS: Final = {
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


def _simulation_settings(
    devices: list[str],
    config: Path | None,
    overrides: dict[str, object],
) -> SimulationSettings:
    from gateway.simulator import load_settings, parse_device_option, parse_settings  # noqa: PLC0415

    if config is not None:
        settings = load_settings(config)
        if devices:
            extra = [parse_device_option(text) for text in devices]
            settings = parse_settings(
                {
                    **settings.model_dump(),
                    "devices": [
                        *settings.model_dump()["devices"],
                        *[d.model_dump() for d in extra],
                    ],
                },
                source=str(config),
            )
    else:
        if not devices:
            raise ConfigError("give at least one --device PROFILE:ADDRESS or a --config file")
        settings = parse_settings(
            {"devices": [parse_device_option(t).model_dump() for t in devices]}
        )
    data = settings.model_dump()
    line = {
        k: v
        for k, v in overrides.items()
        if k in {"baudrate", "parity", "stopbits"} and v is not None
    }
    data["line"] = {**data["line"], **line}
    for key in ("pace", "seed"):
        if overrides.get(key) is not None:
            data[key] = overrides[key]
    if overrides.get("static"):
        for device in data["devices"]:
            device["animate"] = False
    return parse_settings(data, source=str(config or "command line"))


async def _simulate(
    settings: SimulationSettings,
    pty: Path | None,
    tcp: tuple[str, int] | None,
    stats: Path | None,
    *,
    framing: str = "rtu",
    converter_timeout_s: float = 0.05,
) -> None:
    from gateway.simulator import SimulatorServer, build_bus  # noqa: PLC0415

    bus = build_bus(settings)
    server = SimulatorServer(bus, stats_path=stats)
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for signum in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(signum, stop.set)
    try:
        where = []
        if pty is not None:
            slave = server.open_pty(pty)
            where.append(f"{pty} (-> {slave})")
        if tcp is not None:
            port = await server.open_tcp(
                *tcp, framing=framing, converter_timeout_s=converter_timeout_s
            )
            scheme = "tcp" if framing == "tcp" else "socket"
            where.append(f"{scheme}://{tcp[0]}:{port}")
        server.start_stats()
        devices = ", ".join(f"{d.profile.id}@{a}" for a, d in sorted(bus.devices.items()))
        _out.print(
            f"simulating {devices} on {' and '.join(where)}, {bus.line}; Ctrl-C stops",
            markup=False,
        )
        sys.stdout.flush()
        await stop.wait()
    finally:
        await server.close()


def _host_port(text: str) -> tuple[str, int]:
    host, sep, port = text.rpartition(":")
    if not sep or not port.isdigit() or not host:
        raise ConfigError(f"--tcp {text!r}: expected HOST:PORT, e.g. 127.0.0.1:5020")
    return host, int(port)


@app.command()
def simulate(
    device: Annotated[
        list[str] | None,
        typer.Option("--device", "-d", help="PROFILE:ADDRESS of a simulated sensor; repeatable."),
    ] = None,
    config: Annotated[
        Path | None,
        typer.Option("--config", "-c", help="YAML file with line, devices, values, faults."),
    ] = None,
    pty: Annotated[
        Path | None,
        typer.Option("--pty", help="Create a pseudo-terminal and link it at this path."),
    ] = None,
    tcp: Annotated[
        str | None, typer.Option("--tcp", help="Serve RTU over TCP on HOST:PORT (port 0: any).")
    ] = None,
    framing: Annotated[
        str,
        typer.Option(
            help="On --tcp: rtu (RTU over TCP, a transparent converter) or tcp (Modbus TCP: "
            "MBAP frames, unit id = address, 0B for a device that does not answer)."
        ),
    ] = "rtu",
    converter_timeout: Annotated[
        float,
        typer.Option(
            help="With --framing tcp: seconds the converter waits for an answer after its "
            "wire time before it answers 0B."
        ),
    ] = 0.05,
    baudrate: Annotated[
        int | None, typer.Option(help="Line speed for timing rules and pacing.")
    ] = None,
    parity: Annotated[str | None, typer.Option(help="N, E or O.")] = None,
    stopbits: Annotated[int | None, typer.Option(help="1 or 2.")] = None,
    pace: Annotated[
        bool | None, typer.Option("--pace/--no-pace", help="Take the line's real time per frame.")
    ] = None,
    static: Annotated[
        bool, typer.Option("--static", help="Keep values still (for tests).")
    ] = False,
    seed: Annotated[int | None, typer.Option(help="Seed for values and fault injection.")] = None,
    stats: Annotated[
        Path | None, typer.Option("--stats", help="Keep a JSON stats file up to date here.")
    ] = None,
) -> None:
    """Simulate sensors on a pseudo-terminal or TCP, refereeing the master's timing."""
    try:
        if pty is None and tcp is None:
            raise ConfigError("give --pty PATH and/or --tcp HOST:PORT")
        if framing not in {"rtu", "tcp"}:
            raise ConfigError(
                f"--framing {framing!r}: expected rtu (RTU over TCP) or tcp (Modbus TCP)"
            )
        if not 0 < converter_timeout <= 10:  # noqa: PLR2004 - seconds, as the help says
            raise ConfigError(
                f"--converter-timeout {converter_timeout:g}: expected more than 0 and at most 10 s"
            )
        settings = _simulation_settings(
            device or [],
            config,
            {
                "baudrate": baudrate,
                "parity": parity,
                "stopbits": stopbits,
                "pace": pace,
                "seed": seed,
                "static": static,
            },
        )
        asyncio.run(
            _simulate(
                settings,
                pty,
                _host_port(tcp) if tcp else None,
                stats,
                framing=framing,
                converter_timeout_s=converter_timeout,
            )
        )
    except GatewayError as exc:
        raise fail(exc) from exc


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


@app.command("scan")
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
    from rich.progress import (  # noqa: PLC0415
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )
    from rich.table import Table  # noqa: PLC0415

    from gateway.line.scan import parse_addresses, scan_formats  # noqa: PLC0415
    from gateway.line.scan import scan as scan_bus  # noqa: PLC0415

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
            console=_err,
            transient=True,
            disable=as_json or not _err.is_terminal,
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
        _out.print(table)
        sys.stdout.write("\n" + report.config_yaml())
    _err.print(
        f"{len(report.devices)} device(s); {len(wanted)} address(es) x {len(formats)} "
        f"format(s) in {report.elapsed_s:.1f} s, {report.requests} requests",
        markup=False,
    )
    if report.garbled:
        where = ", ".join(f"{address} at {fmt}" for fmt, address in report.garbled)
        _err.print(
            f"broken answers from {where}: another line format? try --all-formats", markup=False
        )
    if not report.devices:
        _err.print(f"[bold red]no device answered[/] on {escape(port)}", highlight=False)
        raise typer.Exit(code=1)


def main() -> None:
    """Any command line, through typer (``gateway.cli.main`` reads a plain run itself)."""
    app()
