"""What every calibration flow shares: its steps, its planned writes, and :class:`Flow`.

A flow reads, plans, checks the flash budget, asks the :class:`Operator`, writes and
checks, so that each procedure reads as the manual's list of steps.
"""

from __future__ import annotations

import asyncio
import inspect
import statistics
from dataclasses import dataclass, field
from datetime import datetime
from enum import StrEnum
from typing import TYPE_CHECKING, Final, Protocol

from gateway.config import FlashPolicy
from gateway.control.calibration.arithmetic import HistoryEntry
from gateway.control.clock_trust import require_trusted_for
from gateway.control.commands import function_for, writable_point
from gateway.control.flash import Action, check_flash_write, utc_today
from gateway.errors import CalibrationInterruptedError, CommandRejectedError, GatewayError
from gateway.line.samples import json_value
from gateway.profiles.model import Storage
from gateway.wire import codec

if TYPE_CHECKING:
    from collections.abc import Awaitable, Iterable, Mapping, Sequence

    from gateway.control.link import DeviceLink
    from gateway.control.writes import SafeWriter
    from gateway.profiles import Profile
    from gateway.profiles.model import Point

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
    """Whoever runs a calibration: sees each step and confirms before anything is written.

    A terminal answers at once (``bool``); a browser answers later, so ``confirm`` may
    return an awaitable of the answer, which the flow waits for.
    """

    def show(self, step: Step) -> None:
        """Show one step as it happens."""

    def confirm(self, question: str) -> bool | Awaitable[bool]:
        """Ask before writing; ``False`` stops the flow with nothing written.

        The question's first line says in plain words what changes (for an operator at
        the basin); the lines after it are the register detail.
        """


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
            f"0x{self.address:04X} {self.point} = {show(self.value)} "
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


# What the operator calls the registers a calibration writes (the question's plain words).
PLAIN_NAMES: Final = {  # in the order the question names them
    "x_span": "slope",
    "x_zero": "zero point",
    "end_value_oxygen": "end value",
    "end_value_oxygen_unit": "unit",
    "calibration_mode": "calibration mode",
    "calibration_stamp": "calibration date",
    "calibration_date": "calibration date",
    "zero_point_calibration_trigger": "then the sensor's zero-point calibration",
    "end_value_calibration_trigger": "then the sensor's end-value calibration",
}


def _plain(value: object, point: Point, unit: object) -> str:
    """A value with its unit as an operator reads it ("6.3 nA/ppm", "2026-11-25 17:10")."""
    if isinstance(value, datetime):
        return f"{value:%Y-%m-%d %H:%M}"
    if isinstance(value, codec.EnumValue):
        return value.label
    text = f"{value:.4g}" if isinstance(value, float) else str(value)
    point_unit = point.unit or ""
    if isinstance(unit, str) and unit:
        point_unit = point_unit.replace("/unit", f"/{unit}")
    return f"{text} {point_unit}".strip()


def show(value: object) -> str:
    """A value as a step shows it."""
    if isinstance(value, float):
        return f"{value:.6g}"
    if isinstance(value, datetime):
        return value.isoformat(sep=" ")
    if isinstance(value, codec.Fault):
        return f"!{value.name}"
    return str(value)


# --- the flow machinery ----------------------------------------------------------------------


class Flow:
    """The shared steps of every procedure: read, say, plan, confirm, write, check."""

    def __init__(self, writer: SafeWriter, operator: Operator, procedure: str) -> None:
        """A ``procedure`` on ``writer``'s device, told to ``operator``."""
        self.writer = writer
        self.link: DeviceLink = writer.link
        self.profile: Profile = writer.link.profile
        self.operator = operator
        self.procedure = procedure
        self.values: dict[str, object] = {}
        self.seen: dict[str, codec.Decoded] = {}  # every point read, as last read: "was"
        self.warnings: list[str] = []
        self.checks: list[Check] = []

    def say(self, kind: StepKind, text: str) -> None:
        """Tell the operator one step."""
        self.operator.show(Step(kind, text))

    def warn(self, text: str) -> None:
        """Keep a warning for the outcome."""
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
        """Read points of the device now (kept in :attr:`seen`, for the question's "was")."""
        values = await self.link.read(*points)
        self.seen.update(values)
        return values

    def number(self, values: Mapping[str, codec.Decoded], point: str) -> float:
        """A read value that must be a number to go on; a fault refuses the calibration."""
        value = values[point]
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise CommandRejectedError(
                f"{point} reads {show(value)}, not a number: cannot calibrate", point=point
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
        """Refuse the whole flow if any write would be refused, so none is half-done.

        :class:`SafeWriter` checks each write again; this only keeps a flow from stopping
        after its first writes because a later point's budget is spent, or because the
        date stamp that comes last may not be written while the host clock is not trusted
        (X_Zero and X_Span would be written and never activated).
        """
        policy = self.writer.policy
        today = utc_today()
        for planned in plans:
            require_trusted_for(
                self.writer.clock,
                self.profile,
                planned.target,
                f"the {self.procedure} calibration of {self.link.device}",
            )
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

    def summary(self, plans: Sequence[PlannedWrite]) -> str:
        """What the planned writes change, in plain words, on one line.

        For the operator who must say yes: "New slope 6.3 nA/ppm (was 7.5 nA/ppm); zero
        point 0 nA (unchanged); ... written to the sensor's memory (flash write 1 of 4
        allowed today)." The register words stay in the steps and the second line.
        """
        unit = self.values.get("unit")
        parts = []
        order = list(PLAIN_NAMES)
        for planned in sorted(
            plans, key=lambda p: order.index(p.point) if p.point in order else len(order)
        ):
            name = PLAIN_NAMES.get(planned.point, planned.point.replace("_", " "))
            if planned.point.endswith("_trigger"):  # its value only starts it
                parts.append(name)
                continue
            text = f"{name} {_plain(planned.value, planned.target, unit)}"
            before = self.seen.get(planned.point)
            if before is not None and not isinstance(before, codec.Fault):
                was = _plain(before, planned.target, unit)
                same = was == _plain(planned.value, planned.target, unit)
                text += " (unchanged)" if same else f" (was {was})"
            parts.append(text)
        line = "New " + "; ".join(parts) if parts else "Nothing to write"
        line = line.replace("New then", "Then")
        flash = [p for p in plans if p.flash]
        if flash:
            today = utc_today()
            done = max(
                self.writer.ledger.count_today(self.link.device, p.point, today) for p in flash
            )
            budget = self.writer.policy.daily_budget
            line += (
                f"; written to the sensor's memory (flash write {done + 1} of {budget} "
                "allowed today)"
            )
        else:
            line += "; nothing goes to the sensor's flash memory"
        return line + "."

    async def confirm(self, plans: Sequence[PlannedWrite]) -> bool:
        """Ask the operator to confirm the planned writes; whether they did."""
        flash = sum(p.flash for p in plans)
        question = (
            f"{self.summary(plans)}\n"
            f"Write {len(plans)} register block(s) to {self.link.device} "
            f"({flash} to flash/EEPROM, counted against the daily budget)?"
        )
        answer = self.operator.confirm(question)
        if inspect.isawaitable(answer):
            answer = await answer
        if answer:
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
        """Record one verification of the result, with its source in the manual."""
        self.checks.append(Check(name=name, expected=expected, actual=actual, ok=ok, source=source))
        verdict = "as expected" if ok else f"expected {show(expected)}"
        self.say(
            StepKind.VERIFIED if ok else StepKind.MISMATCH,
            f"{name}: {show(actual)} ({verdict}; {source})",
        )

    def outcome(
        self,
        status: Status,
        writes: Sequence[PlannedWrite] = (),
        record: Mapping[str, object] | None = None,
    ) -> CalibrationOutcome:
        """The flow's outcome; a calibration with a failed check is not calibrated."""
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
