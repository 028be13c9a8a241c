"""The brokers a gateway may use: ``mqtt.servers`` and ``sparkplug.servers``, tried in turn.

A plant's cabinets publish into one clustered broker (several nodes) or into several
separate ones. The gateway is connected to one server at a time; when the connection is
lost or refused it tries the next in the list, and it goes back to the first after
``mqtt.return_to_first_s`` (``null``: it stays where it is). Example::

    mqtt:
      servers:
        - {host: broker-a.plant, port: 8883, tls: {ca: /etc/gateway/plant-ca.pem}}
        - {host: broker-b.plant, port: 8883, tls: {ca: /etc/gateway/plant-ca.pem}}
      return_to_first_s: 600

The single ``host``/``port``/``tls`` of one broker stays valid; a list replaces them. The
Sparkplug session uses the same list unless ``sparkplug.servers`` gives its own: with
several, Sparkplug 3.0 (5.10, Primary Host Application STATE in Multiple MQTT Server
Topologies) has the edge node walk to the next server when its primary host is offline on
one, which needs ``sparkplug.primary_host_id``.
"""

from __future__ import annotations

from pathlib import Path  # noqa: TC003 - pydantic resolves annotations at run time
from typing import TYPE_CHECKING, Annotated, Any

from pydantic import BaseModel, ConfigDict, Field

if TYPE_CHECKING:
    from collections.abc import Iterator, Mapping

    from gateway.config.problems import KeyPath


class TlsConfig(BaseModel):
    """TLS to the broker: a CA to trust and, for client authentication, a certificate."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    ca: Path | None = None  # CA certificate (PEM); None: the system's trust store
    cert: Path | None = None  # client certificate (PEM)
    key: Path | None = None  # its private key (PEM)


class MqttServer(BaseModel):
    """One broker (or one node of a cluster) of a server list."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    host: Annotated[str, Field(min_length=1)]
    port: Annotated[int, Field(ge=1, le=65535)] = 1883
    tls: TlsConfig | None = None

    @property
    def address(self) -> str:
        """``host:port`` as logs, ``/healthz`` and the metrics name it (IPv6 in brackets)."""
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"{host}:{self.port}"

    def same_as(self, other: MqttServer) -> bool:
        """Whether both name one server (host names compare without case)."""
        return self.host.lower() == other.host.lower() and self.port == other.port


# The keys of ``mqtt:`` that ``servers`` replaces.
SINGLE_SERVER_KEYS = ("host", "port", "tls")


def check_brokers(data: Mapping[str, Any]) -> Iterator[tuple[KeyPath, str]]:
    """Server lists without repeats, not beside a single host, and Sparkplug's host id."""
    mqtt = data.get("mqtt")
    mqtt = mqtt if isinstance(mqtt, dict) else {}
    mqtt_servers = mqtt.get("servers")
    if isinstance(mqtt_servers, list) and mqtt_servers:
        for key in SINGLE_SERVER_KEYS:
            if key in mqtt:
                message = (
                    f"mqtt.{key} and mqtt.servers are both set: with a server list, give "
                    f"each server its {key} in the list and remove mqtt.{key}"
                )
                yield ("mqtt", key), message
    yield from _repeats(("mqtt", "servers"), mqtt_servers)
    sparkplug = data.get("sparkplug")
    if not isinstance(sparkplug, dict):
        return
    own = sparkplug.get("servers")
    yield from _repeats(("sparkplug", "servers"), own)
    if sparkplug.get("enabled") is not True or sparkplug.get("primary_host_id"):
        return
    servers = own if isinstance(own, list) and own else mqtt_servers
    if isinstance(servers, list) and len(servers) > 1:
        where = "sparkplug.servers" if own else "mqtt.servers"
        message = (
            f"{where} has {len(servers)} servers but no sparkplug.primary_host_id: with "
            "several servers the edge node moves to the next one when its primary host is "
            "offline on one (Sparkplug 3.0, 5.10), so it must know the host's id"
        )
        yield ("sparkplug", "primary_host_id"), message


def _repeats(where: KeyPath, raw: object) -> Iterator[tuple[KeyPath, str]]:
    """Each entry that names a server an earlier entry names already."""
    if not isinstance(raw, list):
        return
    seen: list[tuple[int, MqttServer]] = []
    for index, item in enumerate(raw):
        try:
            server = MqttServer.model_validate(item)
        except ValueError:
            continue  # its own problem is reported by the full validation
        first = next((i for i, s in seen if s.same_as(server)), None)
        if first is not None:
            path = ".".join(str(p) for p in where)
            message = (
                f"{server.address} is already {path}[{first}]: each server once "
                "(a repeat would be tried twice in a row when it is down)"
            )
            yield (*where, index), message
        else:
            seen.append((index, server))
