"""One identity per gateway, Sparkplug's too: the edge node follows the MQTT owner claim.

A copied config copies the edge node's descriptor (``group_id``/``edge_node_id``) with the
base topic and client id, and usually its Sparkplug client id as well. The plain connection
finds the copy with its owner marker (:mod:`gateway.publish.mqtt.identity`) and makes the
newcomer stand down; the Sparkplug session of the newcomer must stand down with it, and,
better, never speak: Sparkplug 3.0 requires the edge node descriptor to be unique
(``tck-id-intro-edge-node-id-uniqueness``, ``tck-id-payloads-nbirth-edge-node-descriptor``),
and a second session under it would be seen by a host as the first node's.

So the session connects only once this gateway's claim has stood: published on a
connection that has then lasted :data:`IDENTITY_SETTLE_S` without being contested. Its
CONNECT would otherwise take the holder's session over when the Sparkplug client ids are
equal (the broker then delivers the holder's will, an NDEATH that a host takes as the
holder's death), or publish an NBIRTH of its own beside the holder's. A newcomer learns of
the holder within that time: at once when the holder reads its claim live, or, when the
plain client ids are equal too, at its second connection, after the holder has thrown it
off (each side reconnects within a second: ``mqtt/connection``'s first backoff).

A stand-down found before connecting publishes nothing: no CONNECT, so no will, no NBIRTH
and no NDEATH. One found while connected (the claim could not stand because the plain
topics' broker was away, and the session went ahead after :data:`IDENTITY_WAIT_MAX_S`)
ends the connection with a DISCONNECT, which tells the broker not to deliver the will,
after an NDEATH only if this connection sent births. That NDEATH carries this session's
``bdSeq``, and a host marks a node offline only on an NDEATH whose ``bdSeq`` matches the
NBIRTH it holds (Sparkplug 3.0, "Death Message (NDEATH)" in Topics and Messages, and "Edge
Node Session Establishment"): the holder's node stays online unless the host's last NBIRTH
of it was this session's, which then rightly dies, as an edge node that leaves on purpose
says (``tck-id-operational-behavior-edge-node-intentional-disconnect-ndeath``). Without
births there is nothing of this session that a host holds, and an NDEATH would only risk
matching the holder's ``bdSeq`` (a copied state directory copies the counter too): none is
sent.
"""

from __future__ import annotations

import asyncio
import logging
import time
from typing import TYPE_CHECKING, Final, NoReturn, Protocol

if TYPE_CHECKING:
    from gateway.shared.state import MqttStatus

_LOGGER = logging.getLogger(__name__)

# How long the plain connection's claim must stand before the Sparkplug session connects:
# several times what a newcomer needs to learn of a holder with the same client id (each
# thrown off once, back after mqtt/connection's first backoff of 0.5 s +-20 %).
IDENTITY_SETTLE_S: Final = 3.0
# Past this the session connects without a claim that stood (the plain topics' broker may
# be away while Sparkplug's, another server, is up): a stand-down found later still ends it.
IDENTITY_WAIT_MAX_S: Final = 30.0
POLL_S: Final = 0.1  # the status is read this often while the claim is awaited
WATCH_S: Final = 0.5  # and this often while connected


class IdentityConflictError(Exception):
    """Another gateway holds this gateway's identity: the Sparkplug session stands down."""


class IdentityWatch(Protocol):
    """What the Sparkplug session asks of the gateway's identity."""

    async def held(self) -> None:
        """Return once the session may connect; raise :class:`IdentityConflictError` if never."""
        ...

    async def contested(self) -> NoReturn:
        """Raise :class:`IdentityConflictError` once the identity is found to be another's."""
        ...


class GatewayIdentity:
    """The MQTT connection's verdict on the owner marker, read from its status.

    The connection alone writes ``identity_conflict`` and ``identity_claimed_at``; this
    only reads them.
    """

    def __init__(
        self,
        mqtt: MqttStatus,
        *,
        settle_s: float = IDENTITY_SETTLE_S,
        wait_max_s: float = IDENTITY_WAIT_MAX_S,
    ) -> None:
        """Follow the connection that reports on ``mqtt``."""
        self.mqtt = mqtt
        self.settle_s = settle_s
        self.wait_max_s = wait_max_s

    def _conflict(self) -> IdentityConflictError | None:
        why = self.mqtt.identity_conflict
        return None if why is None else IdentityConflictError(why)

    async def held(self) -> None:
        """Until the claim has stood ``settle_s`` on one connection (at once without MQTT)."""
        give_up = time.monotonic() + self.wait_max_s
        while True:
            if (conflict := self._conflict()) is not None:
                raise conflict
            if not self.mqtt.enabled:
                return
            now = time.monotonic()
            since = self.mqtt.identity_claimed_at
            if since is not None and now - since >= self.settle_s:
                return
            if now >= give_up:
                _LOGGER.warning(
                    "Sparkplug: the MQTT connection has not held the gateway's identity "
                    "(its owner marker) for %.0f s within %.0f s; connecting without it",
                    self.settle_s,
                    self.wait_max_s,
                )
                return
            await asyncio.sleep(POLL_S)

    async def contested(self) -> NoReturn:
        """Read the verdict every :data:`WATCH_S` while the session runs."""
        # Read as /healthz reads it: an event beside the status would be a second copy of
        # the verdict for its one writer to keep in step, for a check that may take 0.5 s.
        while (conflict := self._conflict()) is None:  # noqa: ASYNC110
            await asyncio.sleep(WATCH_S)
        raise conflict
