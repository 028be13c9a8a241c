"""``gateway verify``: a grab sample compared with the sensor's value, judged and recorded.

With ``--config`` it asks the running gateway first (``POST /verify`` on its metrics port,
from this machine; the port is the gateway's, and it keeps the values of the last hour, so
a sample entered late is compared with the value the sensor read when it was taken). With
no gateway answering, it reads the sensor itself, once: the sample must then be from now.
Nothing is written to the sensor. Exit codes: 0 recorded and passed, 1 recorded and not
passed (calibrate), 2 refused (nothing recorded), 3 the sensor or the line failed.
"""

from __future__ import annotations

import asyncio
import json
import sys
import urllib.error
import urllib.request
from datetime import UTC, datetime
from typing import TYPE_CHECKING, Annotated, Any, Final

import typer

from gateway.cli.device import device_link, err, fail, out, with_device_options
from gateway.config import load_config
from gateway.config.verification import VerificationConfig
from gateway.control.flash import FlashLedger
from gateway.control.verification import VerificationRequest, verify
from gateway.control.writes import SafeWriter
from gateway.errors import BusError, CommandRejectedError, ConfigError, GatewayError
from gateway.line.samples import Quality
from gateway.records.actor import Actor, acting, command_line_actor
from gateway.records.recent import ValueAt
from gateway.records.verification import rule_for

if TYPE_CHECKING:
    from gateway.cli.device import DeviceOptions, DeviceSpec
    from gateway.config import GatewayConfig
    from gateway.control.verification import Verified
    from gateway.profiles.model import Point

ASK_TIMEOUT_S: Final = 35.0  # the gateway's own wait is 30 s
NOW_S: Final = 120.0  # without a running gateway, how old a sample may be: it is read now


def _ask_running(
    config: GatewayConfig, device: str, request: VerificationRequest, actor: Actor
) -> dict[str, Any] | None:
    """The running gateway's answer, or None when none answers on the metrics port."""
    if not config.prometheus.enabled:
        return None
    url = f"http://127.0.0.1:{config.prometheus.port}/verify"
    body = {
        "device": device,
        "actor": {"user": actor.user, "detail": actor.detail},
        **{k: v for k, v in request.as_dict().items() if v is not None},
    }
    ask = urllib.request.Request(
        url,
        data=json.dumps(body).encode(),
        headers={"Content-Type": "application/json"},
        method="POST",
    )
    try:
        with urllib.request.urlopen(ask, timeout=ASK_TIMEOUT_S) as answer:  # noqa: S310
            data = json.loads(answer.read())
    except urllib.error.HTTPError as exc:
        with exc:
            if exc.code == 404:  # noqa: PLR2004 - a gateway without verifications
                return None
            data = json.loads(exc.read() or b"{}")
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) else None


async def _verify_here(
    spec: DeviceSpec, request: VerificationRequest, settings: VerificationConfig
) -> Verified:
    """No gateway runs: read the sensor now, judge, record."""
    now = datetime.now(UTC)
    if request.sampled_at is not None and abs((now - request.sampled_at).total_seconds()) > NOW_S:
        raise CommandRejectedError(
            "no gateway is running to keep the sensor's past values, so the sample must be "
            f"from the last {NOW_S / 60:g} min: enter it while the gateway runs, or at once"
        )
    records = spec.records()
    try:
        async with device_link(spec) as link:
            writer = SafeWriter(link, policy=spec.policy, ledger=FlashLedger(None), records=records)

            async def value_at(device: str, point: Point, _at: datetime) -> ValueAt:
                [sample] = await link.worker.read_points(device, (point,))
                if sample.quality is not Quality.GOOD or not isinstance(sample.value, float):
                    raise BusError(f"{device}: {point.name} read {sample.fault or sample.value}")
                return ValueAt(at=sample.time, value=sample.value, unit=sample.unit)

            rule = rule_for(settings, device=spec.target.name, profile=spec.target.profile)
            return await verify(writer, request, rule=rule, value_at=value_at, now=now)
    finally:
        records.close()


def _show(answer: dict[str, Any], *, as_json: bool) -> None:
    if as_json:
        sys.stdout.write(json.dumps(answer, ensure_ascii=False) + "\n")
        return
    rule = answer.get("rule") or {}
    unit = answer.get("unit") or ""
    verdict = "PASSED" if answer.get("passed") else "NOT PASSED: calibrate"
    out.print(
        f"{verdict}: the sensor read {answer['sensor_value']:g} {unit} at "
        f"{answer['sensor_time']}, the reference {answer['reference']:g} {unit}: "
        f"{answer['deviation']:+g} off, {rule.get('name')} allows {answer['limit']:g} "
        f"(record {answer['record']})",
        markup=False,
    )


@with_device_options
def verify_command(
    *,
    options: DeviceOptions,
    reference: Annotated[
        float, typer.Option(help="The grab sample's value, in the sensor's unit.")
    ],
    method: Annotated[
        str, typer.Option(help="How it was analysed: DPD, photometer, titration, ...")
    ],
    unit: Annotated[str | None, typer.Option(help="The reference's unit (checked).")] = None,
    instrument: Annotated[str, typer.Option(help="The instrument's id or serial.")] = "",
    sampled_at: Annotated[
        str | None,
        typer.Option(help="When the sample was taken (ISO 8601, UTC if no zone); default now."),
    ] = None,
    point: Annotated[
        str | None, typer.Option(help="The point to compare (default: the process value).")
    ] = None,
    reason: Annotated[str, typer.Option(help="Why: kept in the record.")] = "",
    as_json: Annotated[bool, typer.Option("--json", help="Print the outcome as JSON.")] = False,
) -> None:
    """Compare a grab sample with the sensor's value at its time, judge it, record it."""
    given: dict[str, object] = {"reference": reference, "method": method, "reason": reason}
    given |= {"unit": unit, "instrument": instrument, "sampled_at": sampled_at, "point": point}
    try:
        request = VerificationRequest.from_arguments(
            {key: value for key, value in given.items() if value not in {None, ""}}
        )
        actor = command_line_actor(reason)
        settings = VerificationConfig()
        if options.config is not None and options.device is not None:
            config = load_config(options.config)
            settings = config.verification
            answer = _ask_running(config, options.device, request, actor)
            if answer is not None:
                if answer.get("status") != "ok":
                    raise CommandRejectedError(str(answer.get("reason")))  # noqa: TRY301
                _show(answer, as_json=as_json)
                raise typer.Exit(code=0 if answer.get("passed") else 1)
        spec = options.spec()
        with acting(actor):
            verified = asyncio.run(_verify_here(spec, request, settings))
    except (CommandRejectedError, ConfigError) as exc:
        raise fail(exc) from exc  # refused: nothing recorded (exit 2)
    except GatewayError as exc:
        raise fail(exc, code=3) from exc
    answer = {"status": "ok", "device": spec.target.name, **verified.as_dict()}
    _show(answer, as_json=as_json)
    if not verified.judgement.passed:
        err.print("not passed: the sensor is due for calibration", markup=False)
    raise typer.Exit(code=0 if verified.judgement.passed else 1)


def register(app: typer.Typer) -> None:
    """Add ``gateway verify`` to the command line."""
    app.command("verify")(verify_command)
