"""Guided calibration: ``gateway calibrate ...``.

Each command names one device with the shared device options (:mod:`gateway.cli.device`),
runs the procedure of the calibration catalogue (:mod:`gateway.control.calibration.catalogue`)
that the device offers, and shows every step: what it reads, what it computes, the
registers it is about to write. It asks before writing unless ``--yes``. The options, their
checks and their defaults are the catalogue's parameters, as on the web page;
``gateway calibrate procedures`` lists them. Exit codes: 0 calibrated (or checked), 1
declined or verification failed, 2 refused before writing, or a device or line error.
"""

from __future__ import annotations

import asyncio
import json
import sys
from datetime import datetime
from typing import TYPE_CHECKING, Annotated, Any, Final

import typer
from rich.markup import escape
from rich.text import Text

from gateway.cli.device import device_link, err, fail, out, with_device_options
from gateway.control.calibration import Status, catalogue
from gateway.control.writes import SafeWriter
from gateway.errors import GatewayError
from gateway.profiles import get_profile
from gateway.records.actor import acting, command_line_actor

# This module is loaded only when one of its commands is run or listed (``cli/root``'s
# LAZY_COMMANDS), so it reads the catalogue, and with it the flows, at import.
if TYPE_CHECKING:
    from collections.abc import Mapping

    from rich.console import Console

    from gateway.cli.device import DeviceOptions, DeviceSpec
    from gateway.control import calibration
    from gateway.control.calibration import CalibrationOutcome, Step

calibrate_app = typer.Typer(
    help=(
        "Guided calibration: tecLine/Reiss slope, zero point, nominal slope and the regular "
        "check; H10/H20 zero point and end value. Shows each step and asks before writing; "
        "'procedures' lists them with their options and defaults."
    ),
    no_args_is_help=True,
)

# By the values of ``StepKind`` (a ``StrEnum``: its members are these strings).
_STYLES: Final = {
    "read": ("read", "cyan"),
    "compute": ("=", "cyan"),
    "plan": ("to write", "bold yellow"),
    "write": ("wrote", "green"),
    "verified": ("ok", "bold green"),
    "mismatch": ("MISMATCH", "bold red"),
    "warning": ("warning", "bold yellow"),
    "note": ("note", "dim"),
}


def _option(procedure_id: str, name: str) -> Any:  # noqa: ANN401 - what typer.Option returns
    """The command line's option for a parameter: its help and bounds from the catalogue."""
    parameter = catalogue.procedure(procedure_id).parameter(name)
    bound = int if parameter.kind is catalogue.InputKind.INTEGER else float
    return typer.Option(
        help=parameter.help,
        min=None if parameter.minimum is None else bound(parameter.minimum),
        max=None if parameter.maximum is None else bound(parameter.maximum),
    )


# The defaults of each procedure's parameters, as typer shows and applies them.
_SLOPE: Final = catalogue.procedure("slope").defaults()
_ZERO: Final = catalogue.procedure("zero").defaults()
_CHECK: Final = catalogue.procedure("check").defaults()
_OXYGEN_ZERO: Final = catalogue.procedure("oxygen_zero").defaults()
_END_VALUE: Final = catalogue.procedure("oxygen_end_value").defaults()
SLOPE_CELL_CURRENT: Final = _SLOPE.optional_number("cell_current")
SLOPE_SAMPLES: Final = _SLOPE.integer("samples")
SLOPE_EVERY: Final = _SLOPE.number("every")
ZERO_CURRENT: Final = _ZERO.optional_number("zero_current")
ZERO_SAMPLES: Final = _ZERO.integer("samples")
ZERO_EVERY: Final = _ZERO.number("every")
OXYGEN_ZERO_MODE: Final = _OXYGEN_ZERO.text("mode")
END_VALUE_UNIT: Final = _END_VALUE.optional_text("unit")
END_VALUE_MODE: Final = _END_VALUE.text("mode")
CHECK_CELL_CURRENT: Final = _CHECK.optional_number("cell_current")
CHECK_SAMPLES: Final = _CHECK.integer("samples")
CHECK_EVERY: Final = _CHECK.number("every")

ReferenceOption = Annotated[float, _option("slope", "reference")]
CellCurrentOption = Annotated[float | None, _option("slope", "cell_current")]
SamplesOption = Annotated[int, _option("slope", "samples")]
EveryOption = Annotated[float, _option("slope", "every")]
ZeroCurrentOption = Annotated[float | None, _option("zero", "zero_current")]
ModeOption = Annotated[str, _option("oxygen_zero", "mode")]
EndValueOption = Annotated[float, _option("oxygen_end_value", "reference")]
UnitOption = Annotated[str | None, _option("oxygen_end_value", "unit")]


def _parse_at(text: str) -> datetime:
    """Parse ``--at`` as ISO 8601; a bad value is a usage error before anything is opened."""
    try:
        return datetime.fromisoformat(text)
    except ValueError:
        raise typer.BadParameter(f"{text!r} is not ISO 8601, e.g. 2025-03-08T13:10") from None


AtOption = Annotated[
    datetime | None,
    typer.Option(
        parser=_parse_at,
        metavar="ISO-8601",
        help="Date and time of the calibration, ISO 8601 (default: now). The tecLine/Reiss "
        "stamp keeps the minute; the H10/H20 date the second and the UTC offset (local if none).",
    ),
]
YesOption = Annotated[bool, typer.Option("--yes", "-y", help="Write without asking.")]
JsonOption = Annotated[
    bool,
    typer.Option("--json", help="Print the outcome as JSON on stdout; progress goes to stderr."),
]


def register(app: typer.Typer) -> None:
    """Add this module's commands to the ``gateway`` command line."""
    app.add_typer(calibrate_app, name="calibrate")


class ConsoleOperator:
    """The operator at a terminal: each step printed as it happens, ``typer.confirm`` to ask."""

    def __init__(self, console: Console, *, assume_yes: bool, prompt_to_stderr: bool) -> None:
        """Print to ``console``; with ``assume_yes`` every confirmation is a yes."""
        self.console = console
        self.assume_yes = assume_yes
        self.prompt_to_stderr = prompt_to_stderr

    def show(self, step: Step) -> None:
        """One line, its kind as a coloured prefix; the text as it is (no markup)."""
        label, style = _STYLES[step.kind]
        self.console.print(Text.assemble((f"{label:>8}", style), " ", step.text))

    def confirm(self, question: str) -> bool:
        """Ask; ``--yes`` answers yes, end of input (no terminal) answers no."""
        if self.assume_yes:
            self.console.print(Text.assemble(("     yes", "bold"), " ", question, " (--yes)"))
            return True
        try:
            return typer.confirm(question, default=False, err=self.prompt_to_stderr)
        except typer.Abort:
            return False


def _when(at: datetime | None) -> datetime:
    """The ``--at`` time, or now (local, with its UTC offset)."""
    return at if at is not None else datetime.now().astimezone()


async def _session(
    spec: DeviceSpec,
    procedure: catalogue.Procedure,
    inputs: catalogue.Inputs,
    operator: calibration.Operator,
    *,
    when: datetime,
) -> CalibrationOutcome:
    ledger = spec.ledger()
    records = spec.records()
    try:
        async with device_link(spec) as link:
            writer = SafeWriter(
                link, policy=spec.policy, ledger=ledger, clock=spec.clock(), records=records
            )
            with acting(command_line_actor()):
                return await procedure.run(writer, operator, inputs, when=when)
    finally:
        ledger.close()
        records.close()


def _run(
    options: DeviceOptions,
    command: str,
    given: Mapping[str, object],
    *,
    at: datetime | None = None,
    yes: bool,
    as_json: bool,
) -> None:
    """Open the device, run the procedure ``command`` names for it, print, exit as above.

    Which procedure that is and the checks of ``given`` are the catalogue's, before the
    port is opened: a device without it is refused without a frame sent.
    """
    console = err if as_json else out
    operator = ConsoleOperator(console, assume_yes=yes, prompt_to_stderr=as_json)
    try:
        spec = options.spec()
        procedure, inputs = catalogue.choose(
            command, spec.target.profile, given, device=spec.target.name
        )
        outcome = asyncio.run(_session(spec, procedure, inputs, operator, when=_when(at)))
    except GatewayError as exc:
        raise fail(exc) from exc
    if as_json:
        sys.stdout.write(json.dumps(outcome.as_dict(), indent=2, ensure_ascii=False) + "\n")
    if outcome.status is Status.DECLINED:
        err.print("[bold]declined:[/] nothing was written")
        raise typer.Exit(code=1)
    if outcome.status is Status.VERIFICATION_FAILED:
        failed = "; ".join(c.name for c in outcome.failed_checks)
        err.print(f"[bold red]verification failed:[/] {escape(failed)}", highlight=False)
        raise typer.Exit(code=1)
    warnings = f" with {len(outcome.warnings)} warning(s)" if outcome.warnings else ""
    console.print(
        Text.assemble((f"{outcome.status.value}", "bold green"), f": {outcome.device}{warnings}")
    )


@calibrate_app.command("slope")
@with_device_options
def slope_command(
    *,
    reference: ReferenceOption,
    cell_current: CellCurrentOption = SLOPE_CELL_CURRENT,
    samples: SamplesOption = SLOPE_SAMPLES,
    every: EveryOption = SLOPE_EVERY,
    at: AtOption = None,
    yes: YesOption = False,
    as_json: JsonOption = False,
    options: DeviceOptions,
) -> None:
    """tecLine/Reiss slope calibration: X_Span = (cell current - X_Zero) / reference."""
    given = {
        "reference": reference,
        "cell_current": cell_current,
        "samples": samples,
        "every": every,
    }
    _run(options, "slope", given, at=at, yes=yes, as_json=as_json)


@calibrate_app.command("zero")
@with_device_options
def zero_command(
    *,
    zero_current: ZeroCurrentOption = ZERO_CURRENT,
    samples: SamplesOption = ZERO_SAMPLES,
    every: EveryOption = ZERO_EVERY,
    mode: ModeOption = OXYGEN_ZERO_MODE,
    at: AtOption = None,
    yes: YesOption = False,
    as_json: JsonOption = False,
    options: DeviceOptions,
) -> None:
    """Zero-point calibration: tecLine/Reiss X_Zero (annex 7.4), or H10/H20 via 0x3003."""
    given = {"zero_current": zero_current, "samples": samples, "every": every, "mode": mode}
    _run(options, "zero", given, at=at, yes=yes, as_json=as_json)


@calibrate_app.command("end-value")
@with_device_options
def end_value_command(
    *,
    reference: EndValueOption,
    unit: UnitOption = END_VALUE_UNIT,
    mode: ModeOption = END_VALUE_MODE,
    at: AtOption = None,
    yes: YesOption = False,
    as_json: JsonOption = False,
    options: DeviceOptions,
) -> None:
    """H10/H20 end-value calibration via 0x2043 and 0x3005, with mode and date."""
    given = {"reference": reference, "unit": unit, "mode": mode}
    _run(options, "end-value", given, at=at, yes=yes, as_json=as_json)


@calibrate_app.command("nominal")
@with_device_options
def nominal_command(
    *,
    at: AtOption = None,
    yes: YesOption = False,
    as_json: JsonOption = False,
    options: DeviceOptions,
) -> None:
    """tecLine/Reiss: restore the nominal slope (0x030A) and the zero point 0 (annex 7.5)."""
    _run(options, "nominal", {}, at=at, yes=yes, as_json=as_json)


@calibrate_app.command("check")
@with_device_options
def check_command(
    *,
    reference: ReferenceOption,
    cell_current: CellCurrentOption = CHECK_CELL_CURRENT,
    samples: SamplesOption = CHECK_SAMPLES,
    every: EveryOption = CHECK_EVERY,
    as_json: JsonOption = False,
    options: DeviceOptions,
) -> None:
    """tecLine/Reiss regular check (annex 7.3.4): today's slope against nominal; no writes."""
    given = {
        "reference": reference,
        "cell_current": cell_current,
        "samples": samples,
        "every": every,
    }
    _run(options, "check", given, yes=False, as_json=as_json)


@calibrate_app.command("procedures")
def procedures_command(
    *,
    profile: Annotated[
        str | None,
        typer.Option(help="Only the procedures a device of this profile offers."),
    ] = None,
    as_json: Annotated[
        bool,
        typer.Option("--json", help="Print them as JSON, as the web page and MQTT get them."),
    ] = False,
) -> None:
    """The guided calibrations: which sensors offer them, their options and defaults."""
    try:
        chosen = catalogue.offered(get_profile(profile)) if profile else catalogue.PROCEDURES
    except GatewayError as exc:
        raise fail(exc) from exc
    if as_json:
        documents = [
            p.as_dict() if profile else {**p.as_dict(), "profiles": catalogue.offering(p)}
            for p in chosen
        ]
        sys.stdout.write(json.dumps(documents, indent=2, ensure_ascii=False) + "\n")
        return
    if not chosen:
        out.print(f"{profile} offers no guided calibration.")
        return
    for procedure in chosen:
        _print_procedure(procedure, with_profiles=profile is None)


def _print_procedure(procedure: catalogue.Procedure, *, with_profiles: bool) -> None:
    from rich.table import Table  # noqa: PLC0415 - this listing only

    out.print(
        Text.assemble(
            (f"gateway calibrate {procedure.command}", "bold"),
            f"  {procedure.title} [{procedure.id}]: {procedure.purpose} ({procedure.source})",
        )
    )
    if with_profiles:
        out.print(f"  offered by: {', '.join(catalogue.offering(procedure))}")
    if not procedure.parameters:
        out.print("  no options\n")
        return
    table = Table(box=None, padding=(0, 2), show_edge=False)
    for column in ("option", "default", "allowed", "source"):
        table.add_column(column)
    for parameter in procedure.parameters:
        table.add_row(
            parameter.option,
            _default_text(parameter),
            _allowed_text(parameter),
            parameter.source,
        )
    out.print(table)
    out.print()


def _default_text(parameter: catalogue.Parameter) -> str:
    if parameter.required:
        return "required"
    if parameter.default is None:
        return f"({parameter.absent})"
    unit = f" {parameter.unit}" if parameter.unit else ""
    return f"{parameter.default}{unit}"


def _allowed_text(parameter: catalogue.Parameter) -> str:
    if parameter.choices:
        return ", ".join(parameter.choices)
    if parameter.minimum is None and parameter.maximum is None:
        return parameter.kind.value
    low = "" if parameter.minimum is None else f"{parameter.minimum:g}"
    high = "" if parameter.maximum is None else f"{parameter.maximum:g}"
    return f"{parameter.kind.value} {low} to {high}"
