"""A simulated sensor with a past: the records it holds after weeks in service.

The ``aging:`` block of a simulated device lays out, at start, what a sensor in service for
some time would hold ("fast-forward"): the tecLine/Reiss calibration history with its
falling slopes (tecLine annex 7.2), the H10/H20 calibration logbook (6.1.6) and counters,
and the S10's and H10/H20's operating hours and cap state. Everything here is pure: given
the settings, the simulator's wall-clock time and the profile, which values to put.
The behaviours (:mod:`gateway.simulator.behaviour`) put them at start and keep a tecLine
cell's slope falling while they run.

Example::

    aging = AgingSettings(weeks_in_service=8, last_calibration_days=9, slope_start=0.8)
    aged = amperometric_values(aging, now=now, profile=profile, nominal_slope=22.0)
    # aged.values["history_0_x_span"] == 22.0 * (0.8 - 0.06 * 6): six weeks after the first
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from datetime import UTC, datetime, timedelta, tzinfo
from typing import TYPE_CHECKING, Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

if TYPE_CHECKING:
    from gateway.profiles import Profile

WEEK = timedelta(weeks=1)
WEEK_S = 604_800
# The operating-seconds counter of a simulated digiLine sensor without an aging block (about
# 42 days): what the simulator has always reported.
OPERATING_SECONDS_AT_START = 3_600_000
# Our choices where the manuals are silent; each one a plausible value, not a documented one.
SLOPE_FLOOR = 0.01  # of nominal: a cell never reports a slope of zero (it divides by it)
ZERO_POINT_PHASE_DEG = 60.0  # the simulated phase in oxygen-free water (behaviour.measure)
END_VALUE_PHASE_DEG = 35.0  # the simulated phase at 100 % saturation (behaviour.measure)
CALIBRATION_TEMPERATURE_C = 20.0
END_VALUE_OXYGEN_MG_PER_L = 9.09  # air-saturated water at 20 °C and 1013 hPa
END_VALUE_PRESSURE_MBAR = 1013.25
# H10/H20: a two-point calibration is a zero point (in nitrogen), then the end value (in
# air) this much later; the logbook holds both as entries of their own (6.1.6).
ZERO_POINT_LEAD = timedelta(minutes=15)
ZERO_POINT_TYPE = 20  # 6.1.6 "Eintragstyp": digiLine ODO Hxx Nullpunkt
END_VALUE_TYPE = 21  # digiLine ODO Hxx Endwert


class AgingSettings(BaseModel):
    """How long a simulated sensor has been in service, and what that did to it.

    Example (YAML, in a device entry)::

        aging: {weeks_in_service: 8, last_calibration_days: 9, slope_start: 0.8}
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    # Fast-forward: the records are laid out as if the sensor had been in service this long.
    weeks_in_service: Annotated[float, Field(ge=0, le=520)] = 8
    # One calibration this often in the past (the tecLine history, the H10/H20 logbook).
    calibration_interval_days: Annotated[float, Field(gt=0, le=3650)] = 7
    # How long ago the newest calibration was (beyond the interval: overdue).
    last_calibration_days: Annotated[float, Field(ge=0, le=3650)] = 9
    # tecLine/Reiss: X_Span at the first calibration as a fraction of the nominal slope ...
    slope_start: Annotated[float, Field(gt=0, le=2)] = 0.95
    # ... and the fraction of nominal lost per week since (linear).
    slope_decay_per_week: Annotated[float, Field(ge=0, le=1)] = 0.06
    # H10/H20: degrees added to the zero-point phase per week, in the logbook.
    zero_phase_drift_per_week: Annotated[float, Field(ge=-5, le=5)] = 0.05
    # H10/H20: measurements per week in service (0x2091), and the counter's maximum (0x2095).
    measurements_per_week: Annotated[int, Field(ge=0, le=10_000_000)] = 100_000
    measurement_counter_max: Annotated[int, Field(ge=1, le=0xFFFF_FFFF)] = 1_000_000
    # digiLine: the sensor (cap) replacement counter 0x0402 now.
    cap_changes: Annotated[int, Field(ge=0, le=0xFFFF)] = 1
    # H10/H20: CIP and SIP cycles since the newest calibration (0x2061, 0x205F).
    cip_cycles: Annotated[int, Field(ge=0, le=0xFFFF_FFFF)] = 0
    sip_cycles: Annotated[int, Field(ge=0, le=0xFFFF_FFFF)] = 0
    # H10/H20: hours outside the operating temperature range (0x2071).
    hours_outside_temperature: Annotated[float, Field(ge=0, le=87_360)] = 0
    # S10: status bit 10; S10 bit 2 and H10/H20 bit 4 "cap missing".
    cap_replacement_recommended: bool = False
    cap_missing: bool = False
    # H10/H20: the rating of the newest logbook entry.
    evaluation: Literal["ok", "warning"] = "ok"

    @model_validator(mode="after")
    def _hours_fit_in_service(self) -> AgingSettings:
        if self.hours_outside_temperature > self.weeks_in_service * 7 * 24:
            raise ValueError(
                f"hours_outside_temperature: {self.hours_outside_temperature} h is more than "
                f"the {self.weeks_in_service} weeks in service"
            )
        return self


@dataclass(frozen=True, slots=True)
class Aged:
    """What to put into a device: values by point name, and bits of bit fields to change.

    ``flags`` are merged into the bit field's current value (other bits kept).
    """

    values: dict[str, object] = field(default_factory=dict)
    flags: dict[str, dict[str, bool]] = field(default_factory=dict)


# --- time --------------------------------------------------------------------------------


def _minute(instant: datetime) -> datetime:
    return instant.astimezone(UTC).replace(second=0, microsecond=0)


def service_start(aging: AgingSettings, now: datetime) -> datetime:
    """When the sensor was put into service (UTC, to the minute)."""
    return _minute(now - aging.weeks_in_service * WEEK)


def calibration_count(aging: AgingSettings) -> int:
    """How many calibrations fit into the time in service, the newest one included."""
    service_days = aging.weeks_in_service * 7
    if aging.last_calibration_days > service_days:
        return 0
    return (
        math.floor((service_days - aging.last_calibration_days) / aging.calibration_interval_days)
        + 1
    )


def calibration_times(aging: AgingSettings, now: datetime, *, limit: int) -> tuple[datetime, ...]:
    """The newest ``limit`` calibrations (UTC, to the minute), newest first."""
    return tuple(
        _minute(
            now - timedelta(days=aging.last_calibration_days + k * aging.calibration_interval_days)
        )
        for k in range(min(limit, calibration_count(aging)))
    )


def first_calibration(aging: AgingSettings, now: datetime) -> datetime:
    """The oldest calibration in service, from which slopes fall and phases drift.

    Without a calibration in service (the newest is older than the sensor), its start.
    """
    count = calibration_count(aging)
    if count == 0:
        return service_start(aging, now)
    days = aging.last_calibration_days + (count - 1) * aging.calibration_interval_days
    return _minute(now - timedelta(days=days))


def weeks_between(earlier: datetime, later: datetime) -> float:
    """Weeks from ``earlier`` to ``later``."""
    return (later - earlier) / WEEK


def local_stamp(instant: datetime, zone: tzinfo | None = None) -> datetime:
    """A tecLine/Reiss YYMMDDHHMM stamp as the gateway writes one: local wall-clock time.

    The gateway stamps a calibration with ``datetime.now().astimezone()`` and drops the
    zone; ``zone=None`` is the host's zone (with its daylight saving time at that instant).
    """
    return instant.astimezone(zone).replace(tzinfo=None, second=0, microsecond=0)


# --- tecLine / Reiss ---------------------------------------------------------------------


def slope_fraction(aging: AgingSettings, weeks_since_first: float) -> float:
    """X_Span (or the cell's real slope) as a fraction of nominal, that long after the first."""
    return max(SLOPE_FLOOR, aging.slope_start - aging.slope_decay_per_week * weeks_since_first)


def real_slope_fraction(aging: AgingSettings, *, first: datetime, at: datetime) -> float:
    """The cell's real slope at wall-clock ``at``, as a fraction of nominal."""
    return slope_fraction(aging, weeks_between(first, at))


def amperometric_values(
    aging: AgingSettings,
    *,
    now: datetime,
    profile: Profile,
    nominal_slope: float,
    zone: tzinfo | None = None,
) -> Aged:
    """The calibration history (annex 7.2) and the active calibration of an aged cell.

    Entry 0 is the newest and a copy of the active calibration (X_Zero, X_Span, DateTime);
    entries the time in service has no calibration for stay empty (stamp 0).
    """
    first = first_calibration(aging, now)
    values: dict[str, object] = {}
    for k, at in enumerate(calibration_times(aging, now, limit=_entries(profile, "history"))):
        span = nominal_slope * slope_fraction(aging, weeks_between(first, at))
        values[f"history_{k}_x_zero"] = 0.0
        values[f"history_{k}_x_span"] = span
        values[f"history_{k}_stamp"] = local_stamp(at, zone)
    if values:
        values["x_zero"] = values["history_0_x_zero"]
        values["x_span"] = values["history_0_x_span"]
        values["calibration_stamp"] = values["history_0_stamp"]
    return Aged(values=values)


# --- digiLine ----------------------------------------------------------------------------


def operating_seconds(aging: AgingSettings) -> int:
    """The operating-seconds counter at start: at least the time in service."""
    return max(OPERATING_SECONDS_AT_START, math.ceil(aging.weeks_in_service * WEEK_S))


def measurement_counter(aging: AgingSettings) -> int:
    """0x2091 at start: the measurements of the time in service, up to the maximum."""
    return min(
        math.floor(aging.weeks_in_service * aging.measurements_per_week),
        aging.measurement_counter_max,
    )


def _digiline_common(aging: AgingSettings, *, now: datetime, counter_s: int) -> dict[str, object]:
    """Initial startup (S10 6.7.1, H10 6.1.5) at the start of service; the cap counter."""
    return {
        "commissioning_date": service_start(aging, now),
        "commissioning_operating_seconds": max(
            0, counter_s - math.ceil(aging.weeks_in_service * WEEK_S)
        ),
        "sensor_replacement_counter": aging.cap_changes,
    }


def s10_values(aging: AgingSettings, *, now: datetime) -> Aged:
    """S10: initial startup, cap counter and the cap bits of the status word (6.8.3)."""
    values = _digiline_common(aging, now=now, counter_s=operating_seconds(aging))
    flags = {
        "status": {
            "cap_replacement_recommended": aging.cap_replacement_recommended,
            "cap_missing": aging.cap_missing,
        }
    }
    return Aged(values=values, flags=flags)


@dataclass(frozen=True, slots=True)
class LogbookEntry:
    """One H10/H20 calibration logbook entry (6.1.6)."""

    entry_type: int  # ZERO_POINT_TYPE or END_VALUE_TYPE
    date: datetime  # UTC, to the minute
    operating_seconds: int
    sensor_replacement_counter: int
    rating: str  # "ok" or "warning"
    values: tuple[float, float, float, float, float, float]
    units: tuple[str, str, str, str, str, str]


def logbook(
    aging: AgingSettings, *, now: datetime, counter_s: int, entries: int
) -> tuple[LogbookEntry, ...]:
    """The newest ``entries`` logbook entries, newest first.

    Each calibration is a zero point and, ``ZERO_POINT_LEAD`` later, an end value; the
    zero-point phase drifts by ``zero_phase_drift_per_week`` from the first calibration on.
    ``counter_s`` is the operating-seconds counter at ``now``.
    """
    first = first_calibration(aging, now)
    cap = min(0xFF, aging.cap_changes)  # the entry's counter is a uint8
    out: list[LogbookEntry] = []
    for at in calibration_times(aging, now, limit=math.ceil(entries / 2)):
        phase = ZERO_POINT_PHASE_DEG + aging.zero_phase_drift_per_week * weeks_between(first, at)
        end_value = (
            END_VALUE_PHASE_DEG,
            CALIBRATION_TEMPERATURE_C,
            0.0,
            END_VALUE_OXYGEN_MG_PER_L,
            END_VALUE_PRESSURE_MBAR,
            0.0,
        )
        zero_point = (phase, CALIBRATION_TEMPERATURE_C, 0.0, 0.0, 0.0, 0.0)
        for entry_type, date, values, units in (
            (END_VALUE_TYPE, at, end_value, ("°", "°C", "", "mg/l", "mbar", "")),
            (ZERO_POINT_TYPE, at - ZERO_POINT_LEAD, zero_point, ("°", "°C", "", "", "", "")),
        ):
            elapsed_s = round((now - date).total_seconds())
            out.append(
                LogbookEntry(
                    entry_type=entry_type,
                    date=date,
                    operating_seconds=max(0, counter_s - elapsed_s),
                    sensor_replacement_counter=cap,
                    rating=aging.evaluation if not out else "ok",  # the newest is rated
                    values=values,
                    units=units,
                )
            )
    return tuple(out[:entries])


_LOGBOOK_VALUES = ("phase", "temperature", "calibration_mode", "oxygen", "pressure", "value_6")


def entry_values(number: int, entry: LogbookEntry) -> dict[str, object]:
    """The points of logbook entry ``number`` (1: newest) holding ``entry``, by name."""
    prefix = f"logbook_{number}_"
    values: dict[str, object] = {
        f"{prefix}entry_type": entry.entry_type,
        f"{prefix}manual_change": "calibration",
        f"{prefix}rating": entry.rating,
        f"{prefix}operating_seconds": entry.operating_seconds,
        f"{prefix}date": entry.date,
        f"{prefix}sensor_replacement_counter": entry.sensor_replacement_counter,
    }
    for name, value, unit in zip(_LOGBOOK_VALUES, entry.values, entry.units, strict=True):
        values[f"{prefix}{name}"] = value
        values[f"{prefix}{name}_unit"] = unit
    return values


def _logbook_values(entries: tuple[LogbookEntry, ...]) -> dict[str, object]:
    values: dict[str, object] = {}
    for number, entry in enumerate(entries, start=1):
        values |= entry_values(number, entry)
    return values


def _active_calibration(entries: tuple[LogbookEntry, ...]) -> dict[str, object]:
    """0x203F-0x204C: the newest zero point and end value of the logbook (6.2.3)."""
    values: dict[str, object] = {}
    zero = next((e for e in entries if e.entry_type == ZERO_POINT_TYPE), None)
    end = next((e for e in entries if e.entry_type == END_VALUE_TYPE), None)
    if zero is not None:
        values["zero_point_phase"] = zero.values[0]
        values["zero_point_temperature"] = zero.values[1]
    if end is not None:
        values["end_value_phase"] = end.values[0]
        values["end_value_temperature"] = end.values[1]
        values["end_value_oxygen"] = end.values[3]
        values["end_value_oxygen_unit"] = "ppm"  # mg/l, as the entry's unit text says
        values["end_value_pressure"] = end.values[4]
    return values


def h10_values(aging: AgingSettings, *, now: datetime, profile: Profile) -> Aged:
    """H10/H20: the logbook (6.1.6), the counters (6.2.5, 6.2.6, 6.2.9) and the cap bits."""
    counter_s = operating_seconds(aging)
    entries = logbook(aging, now=now, counter_s=counter_s, entries=_entries(profile, "logbook"))
    counter = measurement_counter(aging)
    values = _digiline_common(aging, now=now, counter_s=counter_s)
    values.update(_logbook_values(entries))
    values.update(_active_calibration(entries))
    values.update(
        {
            "measurement_counter": counter,
            "measurement_counter_max": aging.measurement_counter_max,
            "cip_cycles_since_calibration": aging.cip_cycles,
            "sip_cycles_since_calibration": aging.sip_cycles,
            # Totals: at least the cycles since the calibration (nothing is known of before).
            "cip_cycles_total": aging.cip_cycles,
            "sip_cycles_total": aging.sip_cycles,
            "hours_outside_operating_temperature": aging.hours_outside_temperature,
        }
    )
    overflow = counter_overflows(counter, aging.measurement_counter_max)
    flags = {"error_register": {"measurement_counter_overflow": overflow}}
    if "cap_missing" in profile.point("status").format.bits.values():
        flags["status"] = {"cap_missing": aging.cap_missing}
    return Aged(values=values, flags=flags)


def counter_overflows(counter: int, maximum: int) -> bool:
    """0x2095: reaching the maximum sets error register bit 7 (6.2.9)."""
    return counter >= maximum


def _entries(profile: Profile, repeat: str) -> int:
    """How many entries a repeated block (history, logbook) of the profile has."""
    indices = {p.index for p in profile.points if p.repeat == repeat and p.index is not None}
    return len(indices)
