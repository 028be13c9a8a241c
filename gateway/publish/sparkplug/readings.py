"""What a sample or a care report reads as in Sparkplug, and whether it is news: no state.

The ``Quality`` property has one meaning per code (the three codes Sparkplug 3.0 allows,
``tck-id-payloads-propertyset-quality-value-value``):

- 192 (good): the value the sensor holds now; null if it holds none (a date never set);
- 0 (bad): the sensor answered with a fault instead of a value: null, and the property
  ``fault`` names it (``overrange``, ``undecodable``, ...); never the fault float;
- 500 (stale): no current reading: not read yet (in a birth), or its read failed (null).

:class:`~gateway.publish.sparkplug.reports.Reporter` keeps what each device last reported
and asks here what a cycle's samples read as (:func:`readings`), whether a reading is news
to the host (:func:`differs`) and how it goes into a metric (:func:`fill`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Final

from gateway.line.samples import Quality
from gateway.publish.sparkplug import payloads
from gateway.publish.sparkplug.payloads import (
    QUALITY_BAD,
    QUALITY_GOOD,
    QUALITY_STALE,
    Scalar,
    SpType,
)
from gateway.wire.codec import BitfieldValue, EnumValue

if TYPE_CHECKING:
    from collections.abc import Callable, Mapping
    from datetime import datetime

    from gateway.care import CareReport
    from gateway.line.samples import Sample
    from gateway.publish.sparkplug.catalogue import DeviceMetrics, MetricSpec

# The Sparkplug quality of each sample quality (see the module's docstring).
_QUALITY_OF = {
    Quality.GOOD: QUALITY_GOOD,
    Quality.FAULT: QUALITY_BAD,
    Quality.STALE: QUALITY_STALE,
    Quality.COMMS_ERROR: QUALITY_STALE,
}


@dataclass(frozen=True, slots=True)
class Reported:
    """A metric's value as reported: ``None`` for no value; ``fault`` only with bad quality."""

    value: Scalar | None
    quality: int
    time_ms: int
    fault: str | None = None
    unit: str | None = None


def _ms(when: datetime | None) -> int | None:
    return None if when is None else payloads.epoch_ms(when)


def _ratio(value: float | None) -> float | None:
    """A ratio to 4 places, as the care document has it (a finer change is no news)."""
    return None if value is None else round(value, 4)


# What each care metric (catalogue.CARE_METRICS, by name) reads of the report.
CARE_VALUES: Final[Mapping[str, Callable[[CareReport], Scalar | None]]] = {
    "state": lambda report: report.state.value,
    "reasons": lambda report: "; ".join(report.reasons),
    "last_calibration": lambda report: _ms(report.last_calibration),
    "due": lambda report: _ms(report.due),
    "slope_ratio": lambda report: _ratio(report.slope_ratio),
    "slope_limit_projected": lambda report: (
        None if report.projection is None else payloads.epoch_ms(report.projection.at)
    ),
    "cap_usage": lambda report: _ratio(report.cap_usage),
}


def readings(
    metrics: DeviceMetrics, spec: MetricSpec, sample: Sample
) -> list[tuple[MetricSpec, Reported]]:
    """A sample as the reading of its metric (and of its bits' and label's metrics).

    One quality per meaning (see the module's docstring): a good sample is good even
    without a value (a date never set); a fault is bad with its name; a read that
    failed is stale, without a fault.
    """
    time_ms = payloads.epoch_ms(sample.time)
    quality = _QUALITY_OF.get(sample.quality, QUALITY_STALE)
    value = sample.value if sample.quality in {Quality.GOOD, Quality.STALE} else None
    scalar = payloads.scalar_of(value, spec.datatype)
    fault = (sample.fault or sample.quality.value) if quality == QUALITY_BAD else None
    result = [(spec, Reported(scalar, quality, time_ms, fault, sample.unit))]
    flags = dict(value.flags) if isinstance(value, BitfieldValue) else {}
    for bit in metrics.bits_of.get(spec.name, ()):
        state = flags.get(bit.bit or "")
        result.append((bit, Reported(state, quality, time_ms, fault)))
    label = metrics.label_of.get(spec.name)
    if label is not None:
        text = value.label if isinstance(value, EnumValue) else None
        result.append((label, Reported(text, quality, time_ms, fault)))
    return result


def fill(metric: payloads.Metric, spec: MetricSpec, reported: Reported) -> None:
    """The metric's value as reported: null (with its fault, if one) or the value."""
    if reported.value is None:
        metric.is_null = True
        if reported.fault:
            payloads.set_property(metric, payloads.FAULT, SpType.STRING, reported.fault)
    else:
        payloads.set_value(metric, spec.datatype, reported.value)


def differs(spec: MetricSpec, before: Reported | None, now: Reported) -> bool:
    """Whether ``now`` is news to the host: a new quality, or a value past the deadband."""
    if before is None or before.quality != now.quality:
        return True
    if now.unit is not None and now.unit != before.unit:
        return True
    if before.value is None or now.value is None:
        return before.value is not now.value
    if (
        spec.deadband > 0
        and isinstance(now.value, int | float)
        and isinstance(before.value, int | float)
    ):
        return abs(float(now.value) - float(before.value)) >= spec.deadband
    return now.value != before.value
