"""The naming of values: a point's family, its unit in the name or in a ``unit`` label.

A value is ``gateway_<point>``, with its unit in the name where the profile fixes it
(``gateway_temperature_celsius``) and in a ``unit`` label where a unit register selects it
(``gateway_oxygen{unit="mg/l"}``) or the unit has no conventional name
(``gateway_nominal_slope{unit="nA/ppm"}``). A point whose family would take the name of
another series gets ``_value``. Also the label names every family shares.
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

PREFIX: Final = "gateway_"

# Units the profiles fix, as Prometheus names them in a metric name. The sensor's own unit
# is kept (no conversion to amperes or pascals): the value is the one the sensor sent.
UNIT_SUFFIXES: Final[Mapping[str, str]] = {
    "°C": "celsius",
    "nA": "nanoamperes",
    "mA": "milliamperes",
    "\u00b5V": "microvolts",  # MICRO SIGN, as in the profiles
    "\u03bcV": "microvolts",  # GREEK SMALL LETTER MU, its look-alike
    "hPa": "hectopascals",
    "mbar": "millibars",
    "s": "seconds",
    "ms": "milliseconds",
    "°": "degrees",
    "mS/cm": "millisiemens_per_centimetre",
    "h": "hours",
    "min": "minutes",
}

# Identity numbers that were gauges before they were labels of ``gateway_device_info``
# (``gateway_firmware_version 1503``). Still exported for one release, marked deprecated in
# their HELP and in docs/metrics.md; removed in the next release.
DEPRECATED_IDENTITY_GAUGES: Final = frozenset(
    {"firmware_version", "hardware_version", "hardware_version_major", "hardware_version_minor"}
)
DEPRECATION_NOTE: Final = (
    " (deprecated: a label of gateway_device_info now; this gauge goes in the next release)"
)

_NUMERIC_POINT_TYPES: Final = NUMERIC_TYPES | {DataType.BOOL}
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
    """Where a numeric point's value goes: its family and how its unit is shown.

    Example::

        value_naming("temperature", "°C")  # gateway_temperature_celsius, no unit label
        value_naming("oxygen", None, unit_from=True)  # gateway_oxygen, unit label from the sample
        value_naming("nominal_slope", "nA/ppm")  # gateway_nominal_slope, unit="nA/ppm"
    """

    family: str
    unit_label: bool = False  # the family's samples carry a ``unit`` label
    from_register: bool = False  # ... taken from the sample (a unit register selected it)
    fixed_unit: str | None = None  # ... or this fixed unit without a conventional name


def value_naming(point: str, unit: str | None, *, unit_from: bool = False) -> ValueNaming:
    """The family of a point's value, after Prometheus's naming conventions."""
    base = PREFIX + point
    if unit_from:
        return ValueNaming(_unreserved(base), unit_label=True, from_register=True)
    if not unit:
        return ValueNaming(_unreserved(base))
    suffix = UNIT_SUFFIXES.get(unit)
    if suffix is None:
        return ValueNaming(_unreserved(base), unit_label=True, fixed_unit=unit)
    # ``operating_seconds`` in s stays gateway_operating_seconds, not ..._seconds_seconds.
    name = base if base.endswith("_" + suffix) else f"{base}_{suffix}"
    return ValueNaming(_unreserved(name))


def _unreserved(name: str) -> str:
    return f"{name}_value" if name in RESERVED_NAMES else name


@functools.cache
def _profile_naming(profile_id: str, point_name: str) -> tuple[ValueNaming, str] | None:
    """A profile point's naming and description; ``None`` for an unknown profile or point."""
    try:
        point = get_profile(profile_id).point(point_name)
    except ConfigError:
        return None
    naming = value_naming(point.name, point.unit, unit_from=point.unit_from is not None)
    deprecated = point.name in DEPRECATED_IDENTITY_GAUGES
    return naming, point.description + (DEPRECATION_NOTE if deprecated else "")


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
            if point.dtype in _NUMERIC_POINT_TYPES:
                unit_from = point.unit_from is not None
                naming = value_naming(point.name, point.unit, unit_from=unit_from)
                if naming.unit_label:
                    families.add(naming.family)
    return frozenset(families)


def naming_of(sample: Sample) -> tuple[ValueNaming, str]:
    """A sample's naming and the description its family documents."""
    known = _profile_naming(sample.profile, sample.point)
    if known is not None:
        return known
    # A profile the gateway does not ship: judge by the sample's unit alone.
    return value_naming(sample.point, sample.unit), f"{sample.point} of {sample.profile}"
