"""``gateway demo``'s command: one gateway (gateway.cli.demo) or a fleet (gateway.cli.demo_fleet).

Apart from both, so that the fleet, which builds on the single demo's pieces, is not
imported by it.
"""

from __future__ import annotations

import asyncio
from typing import Annotated

import typer

from gateway.cli.demo import LOCAL_BIND, run_demo
from gateway.cli.demo_fleet import run_fleet
from gateway.cli.device import fail
from gateway.cli.heap import return_large_blocks
from gateway.errors import GatewayError


def demo(
    mqtt_port: Annotated[
        int, typer.Option(help="MQTT port: a broker there, else an embedded one.")
    ] = 1883,
    metrics_port: Annotated[int, typer.Option(help="Port of /metrics and /healthz.")] = 9108,
    web_port: Annotated[int, typer.Option(help="Port of the web page.")] = 8080,
    modbus_port: Annotated[
        int,
        typer.Option(help="Modbus TCP port for other masters (the shared bus); 0: off."),
    ] = 1502,
    bind: Annotated[
        str,
        typer.Option(
            help="Address /metrics, the web page and the embedded MQTT broker listen on; "
            "0.0.0.0 for every interface (a container with published ports)."
        ),
    ] = LOCAL_BIND,
    live: Annotated[
        bool,
        typer.Option(
            "--live/--no-live",
            help="The live table (on a terminal); without it, one line per poll cycle.",
        ),
    ] = True,
    fleet: Annotated[
        int | None,
        typer.Option(
            metavar="N",
            help="N gateways, one per simulated cabinet, into one broker; each takes the next "
            "port of --metrics-port, --web-port and --modbus-port (no live table).",
        ),
    ] = None,
) -> None:
    """Try it all with no hardware: simulated sensors, MQTT, metrics, the web page, a live table."""
    try:
        return_large_blocks()
        if fleet is not None:
            asyncio.run(
                run_fleet(
                    fleet,
                    mqtt_port=mqtt_port,
                    metrics_port=metrics_port,
                    web_port=web_port,
                    modbus_port=modbus_port,
                    bind=bind,
                )
            )
            return
        asyncio.run(
            run_demo(
                mqtt_port=mqtt_port,
                metrics_port=metrics_port,
                web_port=web_port,
                modbus_port=modbus_port,
                bind=bind,
                live=live,
            )
        )
    except GatewayError as exc:
        raise fail(exc) from exc


def register(app: typer.Typer) -> None:
    """Add ``gateway demo`` to the command line."""
    app.command("demo")(demo)
