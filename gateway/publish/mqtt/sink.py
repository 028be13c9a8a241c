"""The MQTT sink: a poll cycle becomes the contract's messages, handed over to be sent at once.

:class:`MqttSink` is what the bus tasks and the app see; it only joins the pieces. Its
:meth:`~MqttSink.publish` builds a cycle's messages (:class:`~gateway.publish.mqtt.topics.Topics`)
and hands them to the outbox (:class:`~gateway.publish.mqtt.outbox.Outbox`) without waiting:
no batching and no timer, the sender wakes on them. Its :meth:`~MqttSink.run` is the
connection (:class:`~gateway.publish.mqtt.connection.Connection`), the one task that talks
to the broker.
"""

from __future__ import annotations

import socket
from typing import TYPE_CHECKING

from gateway.errors import PublishError
from gateway.publish.mqtt.connection import Connection
from gateway.publish.mqtt.outbox import Outbox
from gateway.publish.mqtt.reannounce import Reannouncer
from gateway.publish.mqtt.topics import Topics
from gateway.publish.store import MessageStore

if TYPE_CHECKING:
    import random
    from collections.abc import Callable, Iterable, Mapping, Sequence
    from pathlib import Path

    from gateway.config import MqttConfig, PublishSettings
    from gateway.line.samples import DeviceEvent, Sample
    from gateway.profiles import Profile
    from gateway.publish.message import Message
    from gateway.publish.mqtt.connection import Listener
    from gateway.shared.state import GatewayState


def check_tls_files(settings: MqttConfig, section: str) -> None:
    """Every TLS file of the server list exists (a missing one fails at start, not later)."""
    servers = settings.server_list()
    for index, server in enumerate(servers):
        if server.tls is None:
            continue
        where = f"{section}.servers[{index}].tls" if settings.servers else f"{section}.tls"
        for name in ("ca", "cert", "key"):
            path = getattr(server.tls, name)
            if path is not None and not path.is_file():
                raise PublishError(f"{where}.{name}: {path} does not exist")


class MqttSink:
    """Publishes samples and availability; keeps the broker connection up.

    ``listeners`` (commands, feed sources) may be appended to until :meth:`run` starts.
    The sink adds one of its own: Home Assistant's restart heard, the discovery sent again
    (:class:`~gateway.publish.mqtt.reannounce.Reannouncer`; it subscribes only while
    discovery is on).
    """

    def __init__(
        self,
        settings: MqttConfig,
        state: GatewayState,
        *,
        state_dir: Path,
        publish: Mapping[tuple[str, str], PublishSettings] | None = None,
        listeners: Sequence[Listener] = (),
        retained_also: Callable[[], list[Message]] | None = None,
        rng: random.Random | None = None,
    ) -> None:
        """Check the settings that can fail at start (TLS files, the state directory).

        ``retained_also``: the retained messages of other parts (the records' head), sent
        again with this sink's own where a server may lack them. ``rng`` draws the waits
        before a re-announce (seeded in tests; by default the re-announcer's own).
        """
        self.state = state
        self._retained_also = retained_also
        self.state_dir = state_dir
        self.listeners = list(listeners)
        self._build(settings, publish)
        # Reads the topics of the moment: a reload's reconfigure builds new ones.
        self.listeners.append(Reannouncer(lambda: self.topics, rng=rng))

    def _build(
        self, settings: MqttConfig, publish: Mapping[tuple[str, str], PublishSettings] | None
    ) -> None:
        """The topics, the queue on disk and the connection, for these settings."""
        client_id = settings.client_id or f"gateway-{socket.gethostname()}"
        topics = Topics(settings, self.state, client_id=client_id, publish=publish)
        check_tls_files(settings, "mqtt")
        store = MessageStore(self.state_dir / "mqtt-queue.sqlite", max_messages=settings.queue_max)
        self.state.storage.track(store.health)
        status = self.state.mqtt
        status.enabled = True
        status.queue_max = settings.queue_max
        status.queue_depth = len(store)
        self.settings = settings
        self.client_id = client_id
        self.topics = topics
        self.outbox = Outbox(store, status, write_ahead=settings.persist == "always")
        self.connection = Connection(
            settings,
            status,
            self.outbox,
            client_id=client_id,
            listeners=self.listeners,
            for_a_new_server=self._for_a_new_server,
        )

    def _for_a_new_server(self) -> list[Message]:
        """The retained state again: on another server of the list, or after a defence.

        The topics of the moment: a reload's reconfigure builds new ones.
        """
        also = self._retained_also() if self._retained_also is not None else []
        return self.topics.for_a_new_server() + also

    def reconfigure(
        self, settings: MqttConfig, publish: Mapping[tuple[str, str], PublishSettings]
    ) -> None:
        """New settings after a reload, while :meth:`run` is not running.

        The queue on disk is opened again where the stopped connection left it, so nothing
        that was not acknowledged is lost; the topics start afresh (a device's document
        count included), as after a restart.
        """
        self._build(settings, publish)

    def set_publish(self, publish: Mapping[tuple[str, str], PublishSettings]) -> None:
        """The publish settings per ``(device, point)`` after a reload (same connection)."""
        self.topics.set_publish(publish)

    def replan(self, bus: str, device: str, profile: Profile, dropped: Iterable[str]) -> None:
        """A device a reload changed: announced anew, the points it no longer polls cleared."""
        self.outbox.enqueue(self.topics.replan(bus, device, profile, dropped))

    def forget(self, bus: str, device: str, profile: Profile, points: Iterable[str]) -> None:
        """A device a reload removed: offline, its retained topics and discovery cleared."""
        self.outbox.enqueue(self.topics.forget(bus, device, profile, points))

    async def publish(self, samples: Sequence[Sample]) -> None:
        """Turn one device's poll cycle into messages and hand them to the sender."""
        if not samples:
            return
        self.outbox.enqueue(self.topics.cycle(samples))

    async def device_event(self, event: DeviceEvent) -> None:
        """Publish a device's availability (retained)."""
        self.outbox.enqueue([self.topics.availability(event)])

    async def run(self) -> None:
        """Keep connected and send, until cancelled (see :meth:`Connection.run`)."""
        await self.connection.run()
