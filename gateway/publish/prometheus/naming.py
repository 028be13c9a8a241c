"""The naming of values: a point's family, in base units, with its unit in the name or a label.

A value is ``gateway_<point>_<base unit>`` where the profile fixes the unit, converted from
the sensor's unit to the base unit Prometheus' conventions ask for: a current in amperes
(``gateway_cell_current_amperes``, the tecLine's nA / 10⁹), a voltage in volts, durations in
seconds, pressures in pascals, a conductivity in siemens per metre, temperatures in degrees
Celsius (https://prometheus.io/docs/practices/naming/#base-units). Where a unit register
selects the unit (``gateway_oxygen{unit="mg/l"}``) or the unit has no base form
(``gateway_nominal_slope{unit="nA/ppm"}``), the value is as the sensor sent it and the unit
is a ``unit`` label. A few points are named apart (:data:`RENAMED`): a count that is not a
counter has no ``_total`` and no ``counter`` in its name.

Not every point is a metric. The entries of a log (the H10/H20 calibration logbook, the
tecLine/Reiss calibration history: a profile's repeated blocks) shift by one with every new
entry, so ``entry 3`` is a different calibration each time and no series of them means
anything over time; sensor care reads them (``gateway_care_state`` and its dates and
ratios). The points that fill ``gateway_device_info``'s labels are labels, not gauges. The
entries of a record that are one quantity (the H10/H20 cap's sensor constants) are one
family with the entry as a label (``gateway_sensor_constant{constant="m"}``).

:mod:`~gateway.publish.prometheus.legacy` keeps the names before these rules, for one
release (``prometheus.legacy_names``).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import TYPE_CHECKING, Final

from gateway.errors import ConfigError
from gateway.profiles import builtin_profiles, get_profile
from gateway.wire.codec import NUMERIC_TYPES, DataType

if TYPE_CHECKING:
    from collections.abc import Mapping

    from gateway.line.samples import Sample
    from gateway.profiles.model import Point

PREFIX: Final = "gateway_"


@dataclass(frozen=True, slots=True)
class BaseUnit:
    """A unit of the profiles in the base unit its metric is named with.

    The value in base units is ``value * multiply / divide``: whole numbers, so that
    152.5 nA is exported as ``1.525e-07`` and not as the nearest product with ``1e-09``.
    """

    suffix: str
    multiply: int = 1
    divide: int = 1

    def convert(self, value: float) -> float:
        """A value in the profile's unit, in the base unit."""
        if self.multiply == self.divide:
            return value
        return value * self.multiply / self.divide


# The units the profiles fix, by the base unit a metric name carries. Angles keep their
# degrees: an angle has no Prometheus base unit, and the manuals give phases in degrees.
BASE_UNITS: Final[Mapping[str, BaseUnit]] = {
    "°C": BaseUnit("celsius"),
    "nA": BaseUnit("amperes", divide=10**9),
    "mA": BaseUnit("amperes", divide=10**3),
    "\u00b5V": BaseUnit("volts", divide=10**6),  # MICRO SIGN, as in the profiles
    "\u03bcV": BaseUnit("volts", divide=10**6),  # GREEK SMALL LETTER MU, its look-alike
    "hPa": BaseUnit("pascals", multiply=100),
    "mbar": BaseUnit("pascals", multiply=100),
    "s": BaseUnit("seconds"),
    "ms": BaseUnit("seconds", divide=10**3),
    "min": BaseUnit("seconds", multiply=60),
    "h": BaseUnit("seconds", multiply=3600),
    "°": BaseUnit("degrees"),
    "mS/cm": BaseUnit("siemens_per_metre", divide=10),
}

# Points whose own name would break Prometheus' conventions once a metric: the name they
# have instead (before the unit's suffix). A count that is not a counter (the sensor's own
# register, read as it is) has no ``_total`` and no ``counter``/``count`` in its name; a
# time in hours is a time once it is in seconds.
RENAMED: Final[Mapping[str, str]] = {
    "cip_cycles_total": "cip_cycles",
    "sip_cycles_total": "sip_cycles",
    "measurement_counter": "measurements",
    "measurement_counter_max": "measurements_max",
    "sensor_replacement_counter": "sensor_replacements",
    "autoclave_count": "autoclave_cycles",
    "hours_outside_operating_temperature": "time_outside_operating_temperature",
    "hours_outside_oxygen_temperature": "time_outside_oxygen_temperature",
}

# Records whose entries are one quantity: the points ``<record>_<entry>`` are the family
# ``gateway_<record>`` with the entry in the label named here, and this HELP.
RECORDS: Final[Mapping[str, tuple[str, str]]] = {
    "sensor_constant": (
        "constant",
        "A constant of the O-DO sensor cap (H10/H20 0x2031-0x203C), named in 'constant'",
    ),
}

# The points whose values are labels of ``gateway_device_info`` (``health.IDENTITY_LABELS``).
INFO_LABEL_POINTS: Final = frozenset(
    {
        "serial_number",
        "software_version",
        "firmware_version",
        "hardware_version",
        "hardware_version_major",
        "hardware_version_minor",
    }
)

NUMERIC_POINT_TYPES: Final = NUMERIC_TYPES | {DataType.BOOL}
# The labels of a device, of its values and of one of its points.
DEVICE_LABELS: Final = ("bus", "device")
VALUE_LABELS: Final = ("bus", "device", "profile")
POINT_LABELS: Final = ("bus", "device", "profile", "point")

# Every series name the collector exports besides the values (histogram and counter
# suffixes included). A point whose value family would take one of them gets ``_value``.
RESERVED_NAMES: Final = frozenset(
    {
        "gateway_up",
        "gateway_start_time_seconds",
        "gateway_value_age_seconds",
        "gateway_value_fault",
        "gateway_status_flag",
        "gateway_enum_info",
        "gateway_device_info",
        "gateway_device_online",
        "gateway_device_identity_mismatch",
        "gateway_poll_lag_seconds",
        "gateway_unreadable_points",
        "gateway_bus_utilisation_ratio",
        "gateway_bus_port_open",
        "gateway_bus_port_problem",
        "gateway_port_latency_timer_seconds",
        "gateway_mqtt_connected",
        "gateway_mqtt_queue_depth",
        "gateway_mqtt_queue_max",
        "gateway_request_latency_seconds",
        "gateway_request_latency_seconds_bucket",
        "gateway_request_latency_seconds_sum",
        "gateway_request_latency_seconds_count",
        "gateway_flash_writes_today",
        "gateway_flash_write_budget",
        "gateway_feed_source_age_seconds",
        "gateway_feed_stale",
        "gateway_feed_fallback",
        "gateway_care_state",
        "gateway_last_calibration_timestamp_seconds",
        "gateway_calibration_due_timestamp_seconds",
        "gateway_slope_ratio",
        "gateway_slope_limit_projected_timestamp_seconds",
        "gateway_cap_usage_ratio",
    }
    | {
        name + suffix
        for name in (
            "gateway_requests",
            "gateway_responses",
            "gateway_errors",
            "gateway_exceptions",
            "gateway_retries",
            "gateway_tolerated_quirks",
            "gateway_missed_deadlines",
            "gateway_bus_busy_seconds",
            "gateway_bus_port_failures",
            "gateway_mqtt_dropped",
            "gateway_mqtt_published",
            "gateway_writes",
            "gateway_flash_writes",
            "gateway_feed_writes",
            "gateway_feed_errors",
        )
        for suffix in ("", "_total")
    }
)


@dataclass(frozen=True, slots=True)
class ValueNaming:
    """Where a numeric point's value goes: its family, its unit, its record entry.

    Example::

        value_naming("temperature", "°C")  # gateway_temperature_celsius, no unit label
        value_naming("cell_current", "nA")  # gateway_cell_current_amperes, value / 10**9
        value_naming("oxygen", None, unit_from=True)  # gateway_oxygen, unit label from the sample
        value_naming("nominal_slope", "nA/ppm")  # gateway_nominal_slope, unit="nA/ppm"
        value_naming("sensor_constant_m", "")  # gateway_sensor_constant, constant="m"
    """

    family: str
    unit_label: bool = False  # the family's samples carry a ``unit`` label
    from_register: bool = False  # ... taken from the sample (a unit register selected it)
    fixed_unit: str | None = None  # ... or this fixed unit without a base form
    base: BaseUnit | None = None  # the value is converted to this base unit
    entry: tuple[str, str] | None = None  # the record entry's label and value

    def convert(self, value: float) -> float:
        """The value as the family exports it (in its base unit)."""
        return value if self.base is None else self.base.convert(value)


def value_naming(
    point: str, unit: str | None, *, unit_from: bool = False, repeat: str | None = None
) -> ValueNaming | None:
    """The family of a point's value after Prometheus' conventions; ``None``: not a metric.

    ``repeat`` is the repeated block the point belongs to (a log's entry: not a metric).
    """
    if repeat is not None or point in INFO_LABEL_POINTS:
        return None
    for record, (label, _) in RECORDS.items():
        if point.startswith(record + "_"):
            entry = (label, point.removeprefix(record + "_"))
            return ValueNaming(_unreserved(PREFIX + record), entry=entry)
    base = PREFIX + RENAMED.get(point, point)
    if unit_from:
        return ValueNaming(_unreserved(base), unit_label=True, from_register=True)
    if not unit:
        return ValueNaming(_unreserved(base))
    base_unit = BASE_UNITS.get(unit)
    if base_unit is None:
        return ValueNaming(_unreserved(base), unit_label=True, fixed_unit=unit)
    # ``operating_seconds`` in s stays gateway_operating_seconds, not ..._seconds_seconds.
    suffix = base_unit.suffix
    name = base if base.endswith("_" + suffix) else f"{base}_{suffix}"
    return ValueNaming(_unreserved(name), base=base_unit)


def point_naming(point: Point) -> ValueNaming | None:
    """A profile point's naming; ``None`` for a point that is not a number or not a metric."""
    if point.dtype not in NUMERIC_POINT_TYPES:
        return None
    return value_naming(
        point.name, point.unit, unit_from=point.unit_from is not None, repeat=point.repeat
    )


def _unreserved(name: str) -> str:
    return f"{name}_value" if name in RESERVED_NAMES else name


def help_text(point: Point, naming: ValueNaming) -> str:
    """A family's HELP: the point's meaning, and the base unit where the value was converted.

    A record's family has the record's (its entries' points each describe one entry).
    """
    if naming.entry is not None:
        return RECORDS[naming.family.removeprefix(PREFIX)][1]
    if naming.base is not None and (naming.base.multiply, naming.base.divide) != (1, 1):
        return f"{point.description} (exported in {naming.base.suffix.replace('_', ' ')})"
    return point.description


@functools.cache
def profile_naming(profile_id: str, point_name: str) -> tuple[Point, ValueNaming | None] | None:
    """A profile point and its naming; ``None`` for an unknown profile or point."""
    try:
        point = get_profile(profile_id).point(point_name)
    except ConfigError:
        return None
    return point, point_naming(point)


def is_log_entry(sample: Sample) -> bool:
    """Whether a sample is of an entry of a sensor's log (a profile's repeated block)."""
    known = profile_naming(sample.profile, sample.point)
    return known is not None and known[0].repeat is not None


@functools.cache
def labelled_families() -> frozenset[str]:
    """Value families that carry a ``unit`` label for some point of some built-in profile.

    Decided from the profiles, not from what one scrape happens to hold, so a family's
    label names never change between scrapes: a point without a unit that shares such a
    family gets ``unit=""`` (which Prometheus stores as no label at all).
    """
    families = set()
    for profile in builtin_profiles().values():
        for point in profile.points:
            naming = point_naming(point)
            if naming is not None and naming.unit_label:
                families.add(naming.family)
    return frozenset(families)


def naming_of(sample: Sample) -> tuple[ValueNaming | None, str]:
    """A sample's naming (``None``: not a metric) and the description its family documents."""
    known = profile_naming(sample.profile, sample.point)
    if known is not None:
        point, naming = known
        return naming, help_text(point, naming) if naming is not None else ""
    # A profile the gateway does not ship: judge by the sample's unit alone.
    return value_naming(sample.point, sample.unit), f"{sample.point} of {sample.profile}"
