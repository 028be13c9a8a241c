"""The families of values: numbers, faults, status bits, enums, and the age of each point.

Faults are never numbers: a point whose latest sample is a fault has no value sample, and
``gateway_value_fault{fault="overrange"}`` says why. Strings and date-times are left to MQTT.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from prometheus_client.metrics_core import GaugeMetricFamily, Metric

from gateway.line.samples import Quality
from gateway.publish.prometheus.naming import (
    POINT_LABELS,
    VALUE_LABELS,
    labelled_families,
    naming_of,
)
from gateway.wire.codec import BitfieldValue, EnumValue

if TYPE_CHECKING:
    from collections.abc import Iterator

    from gateway.line.samples import Sample
    from gateway.publish.state import GatewayState

_LOGGER = logging.getLogger(__name__)


@dataclass(slots=True)
class _ValueFamily:
    documentation: str
    rows: dict[tuple[str, ...], tuple[str | None, float]] = field(default_factory=dict)
    has_unit: bool = False


def value_families(snapshot: GatewayState, now: float) -> Iterator[Metric]:
    """Values, faults, status bits, enums and ages of every point's latest sample."""
    values = _Values()
    for sample in snapshot.latest.values():
        if not snapshot.is_stale(sample, now):  # an old reading is not the present
            values.add(sample)
    yield from values.families()
    yield _ages(snapshot, now)


class _Values:
    """The value-like families of one scrape, filled sample by sample."""

    def __init__(self) -> None:
        self._values: dict[str, _ValueFamily] = {}
        self._faults = GaugeMetricFamily(
            "gateway_value_fault",
            "1 while the latest sample of a point is a sensor fault (named in 'fault')",
            labels=[*POINT_LABELS, "fault"],
        )
        self._flags = GaugeMetricFamily(
            "gateway_status_flag",
            "State of one named bit of a status or error word (0 or 1)",
            labels=[*POINT_LABELS, "flag"],
        )
        self._enums = GaugeMetricFamily(
            "gateway_enum_info",
            "The current label (and code) of an enumerated point; always 1",
            labels=[*POINT_LABELS, "label", "code"],
        )

    def add(self, sample: Sample) -> None:
        """Export one latest sample: a fault by name, never a number; comms errors not."""
        point = [sample.bus, sample.device, sample.profile, sample.point]
        if sample.quality is Quality.FAULT:
            self._faults.add_metric([*point, sample.fault or "unknown"], 1.0)
            return
        if sample.quality is not Quality.GOOD:
            return
        value = sample.value
        if isinstance(value, BitfieldValue):
            for flag, state in value.flags:
                self._flags.add_metric([*point, flag], float(state))
        elif isinstance(value, EnumValue):
            self._enums.add_metric([*point, value.label, str(value.code)], 1.0)
        elif isinstance(value, bool | int | float):
            self._add_value(sample, float(value))
        # strings and date-times are not numbers: MQTT carries them

    def _add_value(self, sample: Sample, value: float) -> None:
        naming, description = naming_of(sample)
        unit: str | None = None
        if naming.from_register:
            if not sample.unit:
                return  # the unit register is unread or unknown: a number without its unit
            unit = sample.unit
        elif naming.fixed_unit is not None:
            unit = naming.fixed_unit
        family = self._values.get(naming.family)
        if family is None:
            family = self._values[naming.family] = _ValueFamily(description)
        key = (sample.bus, sample.device, sample.profile)
        if key in family.rows:
            # Two points of one device named into one family (``x`` in s next to a
            # dimensionless ``x_seconds``): no profile has such a pair; keep the first.
            _LOGGER.debug("%s: %s also maps to %s; left out", sample.device, sample.point, naming)
            return
        family.rows[key] = (unit, value)
        family.has_unit |= unit is not None

    def families(self) -> Iterator[Metric]:
        """One gauge per value family (label names fixed per family), then the rest."""
        labelled = labelled_families()
        for name in sorted(self._values):
            family = self._values[name]
            with_unit = family.has_unit or name in labelled
            gauge = GaugeMetricFamily(
                name,
                family.documentation,
                labels=[*VALUE_LABELS, "unit"] if with_unit else VALUE_LABELS,
            )
            for key, (unit, value) in family.rows.items():
                gauge.add_metric([*key, unit or ""] if with_unit else list(key), value)
            yield gauge
        yield from (self._faults, self._flags, self._enums)


def _ages(snapshot: GatewayState, now: float) -> Metric:
    ages = GaugeMetricFamily(
        "gateway_value_age_seconds",
        "Seconds since the last good sample of a polled point",
        labels=POINT_LABELS,
    )
    for (bus, device, point), sample in snapshot.last_good.items():
        info = snapshot.devices.get((bus, device))
        if info is not None and point in info.intervals and info.intervals[point] is None:
            continue  # identity, read once per connection: its age says nothing
        ages.add_metric([bus, device, sample.profile, point], max(0.0, now - sample.monotonic))
    return ages
