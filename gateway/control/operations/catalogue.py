"""Which operations there are, which apply to a profile, their arguments, values as JSON.

Which operation applies is decided from the profile's data (the points it declares), not
from vendor names:

- ``set_clock``: a writable date-and-time block: the S10 clock (0x2840-0x2846, S10 manual
  6.9) or the H10/H20 calibration date (0x300A-0x3010, manual 6.2.4);
- ``measure``: the H10/H20 measurement control word 0x3001 and the status word 0x3007
  with the bits the profile names (manual 6.2.2 and 6.2.10);
- ``calibration_log``: the H10/H20 logbook (manual 6.1.6) or the tecLine / Reiss history
  (tecLine annex 7.2, Reiss 5.1);
- ``calibrations``: a device that offers a guided calibration, as the calibration
  catalogue decides it (:mod:`gateway.control.calibration.catalogue`).

A refusal here raises :class:`~gateway.errors.CommandRejectedError` before anything
reaches the bus.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Final

from gateway.errors import CommandRejectedError
from gateway.line.samples import json_value
from gateway.wire import codec
from gateway.wire.codec import DataType

if TYPE_CHECKING:
    from collections.abc import Callable, Mapping

    from gateway.profiles import Profile

SET_CLOCK: Final = "set_clock"
MEASURE: Final = "measure"
CALIBRATION_LOG: Final = "calibration_log"
CALIBRATIONS: Final = "calibrations"
OPERATION_NAMES: Final = (SET_CLOCK, MEASURE, CALIBRATION_LOG, CALIBRATIONS)

# H10/H20 manual 6.2.2 (0x3001) and 6.2.10 (0x3007); the bit names are the profile's.
MEASUREMENT_STATUS: Final = "measurement_status"
MEASURING_BIT: Final = "measuring"  # bit 1: "Wenn 1, findet gerade eine Messung statt"
TRIGGER_BIT: Final = (
    "single_measurement_trigger"  # bit 2: "Setzen, um eine Einzelmessung auszulösen"
)
STATUS: Final = "status"
NEW_VALUES_BIT: Final = "new_values"  # 0x3007 bit 15 (0x8000): "Neue Messwerte"
MEASURED_POINTS: Final = ("oxygen", "temperature")

# The manual does not say how long a single measurement takes. Ten seconds is ours; the
# ceiling stays below the MQTT command handler's 60 s (gateway.control.command_router).
MEASURE_TIMEOUT_S: Final = 10.0
MEASURE_TIMEOUT_MAX_S: Final = 50.0

# --- which operation applies: read from the profile's data ------------------------------


@dataclass(frozen=True, slots=True, kw_only=True)
class ClockPoint:
    """A writable date-and-time block that ``set_clock`` sets, and what it means."""

    point: str
    running: bool  # whether the sensor advances it (a clock) or keeps it (a stamp)
    meaning: str


CLOCK_POINTS: Final = (
    ClockPoint(
        point="clock",
        running=True,
        meaning="device date and time for time stamps (S10 manual 6.9)",
    ),
    ClockPoint(
        point="calibration_date",
        running=False,
        meaning=(
            "calibration date copied into the following logbook entries; the sensor "
            "keeps it, it does not run (H10/H20 manual 6.2.4, not written to flash)"
        ),
    ),
)


@dataclass(frozen=True, slots=True, kw_only=True)
class LogLayout:
    """A repeated calibration record in a profile, and how to tell an empty entry."""

    repeat: str  # the profile's repeat name: points are ``{repeat}_{index}_{field}``
    marker: str  # the field that says whether an entry holds data
    current: tuple[str, ...]  # points of the active calibration, shown with the log
    note: str


LOG_LAYOUTS: Final = (
    LogLayout(
        repeat="logbook",
        marker="entry_type",  # 6.1.6 "Eintragstyp": 0 = kein Eintrag
        current=(),
        note=(
            "H10/H20 calibration logbook (manual 6.1.6); the manual does not document the "
            "order of the entries"
        ),
    ),
    LogLayout(
        repeat="history",
        marker="stamp",  # DateTime 0 is the documented initial value: never calibrated
        current=("x_zero", "x_span", "calibration_stamp"),
        note=(
            "calibration history: entry 0 is the current calibration, 4 the oldest "
            "(tecLine annex 7.2, Reiss 5.1)"
        ),
    ),
)


def clock_point(profile: Profile) -> ClockPoint | None:
    """The date-and-time block ``set_clock`` writes on this profile, if it has one."""
    for candidate in CLOCK_POINTS:
        if profile.has_point(candidate.point):
            point = profile.point(candidate.point)
            if point.writable and point.dtype is DataType.DATETIME:
                return candidate
    return None


def log_layout(profile: Profile) -> LogLayout | None:
    """The calibration log this profile declares (logbook or history), if any."""
    repeats = {p.repeat for p in profile.points if p.repeat is not None}
    for layout in LOG_LAYOUTS:
        if layout.repeat in repeats and all(profile.has_point(p) for p in layout.current):
            return layout
    return None


def _has_bits(profile: Profile, point: str, *bits: str) -> bool:
    if not profile.has_point(point):
        return False
    return set(bits) <= set(profile.point(point).format.bits.values())


def _measure_applies(profile: Profile) -> bool:
    return (
        _has_bits(profile, MEASUREMENT_STATUS, MEASURING_BIT, TRIGGER_BIT)
        and profile.point(MEASUREMENT_STATUS).writable
        and _has_bits(profile, STATUS, NEW_VALUES_BIT)
        and all(profile.has_point(p) for p in MEASURED_POINTS)
    )


def offers_calibrations(profile: Profile) -> bool:
    """Whether a device of ``profile`` offers a guided calibration (the catalogue's word).

    The catalogue, and with it the calibration flows, is imported when this is asked (a
    ``command/…`` message), not with the MQTT command router: a gateway without its web
    page does not hold the flows in memory (``tests/cli/test_imports.py``).
    """
    from gateway.control.calibration import catalogue  # noqa: PLC0415 - see above

    return bool(catalogue.offered(profile))


_APPLIES: Final[Mapping[str, Callable[[Profile], bool]]] = {
    SET_CLOCK: lambda profile: clock_point(profile) is not None,
    MEASURE: _measure_applies,
    CALIBRATION_LOG: lambda profile: log_layout(profile) is not None,
    CALIBRATIONS: offers_calibrations,
}


def operations_for(profile: Profile) -> list[str]:
    """The operations that apply to a profile, in :data:`OPERATION_NAMES` order."""
    return [name for name in OPERATION_NAMES if _APPLIES[name](profile)]


def require_operation(name: str, profile: Profile) -> None:
    """Refuse an unknown operation, or one the profile does not support (naming those it does)."""
    if name not in _APPLIES:
        raise CommandRejectedError(
            f"unknown operation {name!r}; operations: {', '.join(OPERATION_NAMES)}"
        )
    if _APPLIES[name](profile):
        return
    supported = operations_for(profile)
    which = ", ".join(supported) if supported else "none"
    raise CommandRejectedError(
        f"operation {name!r} does not apply to profile {profile.id} "
        f"(operations for this device: {which})"
    )


# --- arguments --------------------------------------------------------------------------


def _flag(name: str, value: object) -> bool:
    if not isinstance(value, bool):
        raise CommandRejectedError(f"argument {name!r} must be true or false, got {value!r}")
    return value


def measure_timeout(name: str, value: object) -> float:
    """A measurement's timeout in seconds, within (0, :data:`MEASURE_TIMEOUT_MAX_S`]."""
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise CommandRejectedError(f"argument {name!r} must be a number of seconds, got {value!r}")
    seconds = float(value)
    if not 0 < seconds <= MEASURE_TIMEOUT_MAX_S:
        raise CommandRejectedError(
            f"argument {name!r} must be more than 0 and at most {MEASURE_TIMEOUT_MAX_S:g} "
            f"seconds, got {value!r}"
        )
    return seconds


_ARGUMENTS: Final[Mapping[str, Mapping[str, Callable[[str, object], object]]]] = {
    SET_CLOCK: {"local": _flag},
    MEASURE: {"timeout": measure_timeout},
    CALIBRATION_LOG: {},
    CALIBRATIONS: {},
}


def parse_arguments(name: str, arguments: Mapping[str, object]) -> dict[str, object]:
    """An operation's arguments checked and typed, or a :class:`CommandRejectedError`.

    ``set_clock`` takes ``{"local": true}`` (write the gateway host's local time instead
    of UTC), ``measure`` takes ``{"timeout": seconds}``, ``calibration_log`` and
    ``calibrations`` nothing.
    """
    if name not in _ARGUMENTS:
        raise CommandRejectedError(
            f"unknown operation {name!r}; operations: {', '.join(OPERATION_NAMES)}"
        )
    accepted = _ARGUMENTS[name]
    unknown = sorted(set(arguments) - set(accepted))
    if unknown:
        takes = f"it takes {', '.join(sorted(accepted))}" if accepted else "it takes none"
        raise CommandRejectedError(
            f"unknown argument {', '.join(map(repr, unknown))} for {name}; {takes}"
        )
    return {key: accepted[key](key, value) for key, value in arguments.items()}


# --- results ----------------------------------------------------------------------------


def as_json(value: codec.Decoded) -> object:
    """A decoded value as JSON-ready data; a sensor fault as ``{"fault": name}``."""
    if isinstance(value, codec.Fault):
        return {"fault": value.name}
    return json_value(value)
