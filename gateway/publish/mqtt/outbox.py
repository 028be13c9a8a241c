"""Messages on their way to the broker: the live queue, the disk queue, and the sender.

The bus tasks only hand messages over (:meth:`Outbox.enqueue`, which never waits); the
sender (:meth:`Outbox.send_forever`, run by the connection while it is up) is the one that
publishes. A message leaves the queues only once the broker acknowledged it (QoS 1's
PUBACK), so what was handed over is never lost to a broker outage.

``mqtt.persist`` says when a message is written to
:class:`gateway.publish.store.MessageStore` on disk. ``outage`` (the default): only while
the broker is away (and what was in flight when a session ended); while connected nothing
is written, which an SD card lives on for years, and a kill loses the messages in flight
(those handed over in the last milliseconds). ``always``: every message, as it is handed
over and before it is sent, deleted there once acknowledged; a kill or a crash loses
nothing that was handed over, for some 60 KB written per poll cycle (the manual: What
survives a power cut). Either way, what waits on disk is sent after a restart or when
the broker is back, first, in order, before anything newer.
"""

from __future__ import annotations

import asyncio
import logging
from collections import deque
from typing import TYPE_CHECKING, Any, Final

import aiomqtt
import paho.mqtt.client as mqtt

if TYPE_CHECKING:
    from collections.abc import Callable, Coroutine

    from gateway.publish.message import Message
    from gateway.publish.store import MessageStore
    from gateway.shared.state import MqttStatus

_LOGGER = logging.getLogger(__name__)

BATCH: Final = 100  # messages read from disk at a time while a backlog drains
# Publishes awaiting their PUBACK at once: below paho's own limit of 20 in flight, beyond
# which it would hold messages back in a queue of its own.
WINDOW: Final = 16
CLIENT_TIMEOUT_S: Final = 4.0  # connect, PUBACK and disconnect: within the app's stop bound
# A SUBACK may take longer: a clustered broker (NATS's JetStream MQTT) makes each QoS 1
# subscription a replicated consumer, which waits for a leader while the cluster elects one
# after a node failure. Seen up to 10 s; with 4 s the gateways gave up and walked the list
# again and again while the cluster settled, and the late SUBACK was logged as an error.
SUBSCRIBE_TIMEOUT_S: Final = 15.0

NOT_STORED: Final = 0  # the id of a live message that is not on disk (``persist: outage``)

# A live publish in flight: paho's receipt, published once the broker acknowledged it.
_InFlight = mqtt.MQTTMessageInfo
# The sender's window: each publish in flight with the loop time it was started at.
_Window = deque[tuple[_InFlight, float]]
# A publish of the disk queue in flight, with the message's id in the store.
_Draining = deque[tuple[int, "asyncio.Task[None]"]]


class Outbox:
    """The messages handed over and not yet acknowledged, in order, and their sender.

    ``connected`` is true while the sender runs with the backlog drained: only then do new
    messages go out at once (with ``write_ahead``, once written to disk). The connection
    clears it when the session ends (:meth:`lost`), and the sender sets it again once the
    backlog is out.
    """

    def __init__(
        self, store: MessageStore, status: MqttStatus, *, write_ahead: bool = False
    ) -> None:
        """Send what ``store`` holds first; keep ``status`` (the metrics' view) current.

        ``write_ahead`` (``mqtt.persist: always``): every message is written to ``store``
        before it is sent; otherwise only while not connected.
        """
        self.store = store
        self.status = status
        self.write_ahead = write_ahead
        self.connected = False
        # Sent, or to be sent, at once: each message with its id in the store (NOT_STORED
        # without write_ahead), in order; the first ones are the window in flight.
        self._live: deque[tuple[int, Message]] = deque()
        self._wake = asyncio.Event()

    def enqueue(self, messages: list[Message]) -> None:
        """Hand messages over, in order, without waiting.

        With ``write_ahead`` to disk first; out at once while connected (the backlog
        sent); otherwise to disk, in order, behind what waits there.
        """
        store = self.store
        dropped = store.dropped
        if self.write_ahead:
            ids = store.put(messages)  # before it can be sent: what was sent is on disk
            if self.connected:
                self._live.extend(zip(ids, messages, strict=True))
        elif self.connected:  # connected: the sender found the disk queue empty
            self._live.extend((NOT_STORED, m) for m in messages)
            store.retry()  # nothing written now: a failed file is tried again all the same
        else:
            store.append(messages)
        if store.dropped > dropped:
            _LOGGER.warning(
                "MQTT queue full: dropped the %d oldest messages", store.dropped - dropped
            )
        self.update_status()
        self._wake.set()

    def update_status(self) -> None:
        """The queue's depth, drops and connection, as ``/healthz`` and the metrics show."""
        status = self.status
        live = 0 if self.write_ahead else len(self._live)  # else they are in the store too
        status.queue_depth = len(self.store) + live
        status.dropped = self.store.dropped
        status.connected = self.connected

    def lost(self) -> bool:
        """The session ended: unsent live messages go to the head of the disk queue.

        With ``write_ahead`` they are there already, in order. Returns whether it was
        connected (the backlog drained) until now.
        """
        was_connected = self.connected
        self.connected = False
        if self._live and not self.write_ahead:
            backlog = self.store.peek(len(self.store))  # normally empty: live implies drained
            self.store.remove([i for i, _ in backlog])
            self.store.append([*(m for _, m in self._live), *(m for _, m in backlog)])
        self._live.clear()
        return was_connected

    def close(self) -> None:
        """Keep what was not sent on disk for the next start, and close the store."""
        self.connected = False
        if self._live and not self.write_ahead:
            self.store.append([m for _, m in self._live])
        self._live.clear()
        self.update_status()
        self.store.close()

    async def send_forever(self, client: aiomqtt.Client) -> None:
        """Send live messages in order, up to :data:`WINDOW` awaiting their PUBACK at once.

        The first messages of the live queue are the ones in flight; each leaves the queue
        (and the disk) only once acknowledged, so on a lost connection the unacknowledged
        ones are on disk and are sent again (QoS 1 allows the duplicate). One publish at a
        time moved only some 550 messages a second out of a gateway polling 480 devices:
        each PUBACK waited its turn in a busy event loop.

        The loop wakes on a new message as well as on an acknowledgement (a PUBACK
        sets the same event), so a cycle handed over while the window waits for a PUBACK
        goes out at once, not after it. A publish carries no timer of its own: the oldest
        unacknowledged one is given :data:`CLIENT_TIMEOUT_S`, as aiomqtt gave each. The
        end of the session wakes it too, so that a lost connection ends it at once.
        """
        window: _Window = deque()
        wake = self._wake
        loop = asyncio.get_running_loop()
        wake_on_puback(client, wake)
        # The session's publish and its end, looked up once, not at every turn.
        publish = _direct_publish(client)
        disconnected = client._disconnected  # noqa: SLF001 - see _direct_publish
        while True:
            if not self.connected:  # a new session: newer messages queue behind the backlog
                await self._drain(client)  # the backlog first, before anything newer
                self.connected = True  # no wait since the disk was found empty: in order
                self.update_status()
            wake.clear()
            self._retire(window, disconnected)
            if len(window) < WINDOW and len(self._live) > len(window):
                self._fill(publish, window, loop.time())
            if not window:
                self.update_status()
                await wake.wait()
                continue
            if wake.is_set():
                continue
            try:
                async with asyncio.timeout_at(window[0][1] + CLIENT_TIMEOUT_S):
                    await wake.wait()
            except TimeoutError:
                raise aiomqtt.MqttError("Operation timed out") from None

    async def _drain(self, client: aiomqtt.Client) -> None:
        """Send the disk queue in order, removing each message as the broker acknowledges it.

        Not a batch at a time: a kill while a batch was in flight would send its
        acknowledged messages once more after the restart.
        """
        while batch := self.store.peek(BATCH):
            window: _Draining = deque()
            try:
                for key, m in batch:
                    if len(window) == WINDOW:
                        await self._acknowledged(window)
                    window.append((key, _in_flight(_send(client, m))))
                while window:
                    await self._acknowledged(window)
            finally:
                for _, task in window:
                    task.cancel()

    async def _acknowledged(self, window: _Draining) -> None:
        """Wait for the oldest publish; forget it, and those behind it already acknowledged."""
        key, task = window.popleft()
        await task
        done = [key]
        while window and _succeeded(window[0][1]):
            done.append(window.popleft()[0])
        self.store.remove(done)
        self.status.published += len(done)
        self.update_status()
        _cancelled_meanwhile()

    def _retire(self, window: _Window, disconnected: asyncio.Future[None]) -> None:
        """The acknowledged head of the window leaves it, the live queue and the disk, in order."""
        live = self._live
        acknowledged: list[int] = []
        while window and window[0][0].is_published():
            window.popleft()
            acknowledged.append(live.popleft()[0])
        if acknowledged:
            self.status.published += len(acknowledged)
            if self.write_ahead:
                self.store.remove(acknowledged)  # one transaction for the lot
        if disconnected.done():
            cause = _why_ended(disconnected)
            said = f" ({cause})" if cause is not None else ""
            raise aiomqtt.MqttError(f"the broker closed the connection{said}") from cause

    def _fill(
        self, publish: Callable[[str, bytes, int, bool], _InFlight], window: _Window, now: float
    ) -> None:
        """Start the live messages behind the window until it is full."""
        live = self._live
        while len(window) < WINDOW and len(live) > len(window):
            message = live[len(window)][1]
            window.append(
                (publish(message.topic, message.payload, message.qos, message.retain), now)
            )


def _direct_publish(client: aiomqtt.Client) -> Callable[[str, bytes, int, bool], _InFlight]:
    """Paho's own publish of ``client``, checked: its receipt, or the session's error.

    Live messages bypass ``aiomqtt.Client.publish`` on purpose. It runs as a task per
    message (a coroutine, an event, a pending-call context, a count of every pending call),
    which made the MQTT path the largest cost of a gateway polling each second
    (bench/peers.py: about a fifth of its CPU). paho's publish queues the packet on
    aiomqtt's own socket callbacks and gives a receipt that turns published on the PUBACK;
    :func:`wake_on_puback` makes the PUBACK wake the sender. aiomqtt still connects,
    subscribes, receives, reconnects and sends the backlog and everything else.
    """
    paho = client._client  # noqa: SLF001 - aiomqtt's paho client, see above
    disconnected = client._disconnected  # noqa: SLF001

    def publish(topic: str, payload: bytes, qos: int, retain: bool) -> _InFlight:  # noqa: FBT001
        info = paho.publish(topic, payload, qos, retain)
        if info.rc != mqtt.MQTT_ERR_SUCCESS:
            cause = _why_ended(disconnected) if disconnected.done() else None
            raise aiomqtt.MqttCodeError(info.rc, "Could not publish message") from cause
        return info

    return publish


def wake_on_puback(client: aiomqtt.Client, wake: asyncio.Event) -> None:
    """Set ``wake`` at every PUBACK and when the session ends, besides aiomqtt's own handling."""
    paho = client._client  # noqa: SLF001 - see _direct_publish
    aiomqtt_on_publish = paho.on_publish

    def on_publish(*args: Any) -> None:  # noqa: ANN401 - paho's callback signature
        if aiomqtt_on_publish is not None:
            aiomqtt_on_publish(*args)
        wake.set()

    def on_disconnect(disconnected: asyncio.Future[None]) -> None:
        _why_ended(disconnected)  # seen: asyncio logs an error for an exception never read
        wake.set()

    paho.on_publish = on_publish
    client._disconnected.add_done_callback(on_disconnect)  # noqa: SLF001


def _why_ended(disconnected: asyncio.Future[None]) -> BaseException | None:
    """What ended a session (aiomqtt's disconnect future, done), if anything was said."""
    return None if disconnected.cancelled() else disconnected.exception()


async def _send(client: aiomqtt.Client, message: Message) -> None:
    await client.publish(message.topic, message.payload, qos=message.qos, retain=message.retain)


def _cancelled_meanwhile() -> None:
    """Re-raise a cancellation that a publish of the backlog swallowed.

    Cancelling the sender while it awaits a publish's task cancels that task, and aiomqtt's
    publish (``asyncio.wait_for`` on Python 3.11) may return its result rather than the
    cancellation when both arrive together: the sender then went on, sending the rest of
    the backlog and live messages, while its session waited for it to end. Seen when a
    gateway stood down (identity taken) as its backlog drained: it published on for a
    minute under the other gateway's base topic. The task still counts the request.
    """
    task = asyncio.current_task()
    if task is not None and task.cancelling():
        raise asyncio.CancelledError


def _succeeded(task: asyncio.Task[None]) -> bool:
    return task.done() and not task.cancelled() and task.exception() is None


def _in_flight(publish: Coroutine[object, object, None]) -> asyncio.Task[None]:
    """A publish of the backlog's window, as a task whose failure counts as seen.

    Only the head of the window is awaited; when the connection fails, the others fail
    too and are dropped with it (their messages stay queued), which is no news to log.
    """
    task = asyncio.create_task(publish)
    task.add_done_callback(lambda done: done.cancelled() or done.exception())
    return task
