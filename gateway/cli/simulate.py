"""``gateway simulate``: sensors on a pseudo-terminal or TCP, refereeing the master's timing.

Loaded only when the command is run or listed (``cli/root``'s ``LAZY_COMMANDS``): the
simulator is no part of a running gateway.
"""

from __future__ import annotations

import asyncio
import signal
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from gateway.cli.device import fail, out
from gateway.errors import ConfigError, GatewayError
from gateway.simulator import (
    SimulatorServer,
    build_bus,
    load_settings,
    parse_device_option,
    parse_settings,
)

if TYPE_CHECKING:
    from gateway.simulator import SimulationSettings


def _simulation_settings(
    devices: list[str],
    config: Path | None,
    overrides: dict[str, object],
) -> SimulationSettings:
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
        out.print(
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


def register(app: typer.Typer) -> None:
    """Add ``simulate`` to the ``gateway`` command line."""
    app.command("simulate")(simulate)
