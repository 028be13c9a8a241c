"""Home Assistant restarted: every discovery config again, after a random wait of each gateway's.

Home Assistant says ``online`` on ``{prefix}/status`` when it starts (its birth message), and
its MQTT documentation asks devices to send their discovery again then. Every gateway of a
plant hears it at the same instant; answering at once would put all their configs on the
broker and on Home Assistant in one burst, just as it starts. :class:`Reannouncer` answers
after a random wait of up to ``mqtt.discovery.announce_delay_max_s`` instead, drawn per
gateway (:class:`~gateway.publish.discovery.ReannounceGate` decides, without I/O); it is a
:class:`~gateway.publish.mqtt.connection.Listener`, so the connection subscribes it at every
session and sends what it returns like any other message.
"""

from __future__ import annotations

import asyncio
import logging
import random
from typing import TYPE_CHECKING

from gateway.publish.discovery import ReannounceGate, status_topic

if TYPE_CHECKING:
    from collections.abc import Callable

    from gateway.publish.message import Message
    from gateway.publish.mqtt.topics import Topics

_LOGGER = logging.getLogger(__name__)


class Reannouncer:
    """Listens to Home Assistant's status; on its ``online``, the configs again, once.

    ``topics`` gives the sink's current :class:`~gateway.publish.mqtt.topics.Topics` (a
    reload builds new ones): its settings say whether discovery is on, under which prefix and
    with which longest wait, and :meth:`~gateway.publish.mqtt.topics.Topics.announced` what
    to send. ``rng`` draws the waits (seeded in tests); by default one of its own, so that
    gateways started together draw apart.

    Only the configs go again, retained, as they were: the values, status bits and
    availability they point at are retained already, and Home Assistant reads them when it
    subscribes to an entity's topics, so resending them would add a burst for nothing.
    The wait runs in the task the connection gave the message: a stop or a reload cancels
    it with the connection, and nothing is sent.
    """

    def __init__(self, topics: Callable[[], Topics], *, rng: random.Random | None = None) -> None:
        """Take the sink's topics as they are at each message; draw the waits from ``rng``."""
        self._topics = topics
        self._gate = ReannounceGate(rng or random.Random())  # noqa: S311 - a spread, not a secret

    def subscriptions(self) -> list[str]:
        """Home Assistant's status topic while discovery is on; nothing otherwise."""
        discovery = self._topics().settings.discovery
        return [status_topic(discovery.prefix)] if discovery.enabled else []

    async def handle(self, topic: str, payload: bytes, *, retained: bool = False) -> list[Message]:
        """A status message: after the drawn wait, every config announced (or nothing)."""
        discovery = self._topics().settings.discovery
        if not discovery.enabled or topic != status_topic(discovery.prefix):
            return []  # a reload turned discovery off, or moved it, while this was on its way
        verdict = self._gate.on_status(
            payload, retained=retained, delay_max_s=discovery.announce_delay_max_s
        )
        if verdict.delay_s is None:
            _LOGGER.debug("MQTT: %s: no re-announce (%s)", topic, verdict.reason)
            return []
        try:
            _LOGGER.info(
                "MQTT: Home Assistant online: re-announcing %d entities in %.1f s",
                len(self._topics().announced()),
                verdict.delay_s,
            )
            await asyncio.sleep(verdict.delay_s)
        finally:
            self._gate.done()
        return self._topics().announced()  # as they stand now: a device may have come meanwhile
