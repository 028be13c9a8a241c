"""The session with the broker: connect, subscribe, say online, send, take commands, reconnect.

One client at a time, re-entered in a ``while True`` with ``except MqttError`` (aiomqtt
2.5's reconnect loop) on a capped, jittered backoff, to the servers of ``mqtt.servers`` in
turn (:class:`~gateway.publish.mqtt.servers.ServerWalk`). Each session subscribes the
listeners' filters, says ``online`` on ``{base}/status`` (the last will says ``offline`` if
the gateway vanishes), then runs the outbox's sender beside a receiver that hands every
incoming message to the listeners that asked for it. Whatever ends a session ends it whole:
the error goes to the reconnect loop, which logs it and starts the next one. A session on
another server than the first ends cleanly after ``mqtt.return_to_first_s``; what was not
acknowledged goes back to the queue and is sent on the first server.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import random
import socket
import time
from typing import TYPE_CHECKING, Final, Protocol

import aiomqtt
from aiomqtt.exceptions import MqttConnectError

from gateway.publish.mqtt.client import BrokerClient
from gateway.publish.mqtt.identity import (
    CLAIM_ANSWER_S,
    RESEND_AFTER_DEFENCE_S,
    IdentityGuard,
    IdentityTakenError,
)
from gateway.publish.mqtt.outbox import CLIENT_TIMEOUT_S, SUBSCRIBE_TIMEOUT_S, WINDOW
from gateway.publish.mqtt.servers import ServerWalk

if TYPE_CHECKING:
    from collections.abc import Callable

    from gateway.config import MqttConfig
    from gateway.config.brokers import MqttServer
    from gateway.publish.message import Message
    from gateway.publish.mqtt.outbox import Outbox
    from gateway.shared.state import MqttStatus

_LOGGER = logging.getLogger(__name__)

# aiomqtt logs a warning for every publish beyond 10 awaiting completion; the window holds
# 16 on purpose, so it warns only past the window and the few publishes outside it.
PENDING_CALLS_WARNING: Final = WINDOW + 4
BACKOFF_FIRST_S: Final = 0.5
NOT_AUTHORISED: Final = frozenset({4, 5, 134, 135})  # CONNACK: MQTT 3.1.1 4, 5; MQTT 5 134, 135


class Listener(Protocol):
    """Something that takes messages from the broker: commands, feed sources."""

    def subscriptions(self) -> list[str]:
        """The topic filters it wants (subscribed with QoS 1 at every connection)."""
        ...

    async def handle(self, topic: str, payload: bytes, *, retained: bool = False) -> list[Message]:
        """Take one message; what it returns is published (results)."""
        ...


class Connection:
    """Keeps one client connected to the broker, sending the outbox and feeding listeners.

    ``listeners`` is held, not copied: a listener added before :meth:`run` starts is
    subscribed at the first connection.
    """

    def __init__(
        self,
        settings: MqttConfig,
        status: MqttStatus,
        outbox: Outbox,
        *,
        client_id: str,
        listeners: list[Listener],
        for_a_new_server: Callable[[], list[Message]] | None = None,
    ) -> None:
        """Connect with ``settings`` as ``client_id``; report on ``status``.

        ``for_a_new_server`` gives what is sent first on a server of the list other than the
        one of the session before (separate servers share no retained messages).
        """
        self.settings = settings
        self.status = status
        self.outbox = outbox
        self.client_id = client_id
        self.listeners = listeners
        self.base = settings.base_topic
        self._handling: set[asyncio.Task[None]] = set()
        self._claim_echoed = asyncio.Event()  # this session's claim read back (identity)
        self._resend_after = 0.0  # monotonic: the retained state sent again after a defence
        self._rng = random.Random()  # noqa: S311 - jitter only
        self._failures_in_a_row = 0
        self.walk = ServerWalk(settings.server_list(), return_to_first_s=settings.return_to_first_s)
        status.servers = tuple(server.address for server in self.walk.servers)
        status.server = self.walk.current.address
        self.identity = IdentityGuard(self.base, client_id)
        self._for_a_new_server = for_a_new_server
        self._last_server: MqttServer | None = None  # of the last session that connected
        # A new claim (a start, or a reload that rebuilt the connection): a stand-down of
        # the one before is judged anew.
        status.identity_conflict = None
        status.identity_claimed_at = None

    def _client_for(self, server: MqttServer) -> aiomqtt.Client:
        settings = self.settings
        client = broker_client(
            settings,
            server,
            client_id=self.client_id,
            will=aiomqtt.Will(self.identity.status_topic, "offline", qos=1, retain=True),
            clean_session=settings.clean_session,
        )
        client.pending_calls_threshold = PENDING_CALLS_WARNING
        return client

    async def run(self) -> None:
        """Keep connected; send the backlog in order, then live messages, until cancelled.

        On cancellation the gateway says ``offline`` itself (a clean disconnect does not
        fire the will) and what was not sent stays on disk for the next start.
        """
        delay = BACKOFF_FIRST_S
        walk = self.walk
        try:
            while True:
                server = walk.current
                self._show_server()
                try:
                    async with self._client_for(server) as client:
                        try:
                            await self._on_connect(client, server)
                            delay = BACKOFF_FIRST_S
                            if await self._session_while_welcome(client):
                                continue  # back to the first server, at once
                        except asyncio.CancelledError:
                            await self._say_offline(client)
                            raise
                        finally:
                            self.status.identity_claimed_at = None
                except aiomqtt.MqttError as exc:
                    self._lost(exc, server)
                except IdentityTakenError as taken:
                    await self._stand_down(str(taken))
                if walk.next():  # every server failed once: wait, longer each round
                    await asyncio.sleep(delay * self._rng.uniform(0.8, 1.2))
                    delay = min(delay * 2, self.settings.reconnect_max_s)
                else:  # the next server at once (a pause only against a tight loop)
                    await asyncio.sleep(BACKOFF_FIRST_S * self._rng.uniform(0.2, 0.4))
        finally:
            for task in self._handling:
                task.cancel()
            self.outbox.close()

    async def _session_while_welcome(self, client: aiomqtt.Client) -> bool:
        """The session, until it fails (raised) or its time on this server is up (True).

        A session on another server than the first ends cleanly after
        ``return_to_first_s``: what was not acknowledged goes back to the queue, the
        gateway says ``offline`` on this server (it no longer publishes there) and the
        walk goes back to the first.
        """
        stay = self.walk.stay_for()
        time_here = asyncio.timeout(stay)
        try:
            async with time_here:
                await self._session(client)
        except TimeoutError:
            if not time_here.expired():
                raise
        if not time_here.expired():
            return False
        away = self.walk.current.address
        self.outbox.lost()
        self.outbox.update_status()
        await self._say_offline(client)
        self.walk.first()
        _LOGGER.info(
            "MQTT: %.0f s on %s: back to the first server, %s",
            stay or 0.0,
            away,
            self.walk.current.address,
        )
        return True

    async def _stand_down(self, why: str) -> None:
        """Another gateway holds this identity: publish nothing until the config is fixed.

        Disconnected cleanly (no will: the other gateway is online under this base topic);
        messages keep going to the queue on disk, within its bound.
        """
        self.outbox.lost()
        self.status.identity_conflict = why
        self.status.last_error = why
        self.outbox.update_status()
        _LOGGER.error("MQTT: %s", why)
        await asyncio.Event().wait()  # until a reload or a stop cancels the connection

    def _show_server(self) -> None:
        self.status.server = self.walk.current.address
        self.status.switches = self.walk.switches

    async def _say_offline(self, client: aiomqtt.Client) -> None:
        with contextlib.suppress(aiomqtt.MqttError, TimeoutError):
            async with asyncio.timeout(2):
                await client.publish(self.identity.status_topic, "offline", qos=1, retain=True)

    async def _on_connect(self, client: aiomqtt.Client, server: MqttServer) -> None:
        if self._failures_in_a_row:
            _LOGGER.info("MQTT: connected to %s again", server.address)
        elif self.walk.several:
            _LOGGER.info("MQTT: connected to %s", server.address)
        self._failures_in_a_row = 0
        self.status.last_error = None
        # Subscribed before saying online: a plant system may send a command as soon as it
        # sees ``online``, and a clean session drops what arrives before the subscription
        # (the soak lost a command sent while a broker restart's backlog drained). The
        # backlog drains in the session, while commands are already taken.
        for topic_filter in self._filters():
            await client.subscribe(topic_filter, qos=1, timeout=SUBSCRIBE_TIMEOUT_S)
        # The owner marker: read (a retained one arrives first), then claimed; the status
        # watched for another client's will (publish/mqtt/identity).
        await client.subscribe(self.identity.topic, qos=1, timeout=SUBSCRIBE_TIMEOUT_S)
        await client.subscribe(self.identity.status_topic, qos=1, timeout=SUBSCRIBE_TIMEOUT_S)
        await client.publish(self.identity.status_topic, "online", qos=1, retain=True)
        claim = self.identity.claim()
        await client.publish(claim.topic, claim.payload, qos=1, retain=True)
        if self._last_server not in (None, server) and self._for_a_new_server is not None:
            self.outbox.enqueue(self._for_a_new_server())
        self._last_server = server
        self.status.identity_claimed_at = time.monotonic()

    def _lost(self, exc: aiomqtt.MqttError, server: MqttServer) -> None:
        """Note the failure, loudly at the first of a streak; the outbox keeps what was unsent."""
        was_connected = self.outbox.lost()
        self._failures_in_a_row += 1
        rc = getattr(exc, "rc", None)
        code = getattr(rc, "value", rc)
        refused = isinstance(exc, MqttConnectError) and code in NOT_AUTHORISED
        if refused:
            who = self.settings.username or "an anonymous client"
            reason = f"the broker refused the credentials of {who} ({exc})"
        else:
            reason = f"{server.address}: {exc}"
        self.status.last_error = reason
        log = _LOGGER.error if refused else _LOGGER.warning
        if was_connected or self._failures_in_a_row == 1:
            then = "trying the next server" if self.walk.several else "retrying"
            log("MQTT: %s; buffering on disk and %s", reason, then)
        else:
            _LOGGER.debug("MQTT: %s", reason)
        self.outbox.update_status()

    async def _session(self, client: aiomqtt.Client) -> None:
        """Send, and take messages for the listeners, until the connection fails."""
        self._claim_echoed.clear()
        try:
            async with asyncio.TaskGroup() as group:
                group.create_task(self._receive_forever(client))
                if self.identity.newcomer:
                    await self._until_the_claim_stands()
                group.create_task(self.outbox.send_forever(client))
        except* (IdentityTakenError, aiomqtt.MqttError) as ended:
            # One handler for both: a stand-down as the connection drops (seen) made two
            # handlers raise one each, which left as a group that ended the task. The
            # reconnect loop handles one error, the stand-down first.
            first = next(
                (e for e in ended.exceptions if isinstance(e, IdentityTakenError)),
                ended.exceptions[0],
            )
            raise first from None

    async def _until_the_claim_stands(self) -> None:
        """Until the run's claim has stood: nothing published until a live holder could answer.

        The claim read back from the broker has reached every subscriber of the marker, a
        live holder too; if the marker named another run, :data:`CLAIM_ANSWER_S` more is
        its time to answer. A stand-down read meanwhile ends the session (the receiver
        raises). Without the echo (a broker whose ACL lets this client write the marker but
        not read it) the wait ends after a publish's timeout.
        """
        with contextlib.suppress(TimeoutError):
            async with asyncio.timeout(CLIENT_TIMEOUT_S):
                await self._claim_echoed.wait()
        if self.identity.answer_awaited:
            await asyncio.sleep(CLAIM_ANSWER_S)
        self.identity.has_stood()

    def _filters(self) -> list[str]:
        """The listeners' topic filters, each once."""
        return list(
            dict.fromkeys(f for listener in self.listeners for f in listener.subscriptions())
        )

    async def _receive_forever(self, client: aiomqtt.Client) -> None:
        """Hand every message to the listeners that subscribed to it, each in its own task.

        A command can take seconds (post-write waits, a measurement): it must hold up
        neither the next message nor the publishing.
        """
        async for message in client.messages:
            topic = message.topic
            payload = message.payload
            data = payload if isinstance(payload, bytes) else str(payload or "").encode()
            if topic.value == self.identity.topic:
                self._judge(client, data, retained=message.retain)
                continue
            if topic.value == self.identity.status_topic:
                answer = self.identity.answer_status(data, retained=message.retain)
                say_at_once(client, answer, self._handling)
                continue
            for listener in self.listeners:
                if any(topic.matches(f) for f in listener.subscriptions()):
                    task = asyncio.create_task(
                        self._handle(listener, topic.value, data, retained=message.retain)
                    )
                    self._handling.add(task)
                    task.add_done_callback(self._handling.discard)

    def _judge(self, client: aiomqtt.Client, payload: bytes, *, retained: bool) -> None:
        """The identity guard's answer to a marker, at once; a defence resends the retained.

        The newcomer may have written over this gateway's retained messages (availability,
        discovery, the records head) had its wait been too short: they go again, queued,
        at most once in :data:`RESEND_AFTER_DEFENCE_S` (a flood of claims is not a flood
        of discovery configs).
        """
        answer = self.identity.judge(payload, retained=retained)
        if self.identity.echoed:
            self._claim_echoed.set()
        say_at_once(client, answer, self._handling)
        now = time.monotonic()
        if answer and self._for_a_new_server is not None and now >= self._resend_after:
            self._resend_after = now + RESEND_AFTER_DEFENCE_S
            self.outbox.enqueue(self._for_a_new_server())

    async def _handle(
        self, listener: Listener, topic: str, payload: bytes, *, retained: bool
    ) -> None:
        """One message to one listener; its replies (results) queue like any message."""
        try:
            replies = await listener.handle(topic, payload, retained=retained)
        except Exception:
            _LOGGER.exception("MQTT: handling %s failed", topic)
            return
        if replies:
            self.outbox.enqueue(replies)


def say_at_once(
    client: aiomqtt.Client, messages: list[Message], tasks: set[asyncio.Task[None]]
) -> None:
    """The identity's messages beside the queue, not behind a backlog (a task kept in ``tasks``).

    A newcomer waits for the answer; a lost one is of no use later (the session's end ends
    it, and the next session claims again).
    """
    if not messages:
        return

    async def say() -> None:
        with contextlib.suppress(aiomqtt.MqttError, TimeoutError):
            for message in messages:
                await client.publish(
                    message.topic,
                    message.payload,
                    qos=message.qos,
                    retain=message.retain,
                    timeout=CLIENT_TIMEOUT_S,
                )

    task = asyncio.create_task(say())
    tasks.add(task)
    task.add_done_callback(tasks.discard)


def broker_client(
    settings: MqttConfig,
    server: MqttServer,
    *,
    client_id: str,
    will: aiomqtt.Will,
    clean_session: bool,
) -> aiomqtt.Client:
    """A client of one server of the list (its address and TLS; credentials, keepalive).

    The plain topics' connection and the Sparkplug session each have one, with a will and
    a session kind of their own.
    """
    tls = None
    if server.tls is not None:
        tls = aiomqtt.TLSParameters(
            ca_certs=str(server.tls.ca) if server.tls.ca else None,
            certfile=str(server.tls.cert) if server.tls.cert else None,
            keyfile=str(server.tls.key) if server.tls.key else None,
        )
    return BrokerClient(
        server.host,
        server.port,
        username=settings.username,
        password=settings.password.get_secret_value() if settings.password else None,
        identifier=client_id,
        will=will,
        clean_session=clean_session,
        keepalive=settings.keepalive,
        tls_params=tls,
        timeout=CLIENT_TIMEOUT_S,
        # Small packets at once: without it Nagle's algorithm and delayed ACKs hold
        # publishes back by tens of milliseconds.
        socket_options=[(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)],
    )
