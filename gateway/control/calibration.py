"""Guided calibrations, step by step, as the sensor manuals describe them.

Two families calibrate over Modbus:

- **tecLine / Reiss** amperometric cells (tecLine annex 7, Reiss chapter 5): the master
  computes the calibration and writes it: X_Zero (0x0206, nA), X_Span (0x0208, nA per
  concentration unit), then the date stamp ``YYMMDDHHMM`` (0x020A), whose write activates
  it and moves the five-entry history (0x0210-0x022D). Procedures: slope
  (:func:`calibrate_slope`), zero point (:func:`calibrate_zero_point`), restoring the
  nominal slope (:func:`restore_nominal_slope`) and the regular check
  (:func:`check_slope`, which writes nothing).
- **digiLine O-DO H10/H20** (manual 6.2.4): the sensor calibrates itself with its last
  measured values when 0x3003 (zero point) or 0x3005 (end value) is written, after the
  calibration mode (0x3009) and date (0x300A) are set, and logs a new logbook entry.
  Procedures: :func:`calibrate_oxygen_zero`, :func:`calibrate_oxygen_end_value`.

Every flow reads what it needs and shows it, computes, shows the registers it is about to
write, asks the :class:`Operator` to confirm, writes through
:class:`gateway.control.writes.SafeWriter` (so flash writes are counted against the daily budget),
then reads back and checks the result as the manuals' "checking the calibration" sections
say. The arithmetic is in plain functions (:func:`slope_from`, :func:`judge_slope`,
:func:`calibration_stamp`, :func:`expected_history` ...) that need no I/O.

Outcomes: a :class:`CalibrationOutcome` whose status says calibrated, declined (nothing
written) or verification failed. A refusal before anything is written (bad input, the
flash budget, a wrong family) raises :class:`CommandRejectedError`; a failure part-way
through the writes raises :class:`CalibrationInterruptedError`, naming what was written.
"""

from __future__ import annotations

import asyncio
import math
import statistics
from dataclasses import dataclass, field
from datetime import datetime
from enum import StrEnum
from typing import TYPE_CHECKING, Final, Protocol

from gateway.config import FlashPolicy
from gateway.control.commands import function_for, writable_point
from gateway.control.flash import Action, check_flash_write, utc_today
from gateway.errors import CalibrationInterruptedError, CommandRejectedError, GatewayError
from gateway.line.samples import json_value
from gateway.profiles.model import Storage
from gateway.wire import codec

if TYPE_CHECKING:
    from collections.abc import Iterable, Mapping, Sequence

    from gateway.control.link import DeviceLink
    from gateway.control.writes import SafeWriter
    from gateway.profiles import Profile
    from gateway.profiles.model import Point

# tecLine annex 7.3.4: "If you identify that the currently determined slope is lower than 30 %
# of the nominal slope (value at address 0x030A), follow the maintenance instructions".
SLOPE_WARNING_FRACTION: Final = 0.30
# tecLine annex 7.2 / Reiss 5.1: history entries 0 (newest, copy of the current one) to 4.
HISTORY_ENTRIES: Final = 5
# tecLine annex 7.3.3 / Reiss 5.2.3 "chemical check": the sensor's and the analysed
# concentration "should be broadly identical". The manuals give no number; 10 % is ours.
CHEMICAL_CHECK_TOLERANCE: Final = 0.10
# A float32 read back is compared with the float64 we computed: 24 bits of mantissa.
_FLOAT32_REL_TOL: Final = 1e-6
# H10/H20 registers the sensor fills from the same measurement (203F and the logbook phase):
# compared with a little room, as the manual does not say they are bit-identical.
_SAME_MEASUREMENT_REL_TOL: Final = 1e-4

# X_Span is "nA per unit" of 0x0200 (tecLine annex 7.1), the nominal slope 0x030A is in nA/ppm
# (annex 7.5.1: "22 nA/ppm"). ppm per one unit of each 0x0200 code, for a dilute aqueous
# solution (1 l = 1 kg, so mg/l = ppm); our conversion, the manuals do not give one.
PPM_PER_UNIT: Final[Mapping[str, float]] = {
    "percent": 10_000.0,  # 1 % = 10 g/kg
    "permille": 1_000.0,  # 1 ‰ = 1 g/kg
    "g_per_l": 1_000.0,
    "ppm": 1.0,
    "mg_per_l": 1.0,
    "ppb": 0.001,
    "ug_per_l": 0.001,  # Reiss code 6, µg/l
}

AMPEROMETRIC_POINTS: Final = frozenset(
    {"cell_current", "x_zero", "x_span", "calibration_stamp", "nominal_slope", "unit"}
)
OPTICAL_OXYGEN_POINTS: Final = frozenset(
    {
        "zero_point_calibration_trigger",
        "end_value_calibration_trigger",
        "calibration_mode",
        "calibration_date",
        "end_value_oxygen",
        "logbook_1_entry_type",
    }
)
_LOGBOOK_NEWEST: Final = "logbook_1_"


# --- the pure part ---------------------------------------------------------------------------


def slope_from(cell_current_na: float, reference: float, *, zero_na: float = 0.0) -> float:
    """X_Span = (cell current - X_Zero) / reference concentration (tecLine annex 7.3.1).

    Refuses what cannot be a slope: a reference that is not above zero, or a cell current
    not above the zero point (the sensor would divide by a slope of zero or less).
    """
    if not math.isfinite(reference) or reference <= 0:
        raise CommandRejectedError(
            f"the reference concentration must be above 0, got {reference:g}", point="x_span"
        )
    signal = cell_current_na - zero_na
    if not math.isfinite(signal) or signal <= 0:
        raise CommandRejectedError(
            f"the cell current {cell_current_na:g} nA is not above the zero point "
            f"{zero_na:g} nA: is disinfectant present and the sensor polarised?",
            point="x_span",
        )
    return signal / reference


def nominal_in_unit(nominal_na_per_ppm: float, unit: str) -> float:
    """The nominal slope (nA/ppm) in nA per ``unit``, the unit label of 0x0200."""
    try:
        return nominal_na_per_ppm * PPM_PER_UNIT[unit]
    except KeyError:
        raise CommandRejectedError(
            f"the concentration unit {unit!r} (0x0200) has no known relation to ppm, so the "
            "nominal slope (nA/ppm) cannot be compared or written",
            point="x_span",
        ) from None


@dataclass(frozen=True, slots=True, kw_only=True)
class SlopeJudgement:
    """A slope against the nominal one: its fraction, and whether it is below 30 %."""

    slope: float  # nA per unit of 0x0200
    nominal: float  # the nominal slope in the same unit
    fraction: float  # slope / nominal
    low: bool  # below SLOPE_WARNING_FRACTION: maintain the sensor (annex 7.3.4)


def judge_slope(slope: float, nominal_na_per_ppm: float, unit: str) -> SlopeJudgement:
    """Compare a slope in nA per ``unit`` with the nominal slope (annex 7.3.4)."""
    nominal = nominal_in_unit(nominal_na_per_ppm, unit)
    if not math.isfinite(nominal) or nominal <= 0:
        raise CommandRejectedError(
            f"the nominal slope {nominal_na_per_ppm:g} nA/ppm (0x030A) is not usable",
            point="nominal_slope",
        )
    fraction = slope / nominal
    return SlopeJudgement(
        slope=slope, nominal=nominal, fraction=fraction, low=fraction < SLOPE_WARNING_FRACTION
    )


def calibration_stamp(when: datetime) -> datetime:
    """The tecLine/Reiss date stamp for ``when``: wall-clock time to the minute, no zone.

    The stamp ``YYMMDDHHMM`` (annex 7.1) has no time zone; an aware ``when`` keeps its own
    wall-clock time, as :mod:`gateway.control.commands` does for set commands.
    """
    return when.replace(tzinfo=None, second=0, microsecond=0)


def stamp_number(when: datetime) -> int:
    """The stamp as the sensor holds it, e.g. 2019-03-08 13:10 -> 1903081310 (annex 7.1).

    Representable from 2000-01-01 00:00 to 2042-12-31 23:59 (a uint32, annex 7.1).
    """
    stamp = calibration_stamp(when)
    if not 2000 <= stamp.year <= 2042:  # noqa: PLR2004 - the annex's limits, named above
        raise CommandRejectedError(
            f"{stamp:%Y-%m-%d %H:%M} is outside the stamp's 2000-2042 range",
            point="calibration_stamp",
        )
    return int(f"{stamp:%y%m%d%H%M}")


class HistoryEffect(StrEnum):
    """What writing a date stamp does to the history (tecLine annex 7.2, Reiss 5.1)."""

    PUSH = "push"  # later stamp: new entry 0, the others move down one, entry 4 is dropped
    OVERWRITE = "overwrite"  # equal or earlier stamp: entry 0 replaced, entries 1-4 kept


def history_effect(new: datetime, last: datetime | None) -> HistoryEffect:
    """The effect of stamp ``new`` when history entry 0 holds ``last`` (None: never set)."""
    if last is None or calibration_stamp(new) > calibration_stamp(last):
        return HistoryEffect.PUSH
    return HistoryEffect.OVERWRITE


@dataclass(frozen=True, slots=True)
class HistoryEntry:
    """One calibration: zero point (nA), slope (nA/unit) and date stamp (None: never set)."""

    x_zero: float
    x_span: float
    stamp: datetime | None

    def matches(self, other: HistoryEntry) -> bool:
        """Equal as the sensor stores it: floats to float32 precision, stamps exactly."""
        return (
            _close(self.x_zero, other.x_zero)
            and _close(self.x_span, other.x_span)
            and self.stamp == other.stamp
        )

    def as_dict(self) -> dict[str, object]:
        """JSON-ready."""
        return {
            "x_zero": self.x_zero,
            "x_span": self.x_span,
            "stamp": None if self.stamp is None else self.stamp.isoformat(timespec="minutes"),
        }

    def __str__(self) -> str:
        """One line for the operator."""
        when = "never" if self.stamp is None else f"{self.stamp:%Y-%m-%d %H:%M}"
        return f"X_Zero {self.x_zero:.6g} nA, X_Span {self.x_span:.6g}, {when}"


def expected_history(
    before: Sequence[HistoryEntry], new: HistoryEntry, effect: HistoryEffect
) -> tuple[HistoryEntry, ...]:
    """The history after activating ``new``, as annex 7.2 describes it."""
    if effect is HistoryEffect.PUSH:
        return (new, *before[: len(before) - 1])
    return (new, *before[1:])


def _close(a: float, b: float, rel_tol: float = _FLOAT32_REL_TOL) -> bool:
    return math.isclose(a, b, rel_tol=rel_tol, abs_tol=1e-9)


# --- talking to the operator -----------------------------------------------------------------


class StepKind(StrEnum):
    """What a step shown to the operator is."""

    READ = "read"
    COMPUTE = "compute"
    PLAN = "plan"  # a write about to be confirmed
    WRITE = "write"
    VERIFIED = "verified"  # a verification that held
    MISMATCH = "mismatch"  # a verification that did not
    WARNING = "warning"
    NOTE = "note"


@dataclass(frozen=True, slots=True)
class Step:
    """One line of a flow's progress."""

    kind: StepKind
    text: str


class Operator(Protocol):
    """Whoever runs a calibration: sees each step and confirms before anything is written."""

    def show(self, step: Step) -> None:
        """Show one step as it happens."""

    def confirm(self, question: str) -> bool:
        """Ask before writing; ``False`` stops the flow with nothing written."""


class Status(StrEnum):
    """How a flow ended."""

    CALIBRATED = "calibrated"
    DECLINED = "declined"  # the operator said no; nothing was written
    VERIFICATION_FAILED = "verification_failed"  # written, but the read-back does not agree
    CHECKED = "checked"  # a check that writes nothing


@dataclass(frozen=True, slots=True, kw_only=True)
class Check:
    """One verification: what the manual says should be there, and what is."""

    name: str
    expected: object
    actual: object
    ok: bool
    source: str  # the manual's section that asks for it

    def as_dict(self) -> dict[str, object]:
        """JSON-ready."""
        return {
            "name": self.name,
            "expected": _jsonable(self.expected),
            "actual": _jsonable(self.actual),
            "ok": self.ok,
            "source": self.source,
        }


@dataclass(frozen=True, slots=True, kw_only=True)
class PlannedWrite:
    """One register write of a flow: the point, what is written and how."""

    point: str
    address: int
    value: object
    registers: tuple[int, ...]
    function: int  # 6 or 16
    flash: bool
    why: str
    target: Point = field(repr=False, compare=False)  # the point, resolved once by its name

    def as_dict(self) -> dict[str, object]:
        """JSON-ready."""
        return {
            "point": self.point,
            "address": self.address,
            "value": _jsonable(self.value),
            "registers": list(self.registers),
            "function": self.function,
            "flash": self.flash,
        }

    def __str__(self) -> str:
        """One line: where, what, as which registers."""
        words = " ".join(f"0x{r:04X}" for r in self.registers)
        return (
            f"0x{self.address:04X} {self.point} = {_show(self.value)} "
            f"(function {self.function:02d}: {words}){' [flash]' if self.flash else ''}"
            f" - {self.why}"
        )


@dataclass(frozen=True, slots=True, kw_only=True)
class CalibrationOutcome:
    """What a flow did and found; ``as_dict`` is the ``--json`` output."""

    device: str
    procedure: str
    status: Status
    values: Mapping[str, object]
    writes: tuple[PlannedWrite, ...]  # what was written (nothing when declined)
    checks: tuple[Check, ...]
    warnings: tuple[str, ...]
    record: Mapping[str, object] = field(default_factory=dict)  # history / logbook read back

    @property
    def ok(self) -> bool:
        """Whether the flow reached its goal."""
        return self.status in {Status.CALIBRATED, Status.CHECKED}

    @property
    def failed_checks(self) -> tuple[Check, ...]:
        """The verifications that did not hold."""
        return tuple(c for c in self.checks if not c.ok)

    def as_dict(self) -> dict[str, object]:
        """JSON-ready."""
        return {
            "device": self.device,
            "procedure": self.procedure,
            "status": self.status.value,
            "ok": self.ok,
            "values": {k: _jsonable(v) for k, v in self.values.items()},
            "writes": [w.as_dict() for w in self.writes],
            "checks": [c.as_dict() for c in self.checks],
            "warnings": list(self.warnings),
            "record": {k: _jsonable(v) for k, v in self.record.items()},
        }


def _jsonable(value: object) -> object:
    if isinstance(value, list | tuple):
        return [_jsonable(v) for v in value]
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, codec.Fault):
        return {"fault": value.name}
    if isinstance(value, HistoryEntry):
        return value.as_dict()
    if isinstance(value, StrEnum) or not isinstance(value, _JSON_READY):
        return str(value)
    return json_value(value)


_JSON_READY: Final = (
    type(None),
    bool,
    int,
    float,
    str,
    datetime,
    codec.EnumValue,
    codec.BitfieldValue,
)


def _show(value: object) -> str:
    if isinstance(value, float):
        return f"{value:.6g}"
    if isinstance(value, datetime):
        return value.isoformat(sep=" ")
    if isinstance(value, codec.Fault):
        return f"!{value.name}"
    return str(value)


# --- the flow machinery ----------------------------------------------------------------------


class _Flow:
    """The shared steps of every procedure: read, say, plan, confirm, write, check."""

    def __init__(self, writer: SafeWriter, operator: Operator, procedure: str) -> None:
        self.writer = writer
        self.link: DeviceLink = writer.link
        self.profile: Profile = writer.link.profile
        self.operator = operator
        self.procedure = procedure
        self.values: dict[str, object] = {}
        self.warnings: list[str] = []
        self.checks: list[Check] = []

    def say(self, kind: StepKind, text: str) -> None:
        self.operator.show(Step(kind, text))

    def warn(self, text: str) -> None:
        self.warnings.append(text)
        self.say(StepKind.WARNING, text)

    def require(self, points: Iterable[str], what: str) -> None:
        """Refuse, before any I/O, a device whose profile lacks the procedure's registers."""
        missing = sorted(p for p in points if not self.profile.has_point(p))
        if missing:
            raise CommandRejectedError(
                f"{self.link.device} ({self.profile.id}) has no {what}: "
                f"its profile lacks {', '.join(missing)}"
            )

    async def read(self, *points: str) -> dict[str, codec.Decoded]:
        return await self.link.read(*points)

    def number(self, values: Mapping[str, codec.Decoded], point: str) -> float:
        """A read value that must be a number to go on; a fault refuses the calibration."""
        value = values[point]
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise CommandRejectedError(
                f"{point} reads {_show(value)}, not a number: cannot calibrate", point=point
            )
        return float(value)

    async def sample(self, point: str, *, samples: int, interval_s: float, unit: str) -> float:
        """Read a point ``samples`` times, ``interval_s`` apart, and return the mean."""
        if samples < 1:
            raise CommandRejectedError(f"at least one sample is needed, got {samples}")
        readings: list[float] = []
        for n in range(samples):
            if n:
                await asyncio.sleep(interval_s)
            readings.append(self.number(await self.read(point), point))
            self.say(StepKind.READ, f"{point} sample {n + 1}/{samples}: {readings[-1]:.6g} {unit}")
        mean = statistics.fmean(readings)
        self.values[f"{point}_samples"] = readings
        if samples > 1:
            spread = max(readings) - min(readings)
            self.say(
                StepKind.COMPUTE, f"{point} mean {mean:.6g} {unit}, spread {spread:.3g} {unit}"
            )
        return mean

    async def plan(self, point: str, value: object, why: str) -> PlannedWrite:
        """Encode a write (the value checked against the point) without sending it."""
        target = writable_point(self.profile, point)  # the one lookup by name of the step
        registers = await self.link.encode(target, value)
        planned = PlannedWrite(
            point=point,
            address=target.address,
            value=value,
            registers=registers,
            function=function_for(registers),
            flash=target.storage is Storage.FLASH,
            why=why,
            target=target,
        )
        self.say(StepKind.PLAN, str(planned))
        return planned

    def preflight(self, plans: Sequence[PlannedWrite]) -> None:
        """Refuse the whole flow if any flash write would be refused, so none is half-done.

        :class:`SafeWriter` checks each write again; this only keeps a flow from stopping
        after its first writes because a later point's budget is spent.
        """
        policy = self.writer.policy
        today = utc_today()
        for planned in plans:
            if not planned.flash:
                continue
            decision = check_flash_write(
                planned.target,
                self.link.device,
                policy=FlashPolicy(
                    allowed=policy.allowed | {planned.point}, daily_budget=policy.daily_budget
                ),
                ledger=self.writer.ledger,
                current=None,
                registers=planned.registers,
                today=today,
            )
            if decision.action is Action.REFUSE:
                raise CommandRejectedError(
                    f"{decision.reason}; the calibration needs it, so nothing was written",
                    point=planned.point,
                )

    def confirm(self, plans: Sequence[PlannedWrite]) -> bool:
        flash = sum(p.flash for p in plans)
        question = (
            f"Write {len(plans)} register block(s) to {self.link.device} "
            f"({flash} to flash/EEPROM, counted against the daily budget)?"
        )
        if self.operator.confirm(question):
            return True
        self.say(StepKind.NOTE, "declined: nothing was written")
        return False

    async def write(self, plans: Sequence[PlannedWrite], *, if_interrupted: str) -> None:
        """Write in order; a failure part-way raises :class:`CalibrationInterruptedError`."""
        done: list[str] = []
        for planned in plans:
            try:
                await self.writer.set(planned.target, planned.value, explicit=True, read_back=False)
            except GatewayError as exc:
                before = ", ".join(done) if done else "nothing"
                raise CalibrationInterruptedError(
                    f"{self.procedure} calibration of {self.link.device} stopped at "
                    f"{planned.point}: {exc}. Written before it: {before}. {if_interrupted}",
                    written=tuple(done),
                    failed=planned.point,
                ) from exc
            done.append(planned.point)
            self.say(StepKind.WRITE, f"0x{planned.address:04X} {planned.point}")

    def check(self, name: str, *, expected: object, actual: object, ok: bool, source: str) -> None:
        self.checks.append(Check(name=name, expected=expected, actual=actual, ok=ok, source=source))
        verdict = "as expected" if ok else f"expected {_show(expected)}"
        self.say(
            StepKind.VERIFIED if ok else StepKind.MISMATCH,
            f"{name}: {_show(actual)} ({verdict}; {source})",
        )

    def outcome(
        self,
        status: Status,
        writes: Sequence[PlannedWrite] = (),
        record: Mapping[str, object] | None = None,
    ) -> CalibrationOutcome:
        if status is Status.CALIBRATED and any(not c.ok for c in self.checks):
            status = Status.VERIFICATION_FAILED
        return CalibrationOutcome(
            device=self.link.device,
            procedure=self.procedure,
            status=status,
            values=dict(self.values),
            writes=tuple(writes),
            checks=tuple(self.checks),
            warnings=tuple(self.warnings),
            record=dict(record or {}),
        )


# --- tecLine / Reiss -------------------------------------------------------------------------

_HISTORY_PARTS: Final = ("x_zero", "x_span", "stamp")
_AMPEROMETRIC_SOURCE: Final = "tecLine annex 7.3.3 / Reiss 5.2.3"
_HISTORY_SOURCE: Final = "tecLine annex 7.2 / Reiss 5.1"
_NOT_ACTIVE: Final = (
    "The date stamp activates a calibration, so the one in use may still be the old one: "
    "read X_Zero, X_Span and history entry 0 and repeat the calibration."
)


def _history_points() -> tuple[str, ...]:
    return tuple(f"history_{i}_{part}" for i in range(HISTORY_ENTRIES) for part in _HISTORY_PARTS)


def _history(values: Mapping[str, codec.Decoded]) -> tuple[HistoryEntry, ...]:
    entries = []
    for i in range(HISTORY_ENTRIES):
        zero, span, stamp = (values[f"history_{i}_{part}"] for part in _HISTORY_PARTS)
        entries.append(
            HistoryEntry(
                x_zero=float(zero) if isinstance(zero, int | float) else math.nan,
                x_span=float(span) if isinstance(span, int | float) else math.nan,
                stamp=stamp if isinstance(stamp, datetime) else None,
            )
        )
    return tuple(entries)


@dataclass(frozen=True, slots=True)
class _CellState:
    """What an amperometric flow reads before it starts."""

    unit: str  # label of 0x0200
    unit_text: str  # as shown, e.g. "ppm"
    nominal: float  # nA/ppm, 0x030A
    current: HistoryEntry  # 0x0206-0x020A
    history: tuple[HistoryEntry, ...]
    concentration: codec.Decoded


async def _read_cell(flow: _Flow) -> _CellState:
    values = await flow.read(
        "unit", "nominal_slope", "x_zero", "x_span", "calibration_stamp", "concentration"
    )
    unit = values["unit"]
    label = unit.label if isinstance(unit, codec.EnumValue) else str(unit)
    unit_text = (
        flow.profile.point("unit").enum_units.get(unit.code, label)
        if isinstance(unit, codec.EnumValue)
        else label
    )
    stamp = values["calibration_stamp"]
    current = HistoryEntry(
        x_zero=flow.number(values, "x_zero"),
        x_span=flow.number(values, "x_span"),
        stamp=stamp if isinstance(stamp, datetime) else None,
    )
    history = _history(await flow.read(*_history_points()))
    state = _CellState(
        unit=label,
        unit_text=unit_text,
        nominal=flow.number(values, "nominal_slope"),
        current=current,
        history=history,
        concentration=values["concentration"],
    )
    flow.say(
        StepKind.READ,
        f"concentration {_show(state.concentration)} {unit_text} (unit 0x0200: {unit_text}), "
        f"nominal slope 0x030A {state.nominal:.6g} nA/ppm",
    )
    flow.say(
        StepKind.READ,
        f"current calibration 0x0206-0x020A (X_Span in nA/{unit_text}): {current}",
    )
    for i, entry in enumerate(history):
        flow.say(StepKind.READ, f"history {i}: {entry}")
    flow.values.update(
        unit=unit_text,
        nominal_slope=state.nominal,
        before={"current": current, "history": list(history)},
    )
    return state


def _announce_stamp(flow: _Flow, state: _CellState, stamp: datetime) -> HistoryEffect:
    last = state.history[0].stamp
    effect = history_effect(stamp, last)
    number = stamp_number(stamp)
    flow.values.update(stamp=stamp, stamp_number=number, history_effect=effect)
    if effect is HistoryEffect.PUSH:
        dropped = state.history[-1]
        flow.say(
            StepKind.COMPUTE,
            f"date stamp {number}: later than history entry 0, so the history moves down one "
            f"place and entry {HISTORY_ENTRIES - 1} ({dropped}) is dropped (annex 7.2)",
        )
    elif last == stamp:
        flow.say(
            StepKind.COMPUTE,
            f"date stamp {number}: the same minute as history entry 0, so it overwrites the "
            "current calibration and entry 0 only; entries 1-4 stay (annex 7.2)",
        )
    else:
        flow.warn(
            f"date stamp {number} is earlier than history entry 0 "
            f"({last:%Y-%m-%d %H:%M}): it overwrites entry 0 only and the history does not "
            "move; is the clock right?"
        )
    return effect


async def _activate_and_verify(
    flow: _Flow,
    state: _CellState,
    new: HistoryEntry,
    *,
    order: Sequence[str],
    why: Mapping[str, str],
) -> CalibrationOutcome:
    """Write X_Zero, X_Span (in ``order``) and the stamp; then check as annex 7.3.3 says."""
    assert new.stamp is not None  # noqa: S101 - every flow stamps its calibration
    effect = _announce_stamp(flow, state, new.stamp)
    values = {"x_zero": new.x_zero, "x_span": new.x_span, "calibration_stamp": new.stamp}
    plans = [await flow.plan(point, values[point], why[point]) for point in order]
    plans.append(
        await flow.plan(
            "calibration_stamp", new.stamp, "YYMMDDHHMM; writing it activates the calibration"
        )
    )
    flow.preflight(plans)
    if not flow.confirm(plans):
        return flow.outcome(Status.DECLINED)
    await flow.write(plans, if_interrupted=_NOT_ACTIVE)

    after = await flow.read("x_zero", "x_span", "calibration_stamp", *_history_points())
    history = _history(after)
    stamp = after["calibration_stamp"]
    current = HistoryEntry(
        x_zero=flow.number(after, "x_zero"),
        x_span=flow.number(after, "x_span"),
        stamp=stamp if isinstance(stamp, datetime) else None,
    )
    flow.check(
        "current calibration 0x0206-0x020A",
        expected=new,
        actual=current,
        ok=current.matches(new),
        source=_AMPEROMETRIC_SOURCE,
    )
    flow.check(
        "history entry 0 (X_Zero 0x0210, X_Span 0x0212)",
        expected=new,
        actual=history[0],
        ok=history[0].matches(new),
        source=_AMPEROMETRIC_SOURCE,
    )
    expected = expected_history(state.history, new, effect)
    for i in range(1, HISTORY_ENTRIES):
        moved = "moved down from entry " + str(i - 1) if effect is HistoryEffect.PUSH else "kept"
        flow.check(
            f"history entry {i} ({moved})",
            expected=expected[i],
            actual=history[i],
            ok=history[i].matches(expected[i]),
            source=_HISTORY_SOURCE,
        )
    return flow.outcome(
        Status.CALIBRATED, plans, record={"current": current, "history": list(history)}
    )


async def calibrate_slope(
    writer: SafeWriter,
    operator: Operator,
    *,
    reference: float,
    when: datetime,
    cell_current_na: float | None = None,
    zero_na: float | None = None,
    samples: int = 1,
    sample_interval_s: float = 1.0,
) -> CalibrationOutcome:
    """Slope calibration from a reference concentration (tecLine annex 7.3, Reiss 5.2).

    ``reference`` is the analysed concentration in the unit of 0x0200. The cell current is
    ``cell_current_na`` if the operator noted it when the sample was taken (annex 7.3.1
    step 3), else read now (``samples`` readings, averaged). The zero point is ``zero_na``,
    else the X_Zero the sensor holds (0, or the value of a zero-point calibration, 7.3.2).
    """
    flow = _Flow(writer, operator, "slope")
    flow.require(AMPEROMETRIC_POINTS | {"concentration", "history_0_x_zero"}, "slope calibration")
    state = await _read_cell(flow)
    current = await _cell_current(flow, cell_current_na, samples, sample_interval_s)
    if zero_na is None:
        zero_na = state.current.x_zero
        flow.say(StepKind.COMPUTE, f"zero point X_Zero {zero_na:.6g} nA, as the sensor holds it")
    slope = slope_from(current, reference, zero_na=zero_na)
    flow.say(
        StepKind.COMPUTE,
        f"slope X_Span = ({current:.6g} - {zero_na:.6g}) nA / {reference:.6g} {state.unit_text}"
        f" = {slope:.6g} nA/{state.unit_text}",
    )
    flow.values.update(
        reference=reference, cell_current_na=current, x_zero_na=zero_na, x_span=slope
    )
    _judge(flow, slope, state)
    new = HistoryEntry(x_zero=zero_na, x_span=slope, stamp=calibration_stamp(when))
    outcome = await _activate_and_verify(
        flow,
        state,
        new,
        order=("x_zero", "x_span"),
        why={"x_zero": "zero point (annex 7.3.2 step 1)", "x_span": "slope (7.3.2 step 2)"},
    )
    if outcome.status is Status.CALIBRATED:
        await _chemical_check(flow, reference, state.unit_text)
        outcome = flow.outcome(Status.CALIBRATED, outcome.writes, outcome.record)
    return outcome


async def calibrate_zero_point(
    writer: SafeWriter,
    operator: Operator,
    *,
    when: datetime,
    zero_current_na: float | None = None,
    samples: int = 1,
    sample_interval_s: float = 1.0,
) -> CalibrationOutcome:
    """Zero-point calibration (tecLine annex 7.4): X_Zero = the current without disinfectant.

    The sensor must be in a disinfectant-free medium; the current is ``zero_current_na`` if
    noted, else read now. X_Span stays as the sensor holds it and the date stamp activates
    the new zero point. The annex then asks for a slope calibration (7.4 step 4), which
    subtracts this zero point: run it next, at least a minute later (annex 7.2 note).
    """
    flow = _Flow(writer, operator, "zero_point")
    flow.require(AMPEROMETRIC_POINTS | {"concentration", "history_0_x_zero"}, "zero point")
    flow.say(
        StepKind.NOTE,
        "JUMO: a zero-point calibration is generally not required (annex 7.4); the sensor "
        "must be in a completely disinfectant-free medium",
    )
    state = await _read_cell(flow)
    zero = await _cell_current(flow, zero_current_na, samples, sample_interval_s)
    flow.say(StepKind.COMPUTE, f"zero point X_Zero = {zero:.6g} nA; X_Span stays")
    flow.values.update(x_zero_na=zero, x_span=state.current.x_span)
    new = HistoryEntry(x_zero=zero, x_span=state.current.x_span, stamp=calibration_stamp(when))
    outcome = await _activate_and_verify(
        flow,
        state,
        new,
        order=("x_zero", "x_span"),
        why={
            "x_zero": "zero point without disinfectant (annex 7.4)",
            "x_span": "the slope the sensor holds, unchanged",
        },
    )
    if outcome.status is Status.CALIBRATED:
        flow.say(
            StepKind.NOTE,
            "next: a slope calibration (annex 7.4 step 4) with disinfectant present",
        )
    return outcome


async def restore_nominal_slope(
    writer: SafeWriter, operator: Operator, *, when: datetime
) -> CalibrationOutcome:
    """Restore the nominal slope (tecLine annex 7.5, Reiss 5.3): X_Span = 0x030A, X_Zero = 0.

    Written in the annex's order: X_Span (step 2), X_Zero (step 3), the stamp (step 4).
    The nominal slope is in nA/ppm; for another unit at 0x0200 it is converted.
    """
    flow = _Flow(writer, operator, "nominal_slope")
    flow.require(AMPEROMETRIC_POINTS | {"history_0_x_zero", "concentration"}, "nominal slope")
    state = await _read_cell(flow)
    nominal = nominal_in_unit(state.nominal, state.unit)
    if not math.isfinite(nominal) or nominal <= 0:
        raise CommandRejectedError(
            f"the nominal slope {state.nominal:g} nA/ppm (0x030A) cannot be written",
            point="nominal_slope",
        )
    if nominal != state.nominal:
        flow.say(
            StepKind.COMPUTE,
            f"nominal slope {state.nominal:.6g} nA/ppm = {nominal:.6g} nA/{state.unit_text}",
        )
    flow.values.update(x_zero_na=0.0, x_span=nominal)
    new = HistoryEntry(x_zero=0.0, x_span=nominal, stamp=calibration_stamp(when))
    outcome = await _activate_and_verify(
        flow,
        state,
        new,
        order=("x_span", "x_zero"),
        why={
            "x_span": "nominal slope from 0x030A (annex 7.5.1 step 2)",
            "x_zero": "standard zero point (7.5.1 step 3)",
        },
    )
    if outcome.status is Status.CALIBRATED:
        after = await flow.read("concentration")
        flow.values["concentration_after"] = after["concentration"]
        flow.say(
            StepKind.READ,
            f"concentration now {_show(after['concentration'])} {state.unit_text}",
        )
    return outcome


async def check_slope(
    writer: SafeWriter,
    operator: Operator,
    *,
    reference: float,
    cell_current_na: float | None = None,
    samples: int = 1,
    sample_interval_s: float = 1.0,
) -> CalibrationOutcome:
    """The regular check (tecLine annex 7.3.4): today's slope against nominal; no writes."""
    flow = _Flow(writer, operator, "check")
    flow.require(AMPEROMETRIC_POINTS | {"concentration", "history_0_x_zero"}, "slope check")
    state = await _read_cell(flow)
    current = await _cell_current(flow, cell_current_na, samples, sample_interval_s)
    slope = slope_from(current, reference, zero_na=state.current.x_zero)
    in_use = state.current.x_span
    change = f" ({slope / in_use - 1:+.1%})" if in_use > 0 else ""
    flow.say(
        StepKind.COMPUTE,
        f"slope now ({current:.6g} - {state.current.x_zero:.6g}) nA / {reference:.6g} "
        f"{state.unit_text} = {slope:.6g} nA/{state.unit_text}; the sensor uses "
        f"{in_use:.6g}{change}",
    )
    flow.values.update(
        reference=reference,
        cell_current_na=current,
        x_zero_na=state.current.x_zero,
        slope_now=slope,
        x_span=state.current.x_span,
    )
    _judge(flow, slope, state)
    await _chemical_check(flow, reference, state.unit_text)
    return flow.outcome(Status.CHECKED)


async def _cell_current(
    flow: _Flow, noted_na: float | None, samples: int, interval_s: float
) -> float:
    if noted_na is not None:
        flow.say(StepKind.READ, f"cell current {noted_na:.6g} nA, as noted by the operator")
        return noted_na
    return await flow.sample("cell_current", samples=samples, interval_s=interval_s, unit="nA")


def _judge(flow: _Flow, slope: float, state: _CellState) -> None:
    """Annex 7.3.4: a slope below 30 % of nominal calls for maintenance."""
    judgement = judge_slope(slope, state.nominal, state.unit)
    flow.values["slope_fraction_of_nominal"] = judgement.fraction
    text = (
        f"slope {slope:.6g} nA/{state.unit_text} is {judgement.fraction:.0%} of the nominal "
        f"{judgement.nominal:.6g} nA/{state.unit_text}"
    )
    if judgement.low:
        flow.warn(
            f"{text}: below {SLOPE_WARNING_FRACTION:.0%}, follow the maintenance instructions "
            "in the sensor's operating manual (annex 7.3.4)"
        )
    else:
        flow.say(StepKind.COMPUTE, text)


async def _chemical_check(flow: _Flow, reference: float, unit_text: str) -> None:
    """Annex 7.3.3 "chemical check": the sensor's reading against the analysed value."""
    after = await flow.read("concentration")
    reading = after["concentration"]
    flow.values["concentration_after"] = reading
    if isinstance(reading, bool) or not isinstance(reading, int | float):
        flow.warn(f"the concentration reads {_show(reading)}: no chemical check")
        return
    deviation = reading / reference - 1
    flow.values["concentration_deviation"] = deviation
    text = (
        f"concentration now {reading:.6g} {unit_text} against the reference {reference:.6g} "
        f"{unit_text} ({deviation:+.1%})"
    )
    if abs(deviation) > CHEMICAL_CHECK_TOLERANCE:
        flow.warn(
            f"{text}: not broadly identical (annex 7.3.3); was the concentration stable "
            "while the sample was taken?"
        )
    else:
        flow.say(StepKind.READ, text)


# --- digiLine O-DO H10 / H20 -----------------------------------------------------------------

_OXYGEN_SOURCE: Final = "H10/H20 manual 6.2.4"
_LOGBOOK_SOURCE: Final = "H10/H20 manual 6.1.6 / 6.2.4"
_TRIGGER_INTERRUPTED: Final = (
    "Calibration mode and date are volatile (not in flash). If the trigger was sent, the "
    "sensor may have calibrated: read logbook entry 1 before repeating."
)


def logbook_date(when: datetime) -> datetime:
    """The H10/H20 calibration date (0x300A-0x3010): to the second, with its UTC offset.

    A naive ``when`` is taken as local time.
    """
    aware = when if when.tzinfo is not None else when.astimezone()
    return aware.replace(microsecond=0)


def _logbook_points(profile: Profile) -> tuple[str, ...]:
    return tuple(p.name for p in profile.points if p.name.startswith(_LOGBOOK_NEWEST))


def _logbook_entry(values: Mapping[str, codec.Decoded]) -> dict[str, codec.Decoded]:
    return {
        name.removeprefix(_LOGBOOK_NEWEST): value
        for name, value in values.items()
        if name.startswith(_LOGBOOK_NEWEST)
    }


def _label(value: codec.Decoded) -> str:
    return value.label if isinstance(value, codec.EnumValue) else _show(value)


def _show_logbook(flow: _Flow, title: str, entry: Mapping[str, codec.Decoded]) -> None:
    measured = ("phase", "temperature", "calibration_mode", "oxygen", "pressure", "value_6")
    head = (
        f"{title}: {_label(entry.get('entry_type'))}, {_label(entry.get('manual_change'))}, "
        f"rating {_label(entry.get('rating'))}, date {_show(entry.get('date'))}"
    )
    parts = []
    for name in measured:
        if name in entry:
            unit = entry.get(f"{name}_unit")
            parts.append(f"{name} {_show(entry[name])}{f' {unit}' if unit else ''}")
    flow.say(StepKind.READ, f"{head}; {', '.join(parts)}")


async def _read_oxygen(flow: _Flow, extra: Sequence[str]) -> dict[str, codec.Decoded]:
    values = await flow.read(
        "oxygen",
        "oxygen_unit",
        "temperature",
        "phase_shift",
        "measurement_mode",
        "measurement_status",
        "calibration_mode",
        *extra,
    )
    unit = values["oxygen_unit"]
    unit_text = (
        flow.profile.point("oxygen_unit").enum_units.get(unit.code, unit.label)
        if isinstance(unit, codec.EnumValue)
        else ""
    )
    flow.say(
        StepKind.READ,
        f"oxygen {_show(values['oxygen'])} {unit_text}, temperature "
        f"{_show(values['temperature'])} °C, phase shift {_show(values['phase_shift'])}°, "
        f"measurement mode {_label(values['measurement_mode'])}, calibration mode 0x3009 "
        f"{_label(values['calibration_mode'])}",
    )
    for name in extra:
        flow.say(StepKind.READ, f"{name} {_show(values[name])}")
    status = values["measurement_status"]
    if isinstance(status, codec.BitfieldValue) and "continuous_measurement" not in status.active:
        flow.warn(
            "continuous measurement is off (0x3001 bit 0): the sensor calibrates with its "
            "last measured values (6.2.4), which may be old; trigger a measurement first"
        )
    logbook = _logbook_entry(await flow.read(*_logbook_points(flow.profile)))
    _show_logbook(flow, "logbook entry 1 (newest) before", logbook)
    flow.values["before"] = {**values, "logbook_1": logbook}
    return {**values, **{_LOGBOOK_NEWEST + k: v for k, v in logbook.items()}}


async def _trigger_and_verify(
    flow: _Flow,
    plans: list[PlannedWrite],
    *,
    entry_type: str,
    date: datetime,
    compare: Mapping[str, str],
    extra_checks: Sequence[tuple[str, str, float]] = (),
) -> CalibrationOutcome:
    """Confirm, write, then check the new logbook entry and the updated registers.

    ``compare`` maps calibration registers (203F ...) to the logbook value the same
    measurement went into; ``extra_checks`` are (name, point, expected value) after writing.
    """
    flow.preflight(plans)
    if not flow.confirm(plans):
        return flow.outcome(Status.DECLINED)
    await flow.write(plans, if_interrupted=_TRIGGER_INTERRUPTED)

    after = await flow.read("calibration_mode", *compare, *(p for _, p, _ in extra_checks))
    entry = _logbook_entry(await flow.read(*_logbook_points(flow.profile)))
    _show_logbook(flow, "logbook entry 1 (newest) after", entry)
    kind = entry.get("entry_type")
    flow.check(
        "new logbook entry type",
        expected=entry_type,
        actual=_label(kind),
        ok=isinstance(kind, codec.EnumValue) and kind.label == entry_type,
        source=_LOGBOOK_SOURCE,
    )
    flow.check(
        "new logbook entry date (0x300A-0x3010)",
        expected=date,
        actual=entry.get("date"),
        ok=entry.get("date") == date,
        source=_LOGBOOK_SOURCE,
    )
    for register, logged in compare.items():
        value, in_log = after[register], entry.get(logged)
        flow.check(
            f"{register} = logbook {logged}",
            expected=in_log,
            actual=value,
            ok=isinstance(value, float)
            and isinstance(in_log, float)
            and _close(value, in_log, _SAME_MEASUREMENT_REL_TOL),
            source=_OXYGEN_SOURCE,
        )
    for name, point, expected in extra_checks:
        value = after[point]
        flow.check(
            name,
            expected=expected,
            actual=value,
            ok=isinstance(value, float) and _close(value, expected),
            source=_OXYGEN_SOURCE,
        )
    mode = after["calibration_mode"]
    flow.check(
        "calibration mode 0x3009 reset",
        expected="as_configured",
        actual=_label(mode),
        ok=isinstance(mode, codec.EnumValue) and mode.code == 0,
        source=f"{_OXYGEN_SOURCE} (0x3009 is set to 0 by 0x3003/0x3005)",
    )
    rating = entry.get("rating")
    if isinstance(rating, codec.EnumValue) and rating.label not in {"ok", "none"}:
        flow.warn(f"the sensor rates the calibration {rating.label!r} (logbook 6.1.6)")
    return flow.outcome(Status.CALIBRATED, plans, record=entry)


async def _mode_and_date(
    flow: _Flow, mode: str, date: datetime
) -> tuple[PlannedWrite, PlannedWrite]:
    return (
        await flow.plan("calibration_mode", mode, "0x3009, volatile"),
        await flow.plan(
            "calibration_date", date, "0x300A-0x3010, volatile; goes into the logbook entry"
        ),
    )


async def calibrate_oxygen_zero(
    writer: SafeWriter,
    operator: Operator,
    *,
    when: datetime,
    mode: str = "as_configured",
) -> CalibrationOutcome:
    """H10/H20 zero-point calibration (6.2.4): mode, date, then any value to 0x3003.

    The sensor takes its last measured phase and temperature into 0x203F/0x2041 and logs
    an entry of type 20; the 650 ms wait after 0x3003 is kept by the bus engine.
    """
    flow = _Flow(writer, operator, "oxygen_zero")
    flow.require(OPTICAL_OXYGEN_POINTS | {"zero_point_phase"}, "oxygen zero-point calibration")
    flow.say(StepKind.NOTE, "the sensor must be in an oxygen-free medium, its reading settled")
    await _read_oxygen(flow, ("zero_point_phase", "zero_point_temperature"))
    date = logbook_date(when)
    flow.values.update(mode=mode, date=date)
    plans = [
        *await _mode_and_date(flow, mode, date),
        await flow.plan(
            "zero_point_calibration_trigger", 0.0, "any value starts it; 650 ms wait after"
        ),
    ]
    return await _trigger_and_verify(
        flow,
        plans,
        entry_type="zero_point",
        date=date,
        compare={"zero_point_phase": "phase", "zero_point_temperature": "temperature"},
    )


async def calibrate_oxygen_end_value(
    writer: SafeWriter,
    operator: Operator,
    *,
    reference: float,
    when: datetime,
    unit: str | None = None,
    mode: str = "as_configured",
) -> CalibrationOutcome:
    """H10/H20 end-value calibration (6.2.4) to ``reference`` in ``unit`` (0x204B).

    Writes the unit if it changes, the reference to 0x2043, mode and date, then the
    reference to 0x3005 too. The manual says 0x3005 starts it but also that writing
    0x2043 does; writing both covers either reading (see the profile's note).
    """
    flow = _Flow(writer, operator, "oxygen_end_value")
    flow.require(OPTICAL_OXYGEN_POINTS | {"end_value_oxygen_unit"}, "end-value calibration")
    flow.say(StepKind.NOTE, "the sensor must be in the reference medium, its reading settled")
    before = await _read_oxygen(
        flow,
        (
            "end_value_oxygen",
            "end_value_oxygen_unit",
            "end_value_phase",
            "end_value_temperature",
            "end_value_pressure",
            "pressure",
        ),
    )
    held = before["end_value_oxygen_unit"]
    plans: list[PlannedWrite] = []
    if unit is None:
        if not isinstance(held, codec.EnumValue) or not held.known:
            raise CommandRejectedError(
                f"the end-value unit 0x204B holds {_show(held)}, not a known unit: give the "
                "reference's unit",
                point="end_value_oxygen_unit",
            )
        unit = held.label
    elif not isinstance(held, codec.EnumValue) or held.label != unit:
        plans.append(
            await flow.plan("end_value_oxygen_unit", unit, "unit of the reference; 650 ms wait")
        )
    unit_point = flow.profile.point("end_value_oxygen_unit")
    codes = {label: code for code, label in unit_point.format.enum.items()}
    unit_text = unit_point.enum_units.get(codes.get(unit, -1), unit)
    date = logbook_date(when)
    flow.values.update(reference=reference, unit=unit_text, mode=mode, date=date)
    flow.say(StepKind.COMPUTE, f"end value {reference:.6g} {unit_text}")
    plans.append(
        await flow.plan("end_value_oxygen", reference, "the reference (0x2043); 650 ms wait")
    )
    plans.extend(await _mode_and_date(flow, mode, date))
    plans.append(
        await flow.plan("end_value_calibration_trigger", reference, "starts it; 650 ms wait after")
    )
    return await _trigger_and_verify(
        flow,
        plans,
        entry_type="end_value",
        date=date,
        compare={
            "end_value_phase": "phase",
            "end_value_temperature": "temperature",
            "end_value_pressure": "pressure",
        },
        extra_checks=(
            ("end value 0x2043 = reference", "end_value_oxygen", reference),
            ("logbook oxygen = reference", _LOGBOOK_NEWEST + "oxygen", reference),
        ),
    )
