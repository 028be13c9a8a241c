"""Sensor care in the metrics: each device's care state and the dates and ratios behind it.

``gateway_care_state{state}`` is a StateSet as Prometheus exposes one (one series per
state, 1 for the device's current state, 0 for the others), labelled ``state``; the dates
are Unix seconds in gauges named ``_timestamp_seconds``, as Prometheus' own are. A gauge
of a figure the device does not have (no projection, no cap) is absent, never 0.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from prometheus_client.metrics_core import GaugeMetricFamily, Metric

from gateway.care import CARE_STATES
from gateway.publish.prometheus.naming import VALUE_LABELS

if TYPE_CHECKING:
    from collections.abc import Iterator

    from gateway.shared.state import GatewayState


def care_families(snapshot: GatewayState) -> Iterator[Metric]:
    """The care families of every device care has assessed."""
    reports = snapshot.care.reports()
    state = GaugeMetricFamily(
        "gateway_care_state",
        "Sensor care: 1 for the device's current care state (ok, due_soon, due, "
        "maintenance, unknown), 0 for the others; the reasons are in the MQTT care document",
        labels=(*VALUE_LABELS, "state"),
    )
    last = GaugeMetricFamily(
        "gateway_last_calibration_timestamp_seconds",
        "Time of the device's last calibration, from its own records, seconds since the Unix epoch",
        labels=VALUE_LABELS,
    )
    due = GaugeMetricFamily(
        "gateway_calibration_due_timestamp_seconds",
        "Time the device's next calibration is due (last calibration plus its interval), "
        "seconds since the Unix epoch",
        labels=VALUE_LABELS,
    )
    slope = GaugeMetricFamily(
        "gateway_slope_ratio",
        "tecLine/Reiss: active slope X_Span over the nominal slope 0x030A (below 0.30: "
        "maintenance, tecLine manual annex 7.3.4)",
        labels=VALUE_LABELS,
    )
    projected = GaugeMetricFamily(
        "gateway_slope_limit_projected_timestamp_seconds",
        "tecLine/Reiss: when the slope's least-squares trend over the calibration history "
        "crosses the maintenance limit, seconds since the Unix epoch; absent without a "
        "trustworthy projection",
        labels=VALUE_LABELS,
    )
    cap = GaugeMetricFamily(
        "gateway_cap_usage_ratio",
        "O-DO H10/H20: measurement counter 0x2091 over its maximum 0x2095 (1: counter "
        "overflow, replace the cap)",
        labels=VALUE_LABELS,
    )
    for report in reports:
        labels = [report.bus, report.device, report.profile]
        for name in CARE_STATES:
            state.add_metric([*labels, name], float(report.state.value == name))
        if report.last_calibration is not None:
            last.add_metric(labels, report.last_calibration.timestamp())
        if report.due is not None:
            due.add_metric(labels, report.due.timestamp())
        if report.slope_ratio is not None:
            slope.add_metric(labels, report.slope_ratio)
        if report.projection is not None:
            projected.add_metric(labels, report.projection.at.timestamp())
        if report.cap_usage is not None:
            cap.add_metric(labels, report.cap_usage)
    yield from (state, last, due, slope, projected, cap)
