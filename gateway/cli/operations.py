"""Operations on one sensor from the command line: clock, single measurement, logbook.

``gateway set-clock``, ``gateway measure`` and ``gateway calibration-log`` run the
operations of :mod:`gateway.control.operations` (the same code as the MQTT ``command/{name}``
topics) against one device named by the shared device options. Exit codes as everywhere
in the command line: 0 done, 1 the device or the line failed, 2 refused (bad input, an
operation the device does not have, the flash budget): nothing was written.
"""

from __future__ import annotations

import asyncio
import json
import sys
from datetime import UTC, datetime
from typing import TYPE_CHECKING, Annotated, TypeVar

import typer
from rich.markup import escape
from rich.table import Table

from gateway.cli.device import device_link, err, fail, out, with_device_options
from gateway.control import operations
from gateway.control.writes import SafeWriter
from gateway.errors import CommandRejectedError, ConfigError, GatewayError, ProfileError
from gateway.records.actor import acting, command_line_actor
from gateway.wire import codec

if TYPE_CHECKING:
    from collections.abc import Awaitable, Callable

    from gateway.cli.device import DeviceOptions, DeviceSpec

_T = TypeVar("_T")

JsonOption = Annotated[bool, typer.Option("--json", help="Print the result as JSON.")]


def _device(operation: str, options: DeviceOptions) -> DeviceSpec:
    """The device the options name, refused (exit 2) unless ``operation`` applies to it.

    Checked before the port is opened: a wrong device is refused without a frame sent.
    """
    try:
        spec = options.spec()
        operations.require_operation(operation, spec.target.profile)
    except (CommandRejectedError, ConfigError, ProfileError) as exc:
        raise fail(exc) from exc
    return spec


def _run(spec: DeviceSpec, operation: Callable[[SafeWriter], Awaitable[_T]]) -> _T:
    """Open the device, run ``operation`` with its writer, and map errors to exit codes."""
    try:
        return asyncio.run(_with_device(spec, operation))
    except CommandRejectedError as exc:
        raise fail(exc) from exc  # refused: nothing was written (exit 2)
    except GatewayError as exc:
        raise fail(exc, code=1) from exc  # the device or the line failed (exit 1)


async def _with_device(spec: DeviceSpec, operation: Callable[[SafeWriter], Awaitable[_T]]) -> _T:
    ledger = spec.ledger()
    records = spec.records()
    try:
        async with device_link(spec) as link:
            writer = SafeWriter(
                link, policy=spec.policy, ledger=ledger, clock=spec.clock(), records=records
            )
            with acting(command_line_actor()):
                return await operation(writer)
    finally:
        ledger.close()
        records.close()


def _print_json(data: dict[str, object]) -> None:
    sys.stdout.write(json.dumps(data, ensure_ascii=False) + "\n")


def _shown(value: codec.Decoded) -> str:
    """A value as a table cell: faults by name, dates readable, nothing as empty."""
    if value is None:
        return ""
    if isinstance(value, codec.Fault):
        return f"fault: {value.name}"
    if isinstance(value, datetime):
        return value.isoformat(sep=" ")
    return str(value)


# --- set-clock --------------------------------------------------------------------------


@with_device_options
def set_clock(
    options: DeviceOptions,
    local: Annotated[
        bool,
        typer.Option(
            "--local/--utc", help="Write this host's local time and offset instead of UTC."
        ),
    ] = False,
    as_json: JsonOption = False,
) -> None:
    """Set the sensor's clock (S10) or calibration date (H10/H20) from this host's clock."""
    spec = _device(operations.SET_CLOCK, options)
    result = _run(
        spec, lambda writer: operations.set_clock(writer, now=datetime.now(UTC), local=local)
    )
    if as_json:
        _print_json({"device": result.device, **result.as_dict()})
        return
    table = Table(title=escape(f"{result.device}: {result.point}, {result.meaning}"))
    for column in ("", "sensor", "gateway", "sensor - gateway"):
        table.add_column(column)
    table.add_row(
        "before",
        escape(_shown(result.before)),
        escape(_shown(result.gateway_before)),
        _seconds(result.offset_before_s),
    )
    table.add_row("written", escape(_shown(result.written)), "", "")
    table.add_row(
        "after",
        escape(_shown(result.after)),
        escape(_shown(result.gateway_after)),
        _seconds(result.offset_after_s),
    )
    out.print(table)
    if not result.running:
        out.print("This date does not run on the sensor: it stamps the next calibrations.")
    if result.note:
        err.print(result.note, markup=False)


def _seconds(value: float | None) -> str:
    if value is None:
        return ""
    return f"{round(value, 1) + 0.0:+.1f} s"  # + 0.0: no "-0.0" for a clock that is right


# --- measure ----------------------------------------------------------------------------


@with_device_options
def measure(
    options: DeviceOptions,
    wait: Annotated[
        float,
        typer.Option(
            "--wait",
            help="Seconds to wait for the measurement to finish.",
            min=0.1,
            max=operations.MEASURE_TIMEOUT_MAX_S,
        ),
    ] = operations.MEASURE_TIMEOUT_S,
    as_json: JsonOption = False,
) -> None:
    """Trigger a single measurement (H10/H20), wait for it, print oxygen and temperature."""
    spec = _device(operations.MEASURE, options)
    result = _run(spec, lambda writer: operations.measure(writer, timeout_s=wait))
    if as_json:
        _print_json({"device": result.device, **result.as_dict()})
        return
    parts = [
        f"{name} {_shown(value)} {result.units.get(name) or ''}".rstrip()
        for name, value in result.values.items()
    ]
    out.print(
        f"{result.device}: {', '.join(parts)} (measured in {result.duration_s:.2f} s)", markup=False
    )


# --- calibration-log --------------------------------------------------------------------


@with_device_options
def calibration_log(
    options: DeviceOptions,
    as_json: JsonOption = False,
) -> None:
    """Print the calibration logbook (H10/H20) or history (tecLine, Reiss) as a table."""
    spec = _device(operations.CALIBRATION_LOG, options)
    log = _run(spec, lambda writer: operations.calibration_log(writer.link))
    if as_json:
        _print_json({"device": log.device, **log.as_dict()})
        return
    if log.current:
        current = ", ".join(
            f"{name} {_shown(value)} {log.units.get(name, '')}".rstrip()
            for name, value in log.current.items()
        )
        out.print(f"{log.device}: current calibration: {current}", markup=False)
    table = Table(title=escape(f"{log.device}: {log.kind}"), caption=escape(log.note or ""))
    table.add_column("#", justify="right")
    for name in log.value_fields:
        table.add_column(name)
    for entry in log.entries:
        if entry.empty:
            table.add_row(str(entry.index), "(empty)", *[""] * (len(log.value_fields) - 1))
            continue
        cells = [
            escape(f"{_shown(entry.values[name])} {log.unit_of(entry, name)}".rstrip())
            for name in log.value_fields
        ]
        table.add_row(str(entry.index), *cells)
    out.print(table)


def register(app: typer.Typer) -> None:
    """Add ``set-clock``, ``measure`` and ``calibration-log`` to the ``gateway`` command line."""
    app.command("set-clock")(set_clock)
    app.command("measure")(measure)
    app.command("calibration-log")(calibration_log)
