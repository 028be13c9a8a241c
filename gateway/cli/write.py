"""``gateway write``: one checked write to one point, from the command line.

The same path as an MQTT set command (:class:`gateway.control.writes.SafeWriter`): the value is
checked against the profile, a flash-backed point needs the device's ``flash_writes``
(with ``--config``) or ``--allow-flash``, is skipped when unchanged and counts against
the daily budget in the ledger the running gateway uses too; the point is read back.
"""

from __future__ import annotations

import asyncio
import json
import sys
from typing import TYPE_CHECKING, Annotated

import typer

from gateway.cli.device import device_link, err, fail, out, with_device_options
from gateway.config import FlashPolicy
from gateway.control.flash import FlashLedger
from gateway.control.writes import SafeWriter
from gateway.errors import CommandRejectedError, ConfigError, GatewayError, ProfileError
from gateway.line.samples import json_value
from gateway.profiles.model import Storage
from gateway.records.actor import acting, command_line_actor

if TYPE_CHECKING:
    from gateway.cli.device import DeviceOptions, DeviceSpec
    from gateway.control.writes import WriteOutcome


async def _write(
    spec: DeviceSpec, point: str, value: object, *, allow_flash: bool, reason: str
) -> WriteOutcome:
    policy = spec.policy
    if allow_flash:
        policy = FlashPolicy(allowed=policy.allowed | {point}, daily_budget=policy.daily_budget)
    target = spec.target.profile.point(point)  # the one lookup by name of a write
    flash = target.storage is Storage.FLASH
    # Only a flash write needs the shared ledger on disk; anything else leaves no file.
    ledger = spec.ledger() if flash else FlashLedger(None)
    records = spec.records()  # every write is recorded, where the running gateway records
    try:
        async with device_link(spec) as link:
            writer = SafeWriter(
                link, policy=policy, ledger=ledger, clock=spec.clock(), records=records
            )
            with acting(command_line_actor(reason)):
                return await writer.set(target, value)
    finally:
        ledger.close()
        records.close()


@with_device_options
def write(
    point: Annotated[str, typer.Argument(help="The point to write (see 'gateway profiles show').")],
    value: Annotated[
        str,
        typer.Argument(
            help="The value: a number, a label, true/false, ISO 8601 date-time, text, or "
            "JSON for a bit field ('{\"temperature_from_ram\": true}')."
        ),
    ],
    *,
    options: DeviceOptions,
    allow_flash: Annotated[
        bool,
        typer.Option(
            "--allow-flash",
            help="Allow this flash-backed point for this write (its cells wear out: "
            "never script this to run cyclically).",
        ),
    ] = False,
    as_json: Annotated[bool, typer.Option("--json", help="Print the outcome as JSON.")] = False,
    reason: Annotated[
        str, typer.Option("--reason", help="Why: kept in the write's record (who, what, why).")
    ] = "",
) -> None:
    """Write one point of one device, checked, flash-guarded, read back and recorded."""
    parsed: object = value
    if value.lstrip().startswith("{"):
        try:
            parsed = json.loads(value)
        except json.JSONDecodeError as exc:
            raise fail(CommandRejectedError(f"malformed JSON: {exc}")) from exc
    try:
        spec = options.spec()
        outcome = asyncio.run(_write(spec, point, parsed, allow_flash=allow_flash, reason=reason))
    except (CommandRejectedError, ConfigError, ProfileError) as exc:
        raise fail(exc) from exc  # refused: nothing was written (exit 2)
    except GatewayError as exc:
        raise fail(exc, code=1) from exc  # the device or the line failed (exit 1)
    shown = json_value(outcome.value)  # type: ignore[arg-type]
    if as_json:
        data = {
            "device": spec.target.name,
            "point": point,
            "written": outcome.written,
            "value": shown,
            "registers": list(outcome.registers),
            "flash": outcome.flash,
        }
        if outcome.note:
            data["note"] = outcome.note
        if outcome.record is not None:
            data["record"] = outcome.record
        sys.stdout.write(json.dumps(data, ensure_ascii=False) + "\n")
        return
    what = "written" if outcome.written else "not written"
    words = " ".join(f"{r:04X}" for r in outcome.registers)
    out.print(f"{point}: {what} ({words}); the device holds {shown!r}", markup=False)
    if outcome.note:
        err.print(outcome.note, markup=False)


def register(app: typer.Typer) -> None:
    """Add ``gateway write`` to the command line."""
    app.command("write")(write)
