"""The ``mqtt:`` section: the broker, topics, quality of service, the queue, discovery.

``commands:`` (writes over MQTT on or off) is here too: its topics are the plain ones'.
"""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, SecretStr

from gateway.config.brokers import MqttServer, TlsConfig
from gateway.config.fields import BaseTopic, TcpPort  # noqa: TC001 - pydantic resolves them


class _Model(BaseModel):
    # The same as config.model's: declared here, on BaseModel, so ruff still sees pydantic
    # models, whose list defaults are copied per instance.
    model_config = ConfigDict(extra="forbid", frozen=True)


class CommandsConfig(_Model):
    """Writes over MQTT: ``{base}/{device}/{point}/set`` and ``{base}/{device}/command/{name}``."""

    enabled: bool = True  # False: the gateway only reads; set and command topics are ignored


class DiscoveryConfig(_Model):
    """Home Assistant MQTT discovery (opt-in).

    Example::

        DiscoveryConfig(enabled=True, prefix="homeassistant", announce_delay_max_s=5.0)
    """

    enabled: bool = False
    prefix: BaseTopic = "homeassistant"
    announce_delay_max_s: Annotated[
        float,
        Field(
            ge=0,
            le=300,
            description=(
                "Home Assistant's restart (`online` on `{prefix}/status`) reaches every gateway "
                "of a plant at once; each sends its discovery configs again after a random wait "
                "of up to this many seconds, so that tens of gateways do not answer in the same "
                "instant. 5 s by default: the configs are retained, so Home Assistant has its "
                "entities at its start and the re-announce only repairs what a broker lost; "
                "nothing else waits for it, and 5 s spreads tens of gateways apart. 0: at once."
            ),
        ),
    ] = 5.0


class MqttConfig(_Model):
    """The broker connection, topics, quality of service and the store-and-forward queue."""

    enabled: bool = True
    host: Annotated[str, Field(min_length=1)] = "localhost"
    port: TcpPort = 1883
    # Several brokers (or nodes of a cluster), tried in turn; replaces host, port and tls
    # (config.brokers). Empty: the one of host and port.
    servers: list[MqttServer] = []
    # Back to the first server after this long on another; None: stay where it is.
    return_to_first_s: Annotated[float, Field(ge=10, le=86400)] | None = 600.0
    base_topic: BaseTopic = "gateway"
    client_id: str | None = None  # None: gateway-<host name>
    username: str | None = None
    password: SecretStr | None = None  # meant to come from GATEWAY_MQTT__PASSWORD
    qos: Annotated[int, Field(ge=0, le=1)] = 1  # state, status bits, availability, results
    value_qos: Annotated[int, Field(ge=0, le=1)] = 1  # the plain value topics
    tls: TlsConfig | None = None
    clean_session: bool = True  # False: a persistent session on the broker
    keepalive: Annotated[int, Field(ge=5, le=3600)] = 60
    reconnect_max_s: Annotated[float, Field(gt=0, le=3600)] = 30.0
    queue_max: Annotated[int, Field(ge=100, le=10_000_000)] = 100_000  # messages kept offline
    # When messages are written to the queue on disk: "outage", only while the broker is
    # away (nothing is written while connected: an SD card lasts; a kill loses the messages
    # in flight); "always", each before it is sent (a kill loses nothing handed over, for
    # some 30 GB a day of writes at 5 sensors). The manual: What survives a power cut.
    persist: Literal["outage", "always"] = "outage"
    discovery: DiscoveryConfig = DiscoveryConfig()

    def server_list(self) -> list[MqttServer]:
        """The servers to try, in order: ``servers``, or the one of ``host`` and ``port``."""
        return list(self.servers) or [MqttServer(host=self.host, port=self.port, tls=self.tls)]
