"""Guided calibration: ``gateway calibrate ...``.

Each command names one device with the shared device options (:mod:`gateway.cli.device`),
runs one flow of :mod:`gateway.control.calibration` and shows every step: what it reads, what it
computes, the registers it is about to write. It asks before writing unless ``--yes``.
Exit codes: 0 calibrated (or checked), 1 declined or verification failed, 2 refused
before writing, or a device or line error.
"""

from __future__ import annotations

import asyncio
import json
import sys
from datetime import datetime
from typing import TYPE_CHECKING, Annotated, Final

import typer
from rich.markup import escape
from rich.text import Text

from gateway.cli.device import device_link, err, fail, out, with_device_options
from gateway.control.writes import SafeWriter
from gateway.errors import CommandRejectedError, GatewayError

# The calibrations are imported by the command that runs one, not here: every command of
# the command line imports this module to register its own, `gateway run` included.
if TYPE_CHECKING:
    from collections.abc import Awaitable, Callable

    from rich.console import Console

    from gateway.cli.device import DeviceOptions, DeviceSpec
    from gateway.control import calibration
    from gateway.control.calibration import CalibrationOutcome, Step

    Flow = Callable[[SafeWriter, calibration.Operator], Awaitable[CalibrationOutcome]]

calibrate_app = typer.Typer(
    help=(
        "Guided calibration: tecLine/Reiss slope, zero point and nominal slope; "
        "H10/H20 zero point and end value. Shows each step and asks before writing."
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

ReferenceOption = Annotated[
    float,
    typer.Option(
        help="The analysed concentration, in the sensor's unit (0x0200), e.g. from a "
        "photometer or titration (not a colorimeter)."
    ),
]
CellCurrentOption = Annotated[
    float | None,
    typer.Option(
        help="The cell current in nA noted when the sample was taken (default: read it now)."
    ),
]
SamplesOption = Annotated[
    int, typer.Option(help="Readings of the cell current to average.", min=1, max=100)
]
EveryOption = Annotated[
    float, typer.Option(help="Seconds between those readings.", min=0.0, max=60.0)
]


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
ModeOption = Annotated[
    str,
    typer.Option(help="H10/H20 calibration mode 0x3009: as_configured (0x2021), wet or dry."),
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
    flow: Flow,
    operator: calibration.Operator,
) -> CalibrationOutcome:
    ledger = spec.ledger()
    try:
        async with device_link(spec) as link:
            return await flow(SafeWriter(link, policy=spec.policy, ledger=ledger), operator)
    finally:
        ledger.close()


def _run(
    options: DeviceOptions,
    flow: Flow,
    *,
    yes: bool,
    as_json: bool,
) -> None:
    """Open the device, run the flow, print the outcome and exit as the module says."""
    from gateway.control.calibration import Status  # noqa: PLC0415

    console = err if as_json else out
    operator = ConsoleOperator(console, assume_yes=yes, prompt_to_stderr=as_json)
    try:
        outcome = asyncio.run(_session(options.spec(), flow, operator))
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
    cell_current: CellCurrentOption = None,
    samples: SamplesOption = 3,
    every: EveryOption = 2.0,
    at: AtOption = None,
    yes: YesOption = False,
    as_json: JsonOption = False,
    options: DeviceOptions,
) -> None:
    """tecLine/Reiss slope calibration: X_Span = (cell current - X_Zero) / reference."""

    async def flow(writer: SafeWriter, operator: calibration.Operator) -> CalibrationOutcome:
        from gateway.control import calibration  # noqa: PLC0415

        return await calibration.calibrate_slope(
            writer,
            operator,
            reference=reference,
            when=_when(at),
            cell_current_na=cell_current,
            samples=samples,
            sample_interval_s=every,
        )

    _run(options, flow, yes=yes, as_json=as_json)


@calibrate_app.command("zero")
@with_device_options
def zero_command(
    *,
    zero_current: Annotated[
        float | None,
        typer.Option(
            help="tecLine/Reiss: the cell current in nA without disinfectant, if noted "
            "(default: read it now)."
        ),
    ] = None,
    samples: SamplesOption = 3,
    every: EveryOption = 2.0,
    mode: ModeOption = "as_configured",
    at: AtOption = None,
    yes: YesOption = False,
    as_json: JsonOption = False,
    options: DeviceOptions,
) -> None:
    """Zero-point calibration: tecLine/Reiss X_Zero (annex 7.4), or H10/H20 via 0x3003."""

    async def flow(writer: SafeWriter, operator: calibration.Operator) -> CalibrationOutcome:
        from gateway.control import calibration  # noqa: PLC0415

        if writer.link.profile.has_point("zero_point_calibration_trigger"):
            if zero_current is not None:
                raise CommandRejectedError("--zero-current is for tecLine/Reiss cells")
            return await calibration.calibrate_oxygen_zero(
                writer, operator, when=_when(at), mode=mode
            )
        if mode != "as_configured":
            raise CommandRejectedError("--mode is for the H10/H20 oxygen sensors")
        return await calibration.calibrate_zero_point(
            writer,
            operator,
            when=_when(at),
            zero_current_na=zero_current,
            samples=samples,
            sample_interval_s=every,
        )

    _run(options, flow, yes=yes, as_json=as_json)


@calibrate_app.command("end-value")
@with_device_options
def end_value_command(
    *,
    reference: Annotated[
        float,
        typer.Option(help="Oxygen at the end value (0x2043), in --unit or the unit at 0x204B."),
    ],
    unit: Annotated[
        str | None,
        typer.Option(
            help="Unit of the reference, written to 0x204B if it differs: percent_saturation, "
            "percent_volume, ppm, ppb, hpa (default: the one at 0x204B)."
        ),
    ] = None,
    mode: ModeOption = "as_configured",
    at: AtOption = None,
    yes: YesOption = False,
    as_json: JsonOption = False,
    options: DeviceOptions,
) -> None:
    """H10/H20 end-value calibration via 0x2043 and 0x3005, with mode and date."""

    async def flow(writer: SafeWriter, operator: calibration.Operator) -> CalibrationOutcome:
        from gateway.control import calibration  # noqa: PLC0415

        return await calibration.calibrate_oxygen_end_value(
            writer, operator, reference=reference, when=_when(at), unit=unit, mode=mode
        )

    _run(options, flow, yes=yes, as_json=as_json)


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

    async def flow(writer: SafeWriter, operator: calibration.Operator) -> CalibrationOutcome:
        from gateway.control import calibration  # noqa: PLC0415

        return await calibration.restore_nominal_slope(writer, operator, when=_when(at))

    _run(options, flow, yes=yes, as_json=as_json)


@calibrate_app.command("check")
@with_device_options
def check_command(
    *,
    reference: ReferenceOption,
    cell_current: CellCurrentOption = None,
    samples: SamplesOption = 3,
    every: EveryOption = 2.0,
    as_json: JsonOption = False,
    options: DeviceOptions,
) -> None:
    """tecLine/Reiss regular check (annex 7.3.4): today's slope against nominal; no writes."""

    async def flow(writer: SafeWriter, operator: calibration.Operator) -> CalibrationOutcome:
        from gateway.control import calibration  # noqa: PLC0415

        return await calibration.check_slope(
            writer,
            operator,
            reference=reference,
            cell_current_na=cell_current,
            samples=samples,
            sample_interval_s=every,
        )

    _run(options, flow, yes=False, as_json=as_json)
