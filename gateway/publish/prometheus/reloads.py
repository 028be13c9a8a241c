"""The config's last reload as metrics: Prometheus' own names for the same thing.

``gateway_config_last_reload_successful`` is 0 while the file on disk has a problem that a
reload refused (the gateway runs the config it had), and
``gateway_config_last_reload_success_timestamp_seconds`` is when the running config was
last applied (the start counts as one), so that an alert can say "the config was edited
but not applied" the way Prometheus users know from Prometheus and Alertmanager.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from prometheus_client.metrics_core import GaugeMetricFamily, Metric

if TYPE_CHECKING:
    from collections.abc import Iterator

    from gateway.shared.state import GatewayState


def reload_families(snapshot: GatewayState) -> Iterator[Metric]:
    """Whether the last reload was applied, and when the running config last was."""
    status = snapshot.config
    yield GaugeMetricFamily(
        "gateway_config_last_reload_successful",
        "1 if the last reload of the config file was applied (or none was asked for since "
        "the start); 0: the file has a problem and the gateway runs its previous config",
        value=float(status.last_reload_ok),
    )
    yield GaugeMetricFamily(
        "gateway_config_last_reload_success_timestamp_seconds",
        "When the running config was applied, at the start or by the last successful reload",
        value=status.last_success_at,
    )
