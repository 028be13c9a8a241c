"""The calibration catalogue: every guided procedure, who offers it, its inputs and defaults.

The command line (``gateway calibrate``), the web page and MQTT (the ``calibrations``
operation) read this one table; nothing else decides which procedure a device offers or
what an input defaults to, so the three cannot drift apart.

- A :class:`Procedure` is one flow of :mod:`gateway.control.calibration`: its id (the
  page's and MQTT's name for it), the ``gateway calibrate`` command that runs it, what it
  is for and the manual's section, the points a profile must declare for it (``needs``:
  which devices offer it is decided here, once, from the profile's data, never from a
  vendor name), the live values to watch settle, and its parameters.
- A :class:`~gateway.control.calibration.inputs.Parameter` is one input with its default
  and the manual's section the default comes from; where the manuals are silent, the
  source says the number is ours. :meth:`Procedure.parse` checks what a front end was
  given (text from a form, values from the command line) and fills in the defaults: the
  checks and the defaults are the same wherever a calibration starts.
- ``gateway calibrate zero`` is one command for two procedures (the tecLine/Reiss zero
  point and the H10/H20 one): :func:`choose` picks the one the device offers.
- :func:`asked_by_care` is the procedure sensor care asks for on a device
  (:data:`gateway.care.rules.CALIBRATION_PROCEDURE`), if the device offers it.

The defaults are the manuals': the tecLine annex (7.3.1, 7.4.1) and the Reiss manual
(5.2.1) read the cell current once, after the signal at the sensor is stable, and note
it; so one reading (``samples`` 1). An average of more is the operator's choice, one
second apart unless they say otherwise (the manuals give no interval; ours).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Final, TypeAlias

from gateway.care.rules import CALIBRATION_PROCEDURE, care_kind
from gateway.control.calibration.amperometric import (
    calibrate_slope,
    calibrate_zero_point,
    check_slope,
    restore_nominal_slope,
)
from gateway.control.calibration.arithmetic import (
    CALIBRATION_MODE_DEFAULT,
    CALIBRATION_MODES,
    CELL_CURRENT_READINGS,
    CELL_PROCEDURE_POINTS,
    END_VALUE_UNITS,
    MAX_READING_INTERVAL_S,
    MAX_READINGS,
    OXYGEN_END_VALUE_POINTS,
    OXYGEN_ZERO_POINTS,
    READING_INTERVAL_S,
)
from gateway.control.calibration.inputs import InputKind, Inputs, Parameter
from gateway.control.calibration.oxygen import calibrate_oxygen_end_value, calibrate_oxygen_zero
from gateway.control.clock_trust import require_trusted_clock, time_points
from gateway.errors import CalibrationInterruptedError, CommandRejectedError, RecordError
from gateway.profiles import builtin_profiles
from gateway.records.model import Kind, Result

if TYPE_CHECKING:
    from collections.abc import Awaitable, Callable, Mapping
    from datetime import datetime

    from gateway.control.calibration.steps import CalibrationOutcome, Operator
    from gateway.control.writes import SafeWriter
    from gateway.profiles import Profile

_LOGGER = logging.getLogger(__name__)

__all__ = [  # what the front ends use; the parameters' types come from ``inputs``
    "BY_ID",
    "CELLS",
    "CELL_CURRENT",
    "CELL_REFERENCE",
    "COMMANDS",
    "EVERY",
    "MODE",
    "OXYGEN",
    "OXYGEN_REFERENCE",
    "PROCEDURES",
    "SAMPLES",
    "UNIT",
    "ZERO_CURRENT",
    "InputKind",
    "Inputs",
    "Parameter",
    "Procedure",
    "asked_by_care",
    "choose",
    "offered",
    "offering",
    "procedure",
]

# A flow with its inputs: (writer, operator, inputs, when) -> outcome.
Runner: TypeAlias = (
    "Callable[[SafeWriter, Operator, Inputs, datetime], Awaitable[CalibrationOutcome]]"
)


@dataclass(frozen=True, slots=True, kw_only=True)
class Procedure:
    """One guided calibration: what it is for, who offers it, its inputs, how it runs."""

    id: str  # the page's and MQTT's name for it
    command: str  # the ``gateway calibrate`` command that runs it
    title: str
    family: str  # whose it is, in the words of the manuals' titles
    what: str  # what a refusal calls it: "has no slope calibration"
    purpose: str
    source: str  # the manual's sections
    needs: frozenset[str]  # the points a profile must declare to offer it
    writes: bool  # False: a check
    watch: tuple[str, ...]  # live values shown while the reading settles
    hint: str  # what must be true at the sensor before starting
    parameters: tuple[Parameter, ...]
    runner: Runner = field(repr=False, compare=False)

    def offered_by(self, profile: Profile) -> bool:
        """Whether a device of ``profile`` offers it: the profile declares what it needs."""
        return all(profile.has_point(point) for point in self.needs)

    def parameter(self, name: str) -> Parameter:
        """The parameter ``name`` (a ``KeyError`` if the procedure has none of that name)."""
        for parameter in self.parameters:
            if parameter.name == name:
                return parameter
        raise KeyError(name)

    def defaults(self) -> Inputs:
        """Every parameter at its default (None where it has none)."""
        return Inputs({p.name: p.default for p in self.parameters})

    def parse(self, given: Mapping[str, object]) -> Inputs:
        """The inputs a front end was given, checked, with the defaults of the rest.

        An input the procedure does not take is refused: it would otherwise be dropped
        without a word.
        """
        names = [p.name for p in self.parameters]
        unknown = sorted(set(given) - set(names))
        if unknown:
            takes = ", ".join(names) if names else "none"
            raise CommandRejectedError(
                f"the {self.id} calibration takes no {', '.join(unknown)} (its inputs: {takes})"
            )
        return Inputs({p.name: p.parse(given.get(p.name)) for p in self.parameters})

    async def run(
        self, writer: SafeWriter, operator: Operator, inputs: Inputs, *, when: datetime
    ) -> CalibrationOutcome:
        """Run the flow on ``writer``'s device; ``when`` dates it (the stamp or logbook date).

        A procedure that writes a date (every one that writes) is refused before it reads
        or asks anything while the host clock is not trusted (``writer.clock``): the
        operator learns it before preparing the sensor, not at the confirmation.
        """
        if self.writes:
            dated = [p for p in time_points(writer.link.profile) if p.name in self.needs]
            if dated:
                require_trusted_clock(
                    writer.clock, f"the {self.id} calibration of {writer.device}", dated[0]
                )
        recorder = writer.recorder
        before = recorder.records.head.seq if recorder is not None else 0
        try:
            outcome = await self.runner(writer, operator, inputs, when)
        except CalibrationInterruptedError as exc:
            await self._record(writer, before, Result.FAILED, str(exc), {"written": exc.written})
            raise
        result = Result.DONE if outcome.ok else Result.FAILED
        if not outcome.writes and not outcome.ok:
            result = Result.NOTED  # declined, or stopped before writing: nothing changed
        await self._record(writer, before, result, str(outcome.status), outcome.as_dict())
        return outcome

    async def _record(
        self,
        writer: SafeWriter,
        before: int,
        result: Result,
        note: str,
        data: Mapping[str, object],
    ) -> None:
        """The calibration as a whole, with the numbers of its write records."""
        recorder = writer.recorder
        if recorder is None:
            return
        try:
            await recorder.act(
                Kind.CALIBRATION,
                action=f"calibration: {self.title}",
                result=result,
                note=note,
                data={"procedure": self.id, **data, "write_records": recorder.writes_since(before)},
            )
        except RecordError as exc:
            _LOGGER.error(  # noqa: TRY400 - the cause is the message
                "%s: the calibration was not recorded: %s", writer.device, exc
            )

    def as_dict(self) -> dict[str, object]:
        """JSON-ready: what the page, ``gateway calibrate procedures`` and MQTT show."""
        return {
            "id": self.id,
            "command": self.command,
            "title": self.title,
            "family": self.family,
            "purpose": self.purpose,
            "source": self.source,
            "writes": self.writes,
            "watch": list(self.watch),
            "hint": self.hint,
            "fields": [p.as_dict() for p in self.parameters],
        }


# --- the parameters ------------------------------------------------------------------------

CELL_REFERENCE: Final = Parameter(
    name="reference",
    label="Reference (photometer or titration, in the sensor's unit)",
    help="The analysed concentration, in the sensor's unit (0x0200), e.g. from a "
    "photometer or titration (not a colorimeter).",
    kind=InputKind.NUMBER,
    required=True,
    source="tecLine annex 7.3.1 steps 4-5, Reiss 5.2.1: a sample analysed as fast as "
    "possible, with a photometer or by titration",
)
CELL_CURRENT: Final = Parameter(
    name="cell_current",
    label="Cell current noted when the sample was taken, nA (blank: read it now)",
    help="The cell current in nA noted when the sample was taken (default: read it now).",
    kind=InputKind.NUMBER,
    unit="nA",
    absent="read it now",
    source="tecLine annex 7.3.1 step 3, Reiss 5.2.1: the cell current noted when the "
    "sample is taken",
)
ZERO_CURRENT: Final = Parameter(
    name="zero_current",
    label="Cell current without disinfectant, nA, if noted (blank: read it now)",
    help="tecLine/Reiss: the cell current in nA without disinfectant, if noted "
    "(default: read it now).",
    kind=InputKind.NUMBER,
    unit="nA",
    absent="read it now",
    source="tecLine annex 7.4.1 step 3: the cell current without disinfectant, noted",
)
SAMPLES: Final = Parameter(
    name="samples",
    label="Readings to average",
    help="Readings of the cell current to average.",
    kind=InputKind.INTEGER,
    default=CELL_CURRENT_READINGS,
    minimum=1,
    maximum=MAX_READINGS,
    source="tecLine annex 7.3.1 steps 2-3 and 7.4.1 steps 2-3, Reiss 5.2.1: once the "
    "signal at the sensor is stable, the cell current is read once and noted",
)
EVERY: Final = Parameter(
    name="every",
    label="Seconds between readings",
    help="Seconds between those readings.",
    kind=InputKind.NUMBER,
    unit="s",
    default=READING_INTERVAL_S,
    minimum=0.0,
    maximum=MAX_READING_INTERVAL_S,
    source="ours: the manuals give no interval (one reading needs none); 1 s is the "
    "default poll interval of process values",
)
MODE: Final = Parameter(
    name="mode",
    label="Calibration mode (0x3009)",
    help="H10/H20 calibration mode 0x3009: as_configured (0x2021), wet or dry.",
    kind=InputKind.CHOICE,
    default=CALIBRATION_MODE_DEFAULT,
    choices=CALIBRATION_MODES,
    source="H10/H20 manual 6.2.4: 0x3009 is 0 at start-up, the mode configured at 0x2021",
)
OXYGEN_REFERENCE: Final = Parameter(
    name="reference",
    label="Oxygen at the end value",
    help="Oxygen at the end value (0x2043), in --unit or the unit at 0x204B.",
    kind=InputKind.NUMBER,
    required=True,
    source="H10/H20 manual 6.2.3 (0x2043) and 6.2.4 (0x3005)",
)
UNIT: Final = Parameter(
    name="unit",
    label="Unit of the reference (blank: the one the sensor holds)",
    help="Unit of the reference, written to 0x204B if it differs: "
    f"{', '.join(END_VALUE_UNITS)} (default: the one at 0x204B).",
    kind=InputKind.CHOICE,
    choices=END_VALUE_UNITS,
    absent="the one at 0x204B",
    source="H10/H20 manual 6.2.3, table 2 (0x204B): the unit the sensor holds",
)


# --- how each runs: the flow with its inputs ----------------------------------------------


async def _slope(
    writer: SafeWriter, operator: Operator, inputs: Inputs, when: datetime
) -> CalibrationOutcome:
    return await calibrate_slope(
        writer,
        operator,
        reference=inputs.number("reference"),
        when=when,
        cell_current_na=inputs.optional_number("cell_current"),
        samples=inputs.integer("samples"),
        sample_interval_s=inputs.number("every"),
    )


async def _zero(
    writer: SafeWriter, operator: Operator, inputs: Inputs, when: datetime
) -> CalibrationOutcome:
    return await calibrate_zero_point(
        writer,
        operator,
        when=when,
        zero_current_na=inputs.optional_number("zero_current"),
        samples=inputs.integer("samples"),
        sample_interval_s=inputs.number("every"),
    )


async def _nominal(
    writer: SafeWriter, operator: Operator, inputs: Inputs, when: datetime
) -> CalibrationOutcome:
    del inputs  # it takes none
    return await restore_nominal_slope(writer, operator, when=when)


async def _check(
    writer: SafeWriter, operator: Operator, inputs: Inputs, when: datetime
) -> CalibrationOutcome:
    del when  # it writes nothing, so it dates nothing
    return await check_slope(
        writer,
        operator,
        reference=inputs.number("reference"),
        cell_current_na=inputs.optional_number("cell_current"),
        samples=inputs.integer("samples"),
        sample_interval_s=inputs.number("every"),
    )


async def _oxygen_zero(
    writer: SafeWriter, operator: Operator, inputs: Inputs, when: datetime
) -> CalibrationOutcome:
    return await calibrate_oxygen_zero(writer, operator, when=when, mode=inputs.text("mode"))


async def _oxygen_end_value(
    writer: SafeWriter, operator: Operator, inputs: Inputs, when: datetime
) -> CalibrationOutcome:
    return await calibrate_oxygen_end_value(
        writer,
        operator,
        reference=inputs.number("reference"),
        when=when,
        unit=inputs.optional_text("unit"),
        mode=inputs.text("mode"),
    )


# --- the procedures ------------------------------------------------------------------------

CELLS: Final = "tecLine/Reiss"
OXYGEN: Final = "H10/H20"

PROCEDURES: Final = (
    Procedure(
        id="slope",
        command="slope",
        title="Slope (tecLine/Reiss)",
        family=CELLS,
        what="slope calibration",
        purpose="X_Span = (cell current - X_Zero) / the analysed reference; writes X_Zero, "
        "X_Span and the date stamp that activates them, checks the history and the "
        "concentration",
        source="tecLine annex 7.3.1-7.3.3, Reiss 5.2",
        needs=CELL_PROCEDURE_POINTS,
        writes=True,
        watch=("concentration", "cell_current"),
        hint="Take the sample at the sensor, analyse it, and wait for the cell current to "
        "settle before you start.",
        parameters=(CELL_REFERENCE, CELL_CURRENT, SAMPLES, EVERY),
        runner=_slope,
    ),
    Procedure(
        id="zero",
        command="zero",
        title="Zero point (tecLine/Reiss)",
        family=CELLS,
        what="zero-point calibration",
        purpose="X_Zero = the cell current without disinfectant; the slope stays; a slope "
        "calibration follows",
        source="tecLine annex 7.4, Reiss 5.2.2",
        needs=CELL_PROCEDURE_POINTS,
        writes=True,
        watch=("cell_current",),
        hint="The sensor must be in water without disinfectant, its cell current settled.",
        parameters=(ZERO_CURRENT, SAMPLES, EVERY),
        runner=_zero,
    ),
    Procedure(
        id="nominal",
        command="nominal",
        title="Nominal slope (tecLine/Reiss)",
        family=CELLS,
        what="nominal slope",
        purpose="restores the nominal slope (0x030A) as X_Span and the zero point 0, "
        "with a date stamp",
        source="tecLine annex 7.5, Reiss 5.3",
        needs=CELL_PROCEDURE_POINTS,
        writes=True,
        watch=("concentration",),
        hint="Restores the nominal slope and the zero point 0.",
        parameters=(),
        runner=_nominal,
    ),
    Procedure(
        id="check",
        command="check",
        title="Regular check (tecLine/Reiss, writes nothing)",
        family=CELLS,
        what="slope check",
        purpose="today's slope against the nominal one (below 30 % calls for maintenance) "
        "and the chemical check; writes nothing",
        source="tecLine annex 7.3.4, Reiss 5.2.3",
        needs=CELL_PROCEDURE_POINTS,
        writes=False,
        watch=("concentration", "cell_current"),
        hint="Today's slope against the nominal one; nothing is written.",
        parameters=(CELL_REFERENCE, CELL_CURRENT, SAMPLES, EVERY),
        runner=_check,
    ),
    Procedure(
        id="oxygen_zero",
        command="zero",
        title="Zero point (H10/H20)",
        family=OXYGEN,
        what="zero-point calibration",
        purpose="calibration mode (0x3009), date (0x300A), then 0x3003: the sensor takes "
        "its zero point from its last measurement and logs it",
        source="H10/H20 manual 6.2.4",
        needs=OXYGEN_ZERO_POINTS,
        writes=True,
        watch=("oxygen", "temperature"),
        hint="The sensor must be in an oxygen-free medium, its reading settled.",
        parameters=(MODE,),
        runner=_oxygen_zero,
    ),
    Procedure(
        id="oxygen_end_value",
        command="end-value",
        title="End value / span (H10/H20)",
        family=OXYGEN,
        what="end-value calibration",
        purpose="the reference as the end value (0x2043, unit 0x204B), mode and date, then "
        "0x3005: the sensor calibrates its span and logs it",
        source="H10/H20 manual 6.2.3 and 6.2.4",
        needs=OXYGEN_END_VALUE_POINTS,
        writes=True,
        watch=("oxygen", "temperature"),
        hint="The sensor must be in the reference medium (e.g. water-saturated air), its "
        "reading settled.",
        parameters=(OXYGEN_REFERENCE, UNIT, MODE),
        runner=_oxygen_end_value,
    ),
)
BY_ID: Final[Mapping[str, Procedure]] = {p.id: p for p in PROCEDURES}
# The `gateway calibrate` commands, in the order of the procedures they run.
COMMANDS: Final = tuple(dict.fromkeys(p.command for p in PROCEDURES))


def procedure(procedure_id: str) -> Procedure:
    """The procedure of that id, or a refusal naming the ones there are."""
    try:
        return BY_ID[procedure_id]
    except KeyError:
        raise CommandRejectedError(
            f"no calibration {procedure_id!r}; calibrations: {', '.join(BY_ID)}"
        ) from None


def offered(profile: Profile) -> tuple[Procedure, ...]:
    """The procedures a device of ``profile`` offers, in catalogue order."""
    return tuple(p for p in PROCEDURES if p.offered_by(profile))


def offering(candidate: Procedure) -> list[str]:
    """The built-in profiles that offer ``candidate``."""
    return [pid for pid, profile in builtin_profiles().items() if candidate.offered_by(profile)]


def choose(
    command: str, profile: Profile, given: Mapping[str, object], *, device: str
) -> tuple[Procedure, Inputs]:
    """The procedure ``gateway calibrate COMMAND`` runs on this device, and its inputs.

    ``given`` holds every option of the command. An option of another procedure of the
    same command (``--mode`` of the H10/H20 zero point on a tecLine) is refused when it
    was changed from its default, and dropped otherwise.
    """
    candidates = [p for p in PROCEDURES if p.command == command]
    if not candidates:
        raise CommandRejectedError(f"no calibration command {command!r}")
    chosen = next((p for p in candidates if p.offered_by(profile)), None)
    if chosen is None:
        families = " or ".join(dict.fromkeys(p.family for p in candidates))
        raise CommandRejectedError(
            f"{device} ({profile.id}) has no {candidates[0].what}: that is for {families} "
            f"sensors ({_offers(profile)})"
        )
    own = {p.name for p in chosen.parameters}
    mine: dict[str, object] = {}
    for name, value in given.items():
        if name in own:
            mine[name] = value
            continue
        other = next(p for p in candidates if any(q.name == name for q in p.parameters))
        if value != other.parameter(name).default:
            raise CommandRejectedError(
                f"{other.parameter(name).option} is for the {other.family} {other.what}, "
                f"not for {device} ({profile.id})"
            )
    return chosen, chosen.parse(mine)


def asked_by_care(profile: Profile) -> Procedure | None:
    """The calibration sensor care asks for on a device of ``profile``, if it offers it."""
    kind = care_kind(profile)
    wanted = BY_ID.get(CALIBRATION_PROCEDURE.get(kind, "")) if kind is not None else None
    return wanted if wanted is not None and wanted.offered_by(profile) else None


def _offers(profile: Profile) -> str:
    mine = offered(profile)
    if not mine:
        return "this device has no guided calibration"
    return "its calibrations: " + ", ".join(f"{p.command} ({p.id})" for p in mine)
