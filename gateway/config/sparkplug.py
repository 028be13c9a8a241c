"""The ``sparkplug:`` section: the gateway as a Sparkplug B edge node."""

from __future__ import annotations

from typing import TYPE_CHECKING, Annotated, Final, Literal

from pydantic import AfterValidator, BaseModel, BeforeValidator, ConfigDict, Field

from gateway.config.brokers import MqttServer  # noqa: TC001 - pydantic resolves it at run time
from gateway.profiles import PollGroup

if TYPE_CHECKING:
    from gateway.config.mqtt import MqttConfig


class _Model(BaseModel):
    # The same as config.model's: declared here, on BaseModel, so ruff still sees pydantic
    # models, whose list defaults are copied per instance.
    model_config = ConfigDict(extra="forbid", frozen=True)


def _sparkplug_id(value: str) -> str:
    """A Sparkplug group, edge node or host id: one topic level (Sparkplug 3.0, 4.1.1)."""
    if not value or {"/", "+", "#"} & set(value):
        raise ValueError(f"{value!r} is not a Sparkplug id: one topic level, no '/', '+' or '#'")
    return value


SparkplugId = Annotated[str, Field(min_length=1, max_length=64), AfterValidator(_sparkplug_id)]
Deadband = Annotated[float, Field(ge=0)]


# What a Sparkplug host may get of a device besides the poll groups' points: the care
# report the gateway keeps of it (the manual: Sensor care), its metrics under ``care/``.
CARE_GROUP: Final = "care"
_SPARKPLUG_GROUPS: Final = (*(g.value for g in PollGroup), CARE_GROUP)


def _sparkplug_group(value: object) -> object:
    """A poll group (:class:`PollGroup`) or ``care``; anything else named, with the choices."""
    if value == CARE_GROUP or isinstance(value, PollGroup):
        return value
    if isinstance(value, str) and value in _SPARKPLUG_GROUPS:
        return PollGroup(value)
    choices = ", ".join(_SPARKPLUG_GROUPS)
    raise ValueError(f"{value!r} is not a Sparkplug group: one of {choices}")


SparkplugGroup = Annotated[PollGroup | Literal["care"], BeforeValidator(_sparkplug_group)]
SparkplugGroups = Annotated[list[SparkplugGroup], Field(min_length=1)]


class SparkplugConfig(_Model):
    """Sparkplug B: the gateway as an edge node, beside the plain topics (the manual: Sparkplug B).

    It connects to the broker of ``mqtt:`` (host, port, credentials, TLS, keep-alive) with a
    client of its own, whose last will is the NDEATH; ``mqtt.enabled: false`` leaves it on.
    ``deadband`` applies to every Float metric, ``deadbands`` per device and point (in the
    point's unit); a change smaller than it is not reported by exception.

    ``groups`` are the poll groups whose points are metrics (``device_groups`` per device):
    process values and status by default, what a host expects of a sensor. Diagnostics,
    configuration and identity are polled all the same, but each adds to every DBIRTH (an
    H10 with every group is 312 metrics), so a host gets them only when asked for; so is
    ``care``, the sensor care report of each device (``care/state``, ``care/due``, ...).
    ``birth_wait_s`` bounds how long a device's DBIRTH waits for the unit registers its
    metrics take their unit from (tecLine, Reiss): one birth with its units rather than a
    birth without them and another a second later.
    """

    enabled: bool = False
    group_id: SparkplugId = "water"
    edge_node_id: SparkplugId | None = None  # None: the host name
    primary_host_id: SparkplugId | None = None  # None: publish without waiting for a host
    client_id: str | None = None  # None: spb-<group>-<edge node>
    deadband: Deadband = 0.0
    deadbands: dict[str, dict[str, Deadband]] = {}  # device -> point -> deadband
    groups: SparkplugGroups = [PollGroup.PROCESS, PollGroup.STATUS]
    device_groups: dict[str, SparkplugGroups] = {}
    birth_wait_s: Annotated[float, Field(ge=0, le=600)] = 10.0
    queue_max: Annotated[int, Field(ge=100, le=10_000_000)] = 100_000  # messages kept offline
    # Its own server list (config.brokers); empty: the one of ``mqtt:``.
    servers: list[MqttServer] = []
    # With several servers: how long to wait on one for the primary host's STATE online
    # before moving to the next (Eclipse Tahu's edge client waits 30 s).
    host_wait_s: Annotated[float, Field(ge=1, le=3600)] = 30.0
    # A host's STATE online or a rebirth request reaches every edge node of a plant at
    # once: each waits a random time up to this before its births. 0 (the default, one
    # gateway): at once; a fleet sets a few seconds (the manual: A plant of many cabinets).
    birth_delay_max_s: Annotated[float, Field(ge=0, le=60)] = 0.0

    def server_list(self, mqtt: MqttConfig) -> list[MqttServer]:
        """The servers of the edge node's session, in order (its own, else ``mqtt``'s)."""
        return list(self.servers) or mqtt.server_list()
