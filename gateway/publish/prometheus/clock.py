"""The host clock as metrics and in ``/healthz``: synchronised, its error, and whether trusted.

While the kernel does not hold the host clock synchronised, ``set-clock`` and every write
of a calibration date stamp are refused (:mod:`gateway.control.clock_trust`): a state the
plant must hear of before an operator stands at a sensor with a calibration to write. The
kernel is asked at each scrape (one system call).

An unsynchronised clock does not make ``/healthz`` unhealthy: the polling and publishing
are not touched by it, and what acts on ``/healthz`` (a container's health check, a
restart) cannot fix it. It is said there, in its own ``clock`` part, and alerted on from
``gateway_clock_synchronized``.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from prometheus_client.metrics_core import GaugeMetricFamily, Metric

if TYPE_CHECKING:
    from collections.abc import Iterator

    from gateway.shared.state import GatewayState


def clock_families(snapshot: GatewayState) -> Iterator[Metric]:
    """Whether the host clock is synchronised and trusted, and its maximum error."""
    status = snapshot.clock.status()
    yield GaugeMetricFamily(
        "gateway_clock_synchronized",
        "1 while the kernel holds the host clock synchronised (NTP), as timedatectl's "
        "'System clock synchronized'; 0: set-clock and calibration stamps are refused "
        "unless clock.trust_unsynchronised",
        value=float(status.synchronised),
    )
    yield GaugeMetricFamily(
        "gateway_clock_trusted",
        "1 while dates may be written into sensors (set-clock, calibration stamps): the "
        "clock is synchronised, or clock.trust_unsynchronised is set",
        value=float(status.trusted),
    )
    if status.max_error_s is not None:
        yield GaugeMetricFamily(
            "gateway_clock_max_error_seconds",
            "The kernel's maximum error of the host clock (adjtimex); 16 s and more: "
            "not synchronised",
            value=status.max_error_s,
        )


def clock_health(snapshot: GatewayState) -> dict[str, object]:
    """``/healthz``'s ``clock`` part: the status, and what to do while it is not synchronised."""
    return snapshot.clock.status().as_dict()
