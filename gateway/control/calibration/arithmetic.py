"""The arithmetic of calibrating, without I/O: slopes and their judgement, stamps, history.

The constants carry their source in the manuals (tecLine annex 7, Reiss chapter 5, the
H10/H20 manual 6.2.4); where a manual gives no number, the comment says the number is ours.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import StrEnum
from typing import TYPE_CHECKING, Final

from gateway.errors import CommandRejectedError

if TYPE_CHECKING:
    from collections.abc import Sequence
    from datetime import datetime

    from gateway.profiles import Slope

# tecLine annex 7.3.3 / Reiss 5.2.3 "chemical check": the sensor's and the analysed
# concentration "should be broadly identical". The manuals give no number; 10 % is ours.
CHEMICAL_CHECK_TOLERANCE: Final = 0.10
# A float32 read back is compared with the float64 we computed: 24 bits of mantissa.
_FLOAT32_REL_TOL: Final = 1e-6
# H10/H20 registers the sensor fills from the same measurement (203F and the logbook phase):
# compared with a little room, as the manual does not say they are bit-identical.
SAME_MEASUREMENT_REL_TOL: Final = 1e-4

# How a flow reads the cell current when the operator did not note it. The catalogue
# (``catalogue.py``) offers these as the defaults of ``samples`` and ``every`` to every front
# end; the flows' keyword defaults are the same names, so there is one set of defaults.
# tecLine annex 7.3.1 steps 2-3 and 7.4.1 steps 2-3, Reiss 5.2.1: wait until the signal at
# the sensor is stable, then read the cell current (0x0002) once and note it. One reading.
CELL_CURRENT_READINGS: Final = 1
# Between further readings, if the operator asks for an average: the manuals are silent
# (one reading needs no interval). One second is ours: the default poll interval of process
# values, so the readings follow the live values the operator watched settle.
READING_INTERVAL_S: Final = 1.0
# The bounds of both (ours): a hundred readings a minute apart is already an hour and a
# half at the sensor.
MAX_READINGS: Final = 100
MAX_READING_INTERVAL_S: Final = 60.0
# H10/H20 manual 6.2.4: 0x3009 is 0 at start-up, "mode as configured in register 0x2021";
# 1 wet, 2 dry (the profile's labels).
CALIBRATION_MODES: Final = ("as_configured", "wet", "dry")
CALIBRATION_MODE_DEFAULT: Final = CALIBRATION_MODES[0]
# H10/H20 manual 6.2.3, table 2 (0x204B, the unit of the end value 0x2043): the profile's
# labels of the units the end value may be given in.
END_VALUE_UNITS: Final = ("percent_saturation", "percent_volume", "ppm", "ppb", "hpa")

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
LOGBOOK_NEWEST: Final = "logbook_1_"
# What each family's procedures need of a profile: the flows refuse a device without them
# before any I/O, and the catalogue offers a procedure only to a profile that has them.
CELL_PROCEDURE_POINTS: Final = AMPEROMETRIC_POINTS | {"concentration", "history_0_x_zero"}
OXYGEN_ZERO_POINTS: Final = OPTICAL_OXYGEN_POINTS | {"zero_point_phase"}
OXYGEN_END_VALUE_POINTS: Final = OPTICAL_OXYGEN_POINTS | {"end_value_oxygen_unit"}


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


def nominal_in_unit(nominal_na_per_ppm: float, unit: str, facts: Slope) -> float:
    """The nominal slope (nA/ppm) in nA per ``unit``, the unit label of 0x0200.

    ``facts``: the cell's slope facts, from its profile (:attr:`Profile.slope`).
    """
    nominal = facts.nominal_in(nominal_na_per_ppm, unit)
    if nominal is None:
        raise CommandRejectedError(
            f"the concentration unit {unit!r} (0x0200) has no known relation to ppm, so the "
            "nominal slope (nA/ppm) cannot be compared or written",
            point="x_span",
        )
    return nominal


@dataclass(frozen=True, slots=True, kw_only=True)
class SlopeJudgement:
    """A slope against the nominal one: its fraction, and whether it is below the limit."""

    slope: float  # nA per unit of 0x0200
    nominal: float  # the nominal slope in the same unit
    fraction: float  # slope / nominal
    low: bool  # below the profile's limit (30 %): maintain the sensor (annex 7.3.4)
    limit: float  # that limit


def judge_slope(slope: float, nominal_na_per_ppm: float, unit: str, facts: Slope) -> SlopeJudgement:
    """Compare a slope in nA per ``unit`` with the nominal slope (annex 7.3.4)."""
    nominal = nominal_in_unit(nominal_na_per_ppm, unit, facts)
    if not math.isfinite(nominal) or nominal <= 0:
        raise CommandRejectedError(
            f"the nominal slope {nominal_na_per_ppm:g} nA/ppm (0x030A) is not usable",
            point="nominal_slope",
        )
    fraction = slope / nominal
    return SlopeJudgement(
        slope=slope,
        nominal=nominal,
        fraction=fraction,
        low=fraction < facts.limit,
        limit=facts.limit,
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
            close_to(self.x_zero, other.x_zero)
            and close_to(self.x_span, other.x_span)
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


def close_to(a: float, b: float, rel_tol: float = _FLOAT32_REL_TOL) -> bool:
    """Whether two values are the same as far as a float32 (or ``rel_tol``) can tell."""
    return math.isclose(a, b, rel_tol=rel_tol, abs_tol=1e-9)
