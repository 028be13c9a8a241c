"""The value families' names before they followed Prometheus' conventions, for one release.

Before, a value kept the sensor's unit in its name (``gateway_cell_current_nanoamperes``,
``gateway_cip_min_duration_minutes``), a sensor's counts kept their register's name
(``gateway_cip_cycles_total``, a gauge), each entry of a log was a family of its own
(``gateway_logbook_3_oxygen``), and the identity numbers were gauges besides the labels of
``gateway_device_info``. With ``prometheus.legacy_names: true`` these families are exported
again beside the new ones, with the values as the sensor sent them, so that dashboards and
alerts can move one at a time; the next release drops them.

:func:`renames` lists every family that changed, for the migration note (the manual) and
docs/metrics.md, which the tests compare with it.
"""

from __future__ import annotations

import functools
import re
from dataclasses import dataclass
from typing import TYPE_CHECKING, Final

from gateway.errors import ConfigError
from gateway.profiles import builtin_profiles, get_profile
from gateway.publish.prometheus.naming import (
    INFO_LABEL_POINTS,
    NUMERIC_POINT_TYPES,
    PREFIX,
    RESERVED_NAMES,
    ValueNaming,
    point_naming,
)

if TYPE_CHECKING:
    from collections.abc import Mapping

    from gateway.profiles.model import Point

# The unit suffixes of the old names: the sensor's own unit, not converted.
LEGACY_SUFFIXES: Final[Mapping[str, str]] = {
    "°C": "celsius",
    "nA": "nanoamperes",
    "mA": "milliamperes",
    "\u00b5V": "microvolts",
    "\u03bcV": "microvolts",
    "hPa": "hectopascals",
    "mbar": "millibars",
    "s": "seconds",
    "ms": "milliseconds",
    "°": "degrees",
    "mS/cm": "millisiemens_per_centimetre",
    "h": "hours",
    "min": "minutes",
}
LEGACY_NOTE: Final = "prometheus.legacy_names: an old name, removed in the next release"


def legacy_naming(point: str, unit: str | None, *, unit_from: bool = False) -> ValueNaming:
    """The family a point's value had before (the sensor's unit, the point's own name)."""
    base = PREFIX + point
    if unit_from:
        return ValueNaming(_unreserved(base), unit_label=True, from_register=True)
    if not unit:
        return ValueNaming(_unreserved(base))
    suffix = LEGACY_SUFFIXES.get(unit)
    if suffix is None:
        return ValueNaming(_unreserved(base), unit_label=True, fixed_unit=unit)
    name = base if base.endswith("_" + suffix) else f"{base}_{suffix}"
    return ValueNaming(_unreserved(name))


def _unreserved(name: str) -> str:
    return f"{name}_value" if name in RESERVED_NAMES else name


def _point_legacy(point: Point) -> ValueNaming | None:
    """The old naming of a point whose family changed; ``None`` if it is the same."""
    if point.dtype not in NUMERIC_POINT_TYPES:
        return None
    old = legacy_naming(point.name, point.unit, unit_from=point.unit_from is not None)
    new = point_naming(point)
    return None if new is not None and new.family == old.family else old


@functools.cache
def legacy_of(profile_id: str, point_name: str) -> tuple[ValueNaming, str] | None:
    """A profile point's old family and its HELP, where it differs from the new one."""
    try:
        point = get_profile(profile_id).point(point_name)
    except ConfigError:
        return None
    old = _point_legacy(point)
    if old is None:
        return None
    return old, f"{point.description} ({LEGACY_NOTE}; now {_rename(point, old).now})"


@functools.cache
def legacy_labelled_families() -> frozenset[str]:
    """The old families with a ``unit`` label (as ``naming.labelled_families``)."""
    return frozenset(
        old.family
        for profile in builtin_profiles().values()
        for point in profile.points
        if (old := _point_legacy(point)) is not None and old.unit_label
    )


@dataclass(frozen=True, slots=True, order=True)
class Rename:
    """One family that changed: its old name, its new one (``None``: gone), and how."""

    old: str
    new: str | None
    change: str  # what else changed (the unit, the value), or why it is gone; "" if nothing

    @property
    def now(self) -> str:
        """Where the value is now, in a sentence's words."""
        if self.new is None:
            return self.change
        return f"{self.new} ({self.change})" if self.change else self.new


_SUPERSCRIPTS: Final = str.maketrans("0123456789", "⁰¹²³⁴⁵⁶⁷⁸⁹")


def _factor(number: int) -> str:
    """A million and more as a power of ten (``10⁹``), smaller numbers as they are."""
    text = str(number)
    if number >= 10**6 and text.strip("0") == "1":
        return "10" + str(len(text) - 1).translate(_SUPERSCRIPTS)
    return text


def _rename(point: Point, old: ValueNaming) -> Rename:
    """How a point's family changed, in a plant engineer's words."""
    new = point_naming(point)
    if new is None:
        if point.name in INFO_LABEL_POINTS:
            return Rename(old.family, None, "a label of gateway_device_info")
        return Rename(
            old.family, None, "not a metric: an entry of the sensor's log (sensor care reads it)"
        )
    if new.entry is not None:
        label, value = new.entry
        return Rename(old.family, f'{new.family}{{{label}="{value}"}}', "")
    base = new.base
    if base is None or (base.multiply, base.divide) == (1, 1):
        return Rename(old.family, new.family, "")
    times, divided = "\N{MULTIPLICATION SIGN}", "\N{DIVISION SIGN}"
    by = (
        f"{times} {_factor(base.multiply)}"
        if base.multiply != 1
        else f"{divided} {_factor(base.divide)}"
    )
    unit = base.suffix.replace("_", " ")
    return Rename(old.family, new.family, f"in {unit}: the value in {point.unit} {by}")


_INDEX: Final = re.compile(r"^(gateway_[a-z]+)_\d+_")


@functools.cache
def renames() -> tuple[Rename, ...]:
    """Every value family of a built-in profile whose name changed, once each.

    A log's entries are folded into one row, the entry's number as ``N``
    (``gateway_logbook_N_oxygen``).
    """
    found: set[Rename] = set()
    for profile in builtin_profiles().values():
        for point in profile.points:
            old = _point_legacy(point)
            if old is None:
                continue
            rename = _rename(point, old)
            if point.repeat is not None:  # a log's entries: one row
                rename = Rename(_INDEX.sub(r"\1_N_", rename.old), rename.new, rename.change)
            found.add(rename)
    return tuple(sorted(found))
