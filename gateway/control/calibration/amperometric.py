"""Calibrating tecLine and Reiss amperometric cells (tecLine annex 7, Reiss chapter 5).

The master computes the calibration and writes it: X_Zero (0x0206), X_Span (0x0208), then
the date stamp (0x020A), whose write activates it and moves the five-entry history.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from datetime import datetime
from typing import TYPE_CHECKING, Final

from gateway.control.calibration.arithmetic import (
    CELL_CURRENT_READINGS,
    CELL_PROCEDURE_POINTS,
    CHEMICAL_CHECK_TOLERANCE,
    READING_INTERVAL_S,
    HistoryEffect,
    HistoryEntry,
    calibration_stamp,
    expected_history,
    history_effect,
    judge_slope,
    nominal_in_unit,
    slope_from,
    stamp_number,
)
from gateway.control.calibration.steps import (
    CalibrationOutcome,
    Flow,
    Operator,
    Status,
    StepKind,
    show,
)
from gateway.errors import CommandRejectedError
from gateway.wire import codec

if TYPE_CHECKING:
    from collections.abc import Mapping, Sequence

    from gateway.control.writes import SafeWriter
    from gateway.profiles import Ring, Slope

# --- tecLine / Reiss -------------------------------------------------------------------------

_HISTORY_PARTS: Final = ("x_zero", "x_span", "stamp")  # of each entry, as the profile names them
_AMPEROMETRIC_SOURCE: Final = "tecLine annex 7.3.3 / Reiss 5.2.3"
_HISTORY_SOURCE: Final = "tecLine annex 7.2 / Reiss 5.1"
_NOT_ACTIVE: Final = (
    "The date stamp activates a calibration, so the one in use may still be the old one: "
    "read X_Zero, X_Span and history entry 0 and repeat the calibration."
)


def _ring(flow: Flow) -> Ring:
    """The cell's calibration history, as its profile declares it (annex 7.2's five entries)."""
    ring = flow.profile.ring("history")
    if ring is None:
        msg = f"profile {flow.profile.id} declares no calibration history"
        raise CommandRejectedError(msg)
    return ring


def _history(ring: Ring, values: Mapping[str, codec.Decoded]) -> tuple[HistoryEntry, ...]:
    entries = []
    for number in ring.numbers:
        zero, span, stamp = (values[ring.point(number, part)] for part in _HISTORY_PARTS)
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


async def _read_cell(flow: Flow) -> _CellState:
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
    ring = _ring(flow)
    history = _history(ring, await flow.read(*ring.points(*_HISTORY_PARTS)))
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
        f"concentration {show(state.concentration)} {unit_text} (unit 0x0200: {unit_text}), "
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


def _announce_stamp(flow: Flow, state: _CellState, stamp: datetime) -> HistoryEffect:
    last = state.history[0].stamp
    effect = history_effect(stamp, last)
    number = stamp_number(stamp)
    flow.values.update(stamp=stamp, stamp_number=number, history_effect=effect)
    if effect is HistoryEffect.PUSH:
        dropped = state.history[-1]
        flow.say(
            StepKind.COMPUTE,
            f"date stamp {number}: later than history entry 0, so the history moves down one "
            f"place and entry {len(state.history) - 1} ({dropped}) is dropped (annex 7.2)",
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
    flow: Flow,
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
    if not await flow.confirm(plans):
        return flow.outcome(Status.DECLINED)
    await flow.write(plans, if_interrupted=_NOT_ACTIVE)

    ring = _ring(flow)
    after = await flow.read("x_zero", "x_span", "calibration_stamp", *ring.points(*_HISTORY_PARTS))
    history = _history(ring, after)
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
    for i in range(1, len(history)):
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
    samples: int = CELL_CURRENT_READINGS,
    sample_interval_s: float = READING_INTERVAL_S,
) -> CalibrationOutcome:
    """Slope calibration from a reference concentration (tecLine annex 7.3, Reiss 5.2).

    ``reference`` is the analysed concentration in the unit of 0x0200. The cell current is
    ``cell_current_na`` if the operator noted it when the sample was taken (annex 7.3.1
    step 3), else read now (``samples`` readings, averaged). The zero point is ``zero_na``,
    else the X_Zero the sensor holds (0, or the value of a zero-point calibration, 7.3.2).
    """
    flow = Flow(writer, operator, "slope")
    flow.require(CELL_PROCEDURE_POINTS, "slope calibration")
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
    samples: int = CELL_CURRENT_READINGS,
    sample_interval_s: float = READING_INTERVAL_S,
) -> CalibrationOutcome:
    """Zero-point calibration (tecLine annex 7.4): X_Zero = the current without disinfectant.

    The sensor must be in a disinfectant-free medium; the current is ``zero_current_na`` if
    noted, else read now. X_Span stays as the sensor holds it and the date stamp activates
    the new zero point. The annex then asks for a slope calibration (7.4 step 4), which
    subtracts this zero point: run it next, at least a minute later (annex 7.2 note).
    """
    flow = Flow(writer, operator, "zero_point")
    flow.require(CELL_PROCEDURE_POINTS, "zero point")
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
    flow = Flow(writer, operator, "nominal_slope")
    flow.require(CELL_PROCEDURE_POINTS, "nominal slope")
    state = await _read_cell(flow)
    nominal = nominal_in_unit(state.nominal, state.unit, _slope_facts(flow))
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
            f"concentration now {show(after['concentration'])} {state.unit_text}",
        )
    return outcome


async def check_slope(
    writer: SafeWriter,
    operator: Operator,
    *,
    reference: float,
    cell_current_na: float | None = None,
    samples: int = CELL_CURRENT_READINGS,
    sample_interval_s: float = READING_INTERVAL_S,
) -> CalibrationOutcome:
    """The regular check (tecLine annex 7.3.4): today's slope against nominal; no writes."""
    flow = Flow(writer, operator, "check")
    flow.require(CELL_PROCEDURE_POINTS, "slope check")
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
    flow: Flow, noted_na: float | None, samples: int, interval_s: float
) -> float:
    if noted_na is not None:
        flow.say(StepKind.READ, f"cell current {noted_na:.6g} nA, as noted by the operator")
        return noted_na
    return await flow.sample("cell_current", samples=samples, interval_s=interval_s, unit="nA")


def _slope_facts(flow: Flow) -> Slope:
    """The cell's slope limit and units, as its profile gives them."""
    facts = flow.profile.slope
    if facts is None:
        msg = f"profile {flow.profile.id} gives no slope limit or units"
        raise CommandRejectedError(msg)
    return facts


def _judge(flow: Flow, slope: float, state: _CellState) -> None:
    """Annex 7.3.4: a slope below 30 % of nominal calls for maintenance."""
    judgement = judge_slope(slope, state.nominal, state.unit, _slope_facts(flow))
    flow.values["slope_fraction_of_nominal"] = judgement.fraction
    text = (
        f"slope {slope:.6g} nA/{state.unit_text} is {judgement.fraction:.0%} of the nominal "
        f"{judgement.nominal:.6g} nA/{state.unit_text}"
    )
    if judgement.low:
        flow.warn(
            f"{text}: below {judgement.limit:.0%}, follow the maintenance instructions "
            "in the sensor's operating manual (annex 7.3.4)"
        )
    else:
        flow.say(StepKind.COMPUTE, text)


async def _chemical_check(flow: Flow, reference: float, unit_text: str) -> None:
    """Annex 7.3.3 "chemical check": the sensor's reading against the analysed value."""
    after = await flow.read("concentration")
    reading = after["concentration"]
    flow.values["concentration_after"] = reading
    if isinstance(reading, bool) or not isinstance(reading, int | float):
        flow.warn(f"the concentration reads {show(reading)}: no chemical check")
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
