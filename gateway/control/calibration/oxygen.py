"""Calibrating digiLine O-DO H10/H20 oxygen sensors (manual 6.2.4).

The sensor calibrates itself with its last measured values when a trigger is written, after
the calibration mode and date are set, and logs a new logbook entry.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Final

from gateway.control.calibration.arithmetic import (
    CALIBRATION_MODE_DEFAULT,
    LOGBOOK_NEWEST,
    OXYGEN_END_VALUE_POINTS,
    OXYGEN_ZERO_POINTS,
    SAME_MEASUREMENT_REL_TOL,
    close_to,
)
from gateway.control.calibration.steps import (
    CalibrationOutcome,
    Flow,
    Operator,
    PlannedWrite,
    Status,
    StepKind,
    show,
)
from gateway.errors import CommandRejectedError
from gateway.wire import codec

if TYPE_CHECKING:
    from collections.abc import Mapping, Sequence
    from datetime import datetime

    from gateway.control.writes import SafeWriter
    from gateway.profiles import Profile

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
    return tuple(p.name for p in profile.points if p.name.startswith(LOGBOOK_NEWEST))


def _logbook_entry(values: Mapping[str, codec.Decoded]) -> dict[str, codec.Decoded]:
    return {
        name.removeprefix(LOGBOOK_NEWEST): value
        for name, value in values.items()
        if name.startswith(LOGBOOK_NEWEST)
    }


def _label(value: codec.Decoded) -> str:
    return value.label if isinstance(value, codec.EnumValue) else show(value)


def _show_logbook(flow: Flow, title: str, entry: Mapping[str, codec.Decoded]) -> None:
    measured = ("phase", "temperature", "calibration_mode", "oxygen", "pressure", "value_6")
    head = (
        f"{title}: {_label(entry.get('entry_type'))}, {_label(entry.get('manual_change'))}, "
        f"rating {_label(entry.get('rating'))}, date {show(entry.get('date'))}"
    )
    parts = []
    for name in measured:
        if name in entry:
            unit = entry.get(f"{name}_unit")
            parts.append(f"{name} {show(entry[name])}{f' {unit}' if unit else ''}")
    flow.say(StepKind.READ, f"{head}; {', '.join(parts)}")


async def _read_oxygen(flow: Flow, extra: Sequence[str]) -> dict[str, codec.Decoded]:
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
        f"oxygen {show(values['oxygen'])} {unit_text}, temperature "
        f"{show(values['temperature'])} °C, phase shift {show(values['phase_shift'])}°, "
        f"measurement mode {_label(values['measurement_mode'])}, calibration mode 0x3009 "
        f"{_label(values['calibration_mode'])}",
    )
    for name in extra:
        flow.say(StepKind.READ, f"{name} {show(values[name])}")
    status = values["measurement_status"]
    if isinstance(status, codec.BitfieldValue) and "continuous_measurement" not in status.active:
        flow.warn(
            "continuous measurement is off (0x3001 bit 0): the sensor calibrates with its "
            "last measured values (6.2.4), which may be old; trigger a measurement first"
        )
    logbook = _logbook_entry(await flow.read(*_logbook_points(flow.profile)))
    _show_logbook(flow, "logbook entry 1 (newest) before", logbook)
    flow.values["before"] = {**values, "logbook_1": logbook}
    return {**values, **{LOGBOOK_NEWEST + k: v for k, v in logbook.items()}}


async def _trigger_and_verify(
    flow: Flow,
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
    if not await flow.confirm(plans):
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
            and close_to(value, in_log, SAME_MEASUREMENT_REL_TOL),
            source=_OXYGEN_SOURCE,
        )
    for name, point, expected in extra_checks:
        value = after[point]
        flow.check(
            name,
            expected=expected,
            actual=value,
            ok=isinstance(value, float) and close_to(value, expected),
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
    flow: Flow, mode: str, date: datetime
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
    mode: str = CALIBRATION_MODE_DEFAULT,
) -> CalibrationOutcome:
    """H10/H20 zero-point calibration (6.2.4): mode, date, then any value to 0x3003.

    The sensor takes its last measured phase and temperature into 0x203F/0x2041 and logs
    an entry of type 20; the 650 ms wait after 0x3003 is kept by the bus engine.
    """
    flow = Flow(writer, operator, "oxygen_zero")
    flow.require(OXYGEN_ZERO_POINTS, "oxygen zero-point calibration")
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
    mode: str = CALIBRATION_MODE_DEFAULT,
) -> CalibrationOutcome:
    """H10/H20 end-value calibration (6.2.4) to ``reference`` in ``unit`` (0x204B).

    Writes the unit if it changes, the reference to 0x2043, mode and date, then the
    reference to 0x3005 too. The manual says 0x3005 starts it but also that writing
    0x2043 does; writing both covers either reading (see the profile's note).
    """
    flow = Flow(writer, operator, "oxygen_end_value")
    flow.require(OXYGEN_END_VALUE_POINTS, "end-value calibration")
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
                f"the end-value unit 0x204B holds {show(held)}, not a known unit: give the "
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
            ("logbook oxygen = reference", LOGBOOK_NEWEST + "oxygen", reference),
        ),
    )
