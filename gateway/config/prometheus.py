"""The ``prometheus:`` section: where ``/metrics`` and ``/healthz`` are served, and what of."""

from __future__ import annotations

from typing import Annotated

from pydantic import BaseModel, BeforeValidator, ConfigDict, Field

from gateway.config.fields import TcpPort  # noqa: TC001 - pydantic resolves it at run time
from gateway.config.sparkplug import CARE_GROUP
from gateway.profiles import PollGroup


class _Model(BaseModel):
    # The same as config.model's: declared here, on BaseModel, so ruff still sees pydantic
    # models, whose list defaults are copied per instance.
    model_config = ConfigDict(extra="forbid", frozen=True)


def _prometheus_group(value: object) -> object:
    """A poll group (:class:`PollGroup`); anything else named, with the choices."""
    if isinstance(value, PollGroup):
        return value
    choices = ", ".join(g.value for g in PollGroup)
    if isinstance(value, str) and value in {g.value for g in PollGroup}:
        return PollGroup(value)
    if value == CARE_GROUP:
        raise ValueError(
            "'care' is not a poll group: the care metrics (gateway_care_state, ...) are "
            f"always exported; list poll groups only: {choices}"
        )
    raise ValueError(f"{value!r} is not a poll group: one of {choices}")


PrometheusGroup = Annotated[PollGroup, BeforeValidator(_prometheus_group)]
PrometheusGroups = Annotated[list[PrometheusGroup], Field(min_length=1)]


class PrometheusConfig(_Model):
    """Where ``/metrics`` and ``/healthz`` are served, and what they carry (the manual: Prometheus).

    ``groups`` are the poll groups whose points are series (``device_groups`` per device):
    process values and status by default. Diagnostics, configuration and identity are
    polled all the same and go to MQTT; as series they are some 170 more per O-DO H10 that
    rarely change, so Prometheus gets them only when asked for. The gateway's own health,
    sensor care and ``gateway_device_info`` are always exported. ``legacy_names: true``
    exports the values whose names changed (base units, no ``_total`` on gauges, no log
    entries as families) under their old names too, for one release. Example::

        prometheus: {port: 9108, groups: [process, status, diagnostics]}
    """

    enabled: bool = True
    port: TcpPort = 9108
    host: Annotated[str, Field(min_length=1)] = "0.0.0.0"  # noqa: S104 - the documented default
    groups: PrometheusGroups = [PollGroup.PROCESS, PollGroup.STATUS]
    device_groups: dict[str, PrometheusGroups] = {}  # device -> its own groups
    legacy_names: bool = False  # also the old names (until the next release)
