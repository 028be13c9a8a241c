"""``gateway care``: what each sensor needs and when, as a table or JSON (cron, shift handover).

It asks the running gateway first (``GET /care`` on its metrics port: no frame on the
line, the same documents as MQTT's ``{base}/{device}/care``); when none answers, it opens
the buses itself and reads each sensor's care records once. Exit codes: 0 shown, 2 a bad
config, 1 no sensor could be read.
"""

from __future__ import annotations

import asyncio
import json
import sys
import urllib.error
import urllib.request
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, Final

import typer
from rich.markup import escape
from rich.table import Table

from gateway.app import device_target
from gateway.care import Records, assess, care_order, care_points
from gateway.care.rules import rules_for
from gateway.cli.device import err, fail, out
from gateway.config import load_config
from gateway.control.link import open_link
from gateway.control.ports import port_options
from gateway.errors import GatewayError
from gateway.wire import codec

if TYPE_CHECKING:
    from gateway.care import CareReport
    from gateway.config import DeviceConfig, GatewayConfig

DEFAULT_CONFIG: Final = Path("/etc/rs485-gateway/gateway.yaml")  # deploy/systemd's
ASK_TIMEOUT_S: Final = 3.0
_STYLE: Final = {
    "ok": "green",
    "due_soon": "yellow",
    "due": "dark_orange",
    "maintenance": "bold red",
    "unknown": "dim",
}


def _ask_running(config: GatewayConfig) -> list[dict[str, Any]] | None:
    """The running gateway's care documents, or None when none answers on the metrics port."""
    if not config.prometheus.enabled:
        return None
    host = config.prometheus.host
    host = "127.0.0.1" if host in {"0.0.0.0", "::", ""} else host  # noqa: S104 - a listen-all
    if ":" in host:
        host = f"[{host}]"
    url = f"http://{host}:{config.prometheus.port}/care"
    try:
        with urllib.request.urlopen(url, timeout=ASK_TIMEOUT_S) as answer:
            data = json.loads(answer.read())
    except (OSError, ValueError, urllib.error.URLError):
        return None
    return data if isinstance(data, list) else None


async def _read_one(config: GatewayConfig, device: DeviceConfig) -> tuple[CareReport, bool] | None:
    """One sensor's care report from its records read now, and whether it answered.

    None: care is off for it.
    """
    rules = rules_for(config, device)
    if rules is None:
        return None
    bus = config.bus(device.bus)
    target = device_target(device, bus)
    names = care_points(target.profile, rules.kind)
    values: dict[str, codec.Decoded] = {}
    unreadable: dict[str, str] = {}
    try:
        async with open_link(
            bus.port,
            bus.line,
            target,
            echo=bus.echo,
            options=port_options(bus, config.shared_bus),
            tcp=bus.tcp,
        ) as link:
            read = await link.read(*names)
    except GatewayError as exc:
        unreadable = dict.fromkeys(names, str(exc))
    else:
        for name, value in read.items():
            if isinstance(value, codec.Fault):
                unreadable[name] = f"the sensor sent {value.name}"
            else:
                values[name] = value
    report = assess(
        Records(values=values, unreadable=unreadable),
        rules,
        device=device.name,
        bus=device.bus,
        profile=device.profile,
        now=datetime.now(UTC),
    )
    return report, bool(values)


async def _read_all(config: GatewayConfig) -> tuple[list[CareReport], bool]:
    """Every device's report, one at a time (one port open at a time); whether any answered."""
    reports = []
    answered = False
    for device in config.devices:
        result = await _read_one(config, device)
        if result is not None:
            reports.append(result[0])
            answered = answered or result[1]
    return care_order(reports), answered


def _day(text: str | None) -> str:
    if text is None:
        return ""
    return f"{datetime.fromisoformat(text).astimezone():%a %d %b %Y}"


def _percent(value: object) -> str:
    return f"{value:.0%}" if isinstance(value, float) else ""


def _print_table(documents: list[dict[str, Any]], source: str) -> None:
    """A row per sensor, most urgent first; then each sensor's reasons in full."""
    table = Table(title="Sensor care", caption=escape(source))
    for column in ("device", "state", "last calibration", "due", "slope", "cap"):
        table.add_column(column)
    for doc in documents:
        state = str(doc.get("state"))
        table.add_row(
            escape(str(doc.get("device"))),
            f"[{_STYLE.get(state, '')}]{escape(state)}[/]",
            _day(doc.get("last_calibration")),
            _day(doc.get("due")),
            _percent(doc.get("slope_ratio")),
            _percent(doc.get("cap_usage")),
        )
    out.print(table)
    for doc in documents:
        reasons = "; ".join(doc.get("reasons") or [])
        out.print(f"{doc.get('device')} ({doc.get('state')}): {reasons}", markup=False)


def care(
    config: Annotated[
        Path,
        typer.Option("--config", "-c", help="The gateway's YAML config."),
    ] = DEFAULT_CONFIG,
    as_json: Annotated[
        bool, typer.Option("--json", help="Print the care documents as JSON.")
    ] = False,
) -> None:
    """What each sensor needs and when: calibration due, slope, cap, most urgent first.

    Asks the running gateway (its metrics port) or, when none answers, reads the sensors.
    """
    try:
        settings = load_config(config)
    except GatewayError as exc:
        raise fail(exc) from exc
    documents = _ask_running(settings)
    source = "from the running gateway"
    if documents is None:
        source = "read from the sensors now (no gateway answered on the metrics port)"
        reports, answered = asyncio.run(_read_all(settings))
        documents = [report.as_dict() for report in reports]
        if reports and not answered:
            ports = ", ".join(bus.port for bus in settings.buses)
            err.print(
                f"no sensor answered on {ports}, and no gateway answered on its metrics port "
                f"{settings.prometheus.port}: start the gateway service, or check the wiring, "
                "the line format and the addresses (each reason above says what the line did)",
                markup=False,
            )
            _show(documents, source, as_json=as_json)
            raise typer.Exit(code=1)
    _show(documents, source, as_json=as_json)


def _show(documents: list[dict[str, Any]], source: str, *, as_json: bool) -> None:
    if as_json:
        sys.stdout.write(json.dumps(documents, ensure_ascii=False) + "\n")
    else:
        _print_table(documents, source)


def register(app: typer.Typer) -> None:
    """Add ``care`` to the ``gateway`` command line."""
    app.command("care")(care)
