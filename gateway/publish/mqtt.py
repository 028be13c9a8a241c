"""MQTT: the contract's topics, publish modes, and store-and-forward across broker outages.

Topics under ``{base}``: ``{base}/{device}/{point}`` plain value (retained),
``{base}/{device}/state`` one JSON document per poll cycle, ``{base}/{device}/status/{flag}``
``true``/``false`` per named status or error bit (retained), ``{base}/{device}/availability``
``online``/``offline`` (retained) and ``{base}/status`` for the gateway itself (the last will).

A value in fault or unreadable is never published as a number: its plain topic is cleared
(an empty retained payload, so no stale number lingers) and the state document names the
fault. The bus tasks only hand messages over; a sender task owns the connection, and what
cannot go out at once is kept in :class:`gateway.publish.store.MessageStore` and sent first, in
order, when the broker is back (aiomqtt 2.5's reconnect loop: one client re-entered in a
``while True`` with ``except MqttError``).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import math
import random
import socket
import time
from collections import deque
from dataclasses import dataclass
from typing import TYPE_CHECKING, Final, Protocol

import aiomqtt
from aiomqtt.exceptions import MqttConnectError

from gateway.config import PublishMode, PublishSettings
from gateway.errors import PublishError
from gateway.line.samples import Quality, hex_registers, json_value
from gateway.profiles import get_profile
from gateway.publish.discovery import discovery_messages
from gateway.publish.message import Message
from gateway.publish.state import STALE_FACTOR, STALE_MARGIN_S
from gateway.publish.store import MessageStore
from gateway.wire.codec import BitfieldValue

if TYPE_CHECKING:
    from collections.abc import Coroutine, Mapping, Sequence
    from datetime import datetime
    from pathlib import Path

    from gateway.config import MqttConfig
    from gateway.line.samples import DeviceEvent, Sample
    from gateway.publish.state import GatewayState

_LOGGER = logging.getLogger(__name__)

BATCH: Final = 100  # messages read from disk at a time while a backlog drains
# Publishes awaiting their PUBACK at once: below paho's own limit of 20 in flight, beyond
# which it would hold messages back in a queue of its own.
WINDOW: Final = 16
# aiomqtt logs a warning for every publish beyond 10 awaiting completion; the window holds
# 16 on purpose, so it warns only past the window and the few publishes outside it.
PENDING_CALLS_WARNING: Final = WINDOW + 4
BACKOFF_FIRST_S: Final = 0.5
CLIENT_TIMEOUT_S: Final = 4.0  # connect, PUBACK and disconnect: within the app's stop bound
NOT_AUTHORISED: Final = frozenset({4, 5, 134, 135})  # CONNACK: MQTT 3.1.1 4, 5; MQTT 5 134, 135


class Listener(Protocol):
    """Something that takes messages from the broker: commands, feed sources."""

    def subscriptions(self) -> list[str]:
        """The topic filters it wants (subscribed with QoS 1 at every connection)."""
        ...

    async def handle(self, topic: str, payload: bytes, *, retained: bool = False) -> list[Message]:
        """Take one message; what it returns is published (results)."""
        ...


@dataclass(slots=True)
class _Published:
    """What was last published on a value topic, for the change and deadband modes."""

    value: object
    at: float


# The state document's serialiser, built once: ``json.dumps`` with an argument builds a
# new encoder at every call. Same text as ``json.dumps(document, ensure_ascii=False)``.
_encode_json = json.JSONEncoder(ensure_ascii=False).encode


def _payload(value: object) -> str:
    """A plain value as text: numbers as numbers, true/false, labels, ISO date-times."""
    data = json_value(value)  # type: ignore[arg-type]
    if isinstance(data, bool):
        return "true" if data else "false"
    if isinstance(data, dict):
        return str(value.raw) if isinstance(value, BitfieldValue) else json.dumps(data)
    return "" if data is None else str(data)


class MqttSink:
    """Publishes samples and availability; keeps the broker connection up."""

    def __init__(
        self,
        settings: MqttConfig,
        state: GatewayState,
        *,
        state_dir: Path,
        publish: Mapping[tuple[str, str], PublishSettings] | None = None,
        listeners: Sequence[Listener] = (),
    ) -> None:
        """Check the settings that can fail at start (TLS files, the state directory)."""
        self.settings = settings
        self.listeners = list(listeners)
        self._handling: set[asyncio.Task[None]] = set()
        self.state = state
        self.base = settings.base_topic
        self.client_id = settings.client_id or f"gateway-{socket.gethostname()}"
        # Only the points whose settings are not the default need an entry.
        self._publish = dict(publish or {})
        self._default_publish = PublishSettings()
        self._last: dict[str, _Published] = {}  # the change modes' last publish per topic
        # Each point's value topic, {base}/{device}/{point}, made at its first sample: by
        # device, then point, so that tens of thousands of points keep one string each.
        self._topics: dict[str, dict[str, str]] = {}
        self._flags: dict[str, bool] = {}
        self._fault_cleared: set[str] = set()
        self._live: deque[Message] = deque()
        self._wake = asyncio.Event()
        self._connected = False
        self._rng = random.Random()  # noqa: S311 - jitter only
        self._failures_in_a_row = 0
        self._discovered: set[tuple[str, str]] = set()
        self._sequence: dict[str, int] = {}  # state documents per device since the start
        if settings.tls is not None:
            for name in ("ca", "cert", "key"):
                path = getattr(settings.tls, name)
                if path is not None and not path.is_file():
                    raise PublishError(f"mqtt.tls.{name}: {path} does not exist")
        self.store = MessageStore(state_dir / "mqtt-queue.sqlite", max_messages=settings.queue_max)
        status = state.mqtt
        status.enabled = True
        status.queue_max = settings.queue_max
        status.queue_depth = len(self.store)

    # --- the sink interface --------------------------------------------------------------

    async def publish(self, samples: Sequence[Sample]) -> None:
        """Turn one device's poll cycle into messages and hand them to the sender."""
        if not samples:
            return
        messages: list[Message] = []
        for sample in samples:
            self._value_messages(sample, messages)
        first = samples[0]
        messages.append(self._state_document(first.bus, first.device, first.time))
        if self.settings.discovery.enabled and (first.bus, first.device) not in self._discovered:
            self._discovered.add((first.bus, first.device))
            messages.extend(self._discovery(first.bus, first.device))
        self._enqueue(messages)

    def _discovery(self, bus: str, device: str) -> list[Message]:
        """Home Assistant discovery for a device, from its identity and units read so far."""
        info = self.state.devices.get((bus, device))
        if info is None:
            return []
        mine = self.state.device_samples(bus, device)
        return discovery_messages(
            prefix=self.settings.discovery.prefix,
            base_topic=self.base,
            gateway_id=self.client_id,
            device=device,
            profile=get_profile(info.profile),
            points=[p for p in info.intervals if p in mine],
            identity={p: s.value for p, s in mine.items() if s.group == "identity" and s.good},
            units={p: s.unit for p, s in mine.items()},
            qos=self.settings.qos,
        )

    async def device_event(self, event: DeviceEvent) -> None:
        """Publish a device's availability (retained)."""
        payload = "online" if event.online else "offline"
        self._enqueue([self._message(f"{event.device}/availability", payload, retain=True)])

    # --- building messages ---------------------------------------------------------------

    def _message(
        self, suffix: str, payload: str, *, retain: bool, qos: int | None = None
    ) -> Message:
        return Message(
            topic=f"{self.base}/{suffix}",
            payload=payload.encode(),
            qos=self.settings.qos if qos is None else qos,
            retain=retain,
        )

    def _topic(self, sample: Sample) -> str:
        """A point's value topic, made at its first sample."""
        topic = f"{self.base}/{sample.device}/{sample.point}"
        self._topics.setdefault(sample.device, {})[sample.point] = topic
        return topic

    def _value_messages(self, sample: Sample, messages: list[Message]) -> None:
        """Append a sample's value (and status bit) messages to ``messages``."""
        topics = self._topics.get(sample.device)
        topic = topics.get(sample.point) if topics is not None else None
        if topic is None:
            topic = self._topic(sample)
        value_qos = self.settings.value_qos
        if sample.quality is not Quality.GOOD:
            # No number for a fault or a failed read: clear the retained value once.
            if topic not in self._fault_cleared:
                self._fault_cleared.add(topic)
                self._last.pop(topic, None)
                messages.append(Message(topic=topic, payload=b"", qos=value_qos, retain=True))
            return
        if self._fault_cleared:
            self._fault_cleared.discard(topic)
        settings = (
            self._publish.get((sample.device, sample.point), self._default_publish)
            if self._publish
            else self._default_publish
        )
        value = sample.value
        if settings.mode is PublishMode.EVERY_POLL or self._due(topic, settings, sample):
            if settings.mode is not PublishMode.EVERY_POLL:
                self._last[topic] = _Published(value=value, at=sample.monotonic)
            payload = repr(value) if type(value) is float else _payload(value)
            messages.append(
                Message(topic=topic, payload=payload.encode(), qos=value_qos, retain=True)
            )
        if isinstance(value, BitfieldValue):
            for flag, on in value.flags:
                key = f"{sample.device}/status/{flag}"
                if self._flags.get(key) != on:
                    self._flags[key] = on
                    messages.append(self._message(key, "true" if on else "false", retain=True))

    def _due(self, topic: str, settings: PublishSettings, sample: Sample) -> bool:
        """Whether a change mode wants this value out now."""
        last = self._last.get(topic)
        if last is None:
            return True
        if sample.monotonic - last.at >= settings.heartbeat_s:
            return True
        if settings.mode is PublishMode.ON_CHANGE:
            return sample.value != last.value
        value, previous = sample.value, last.value
        if isinstance(value, int | float) and isinstance(previous, int | float):
            return abs(value - previous) > settings.deadband
        return value != previous

    def _state_document(self, bus: str, device: str, when: datetime) -> Message:
        """Every point's latest value, unit, fault and quality, as the gateway sees them now.

        A value that could not be decoded also has its registers under ``raw`` (a key
        present only then), so a subscriber sees what the sensor sent. Built once per
        cycle: the device's intervals and the clock are read once, not per point.
        """
        values: dict[str, object] = {}
        units: dict[str, str | None] = {}
        faults: dict[str, str] = {}
        quality: dict[str, str] = {}
        raw: dict[str, list[str]] = {}
        info = self.state.devices.get((bus, device))
        intervals = info.intervals if info is not None else {}
        now = time.monotonic()
        good = Quality.GOOD
        for point, sample in sorted(self.state.device_samples(bus, device).items()):
            units[point] = sample.unit
            if sample.quality is good:
                value = sample.value
                values[point] = value if type(value) is float else json_value(value)
                interval = intervals.get(point)
                stale = interval is not None and now - sample.monotonic > (
                    STALE_FACTOR * interval + STALE_MARGIN_S
                )
                quality[point] = "stale" if stale else "good"
            else:
                faults[point] = sample.fault or sample.quality.value
                quality[point] = sample.quality.value
            if sample.raw:
                raw[point] = hex_registers(sample.raw)
        seq = self._sequence[device] = self._sequence.get(device, 0) + 1
        document = {
            "time": when.isoformat(),
            "seq": seq,
            "values": values,
            "units": units,
            "faults": faults,
            "quality": quality,
        }
        if raw:
            document["raw"] = raw
        return Message(
            topic=f"{self.base}/{device}/state",
            payload=_encode_json(document).encode(),
            qos=self.settings.qos,
            retain=False,
        )

    # --- queueing --------------------------------------------------------------------------

    def _enqueue(self, messages: list[Message]) -> None:
        """Live while connected with nothing waiting; otherwise to disk, in order."""
        if self._connected and not len(self.store):
            self._live.extend(messages)
        else:
            dropped = self.store.append(messages)
            if dropped:
                _LOGGER.warning("MQTT queue full: dropped the %d oldest messages", dropped)
        self._update_status()
        self._wake.set()

    def _update_status(self) -> None:
        status = self.state.mqtt
        status.queue_depth = len(self.store) + len(self._live)
        status.dropped = self.store.dropped
        status.connected = self._connected

    # --- the connection ------------------------------------------------------------------

    def _client_for(self) -> aiomqtt.Client:
        settings = self.settings
        tls = None
        if settings.tls is not None:
            tls = aiomqtt.TLSParameters(
                ca_certs=str(settings.tls.ca) if settings.tls.ca else None,
                certfile=str(settings.tls.cert) if settings.tls.cert else None,
                keyfile=str(settings.tls.key) if settings.tls.key else None,
            )
        client = aiomqtt.Client(
            settings.host,
            settings.port,
            username=settings.username,
            password=settings.password.get_secret_value() if settings.password else None,
            identifier=self.client_id,
            will=aiomqtt.Will(f"{self.base}/status", "offline", qos=1, retain=True),
            clean_session=settings.clean_session,
            keepalive=settings.keepalive,
            tls_params=tls,
            timeout=CLIENT_TIMEOUT_S,
            # Small packets at once: without it Nagle's algorithm and delayed ACKs hold
            # publishes back by tens of milliseconds.
            socket_options=[(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)],
        )
        client.pending_calls_threshold = PENDING_CALLS_WARNING
        return client

    async def run(self) -> None:
        """Keep connected; send the backlog in order, then live messages, until cancelled.

        On cancellation the gateway says ``offline`` itself (a clean disconnect does not
        fire the will) and what was not sent stays on disk for the next start.
        """
        delay = BACKOFF_FIRST_S
        try:
            while True:
                client = self._client_for()
                try:
                    async with client:
                        try:
                            await self._on_connect(client)
                            delay = BACKOFF_FIRST_S
                            await self._session(client)
                        except asyncio.CancelledError:
                            await self._say_offline(client)
                            raise
                except aiomqtt.MqttError as exc:
                    self._lost(exc)
                await asyncio.sleep(delay * self._rng.uniform(0.8, 1.2))
                delay = min(delay * 2, self.settings.reconnect_max_s)
        finally:
            for task in self._handling:
                task.cancel()
            self._connected = False
            if self._live:
                self.store.append(list(self._live))
                self._live.clear()
            self._update_status()
            self.store.close()

    async def _say_offline(self, client: aiomqtt.Client) -> None:
        with contextlib.suppress(aiomqtt.MqttError, TimeoutError):
            async with asyncio.timeout(2):
                await client.publish(f"{self.base}/status", "offline", qos=1, retain=True)

    async def _on_connect(self, client: aiomqtt.Client) -> None:
        if self._failures_in_a_row:
            _LOGGER.info("MQTT: connected to %s:%d again", self.settings.host, self.settings.port)
        self._failures_in_a_row = 0
        self.state.mqtt.last_error = None
        # Subscribed before saying online: a plant system may send a command as soon as it
        # sees ``online``, and a clean session drops what arrives before the subscription
        # (the soak lost a command sent while a broker restart's backlog drained). The
        # backlog drains in the session, while commands are already taken.
        for topic_filter in self._filters():
            await client.subscribe(topic_filter, qos=1)
        await client.publish(f"{self.base}/status", "online", qos=1, retain=True)

    def _lost(self, exc: aiomqtt.MqttError) -> None:
        """Note the failure; unsent live messages go to the head of the disk queue."""
        was_connected = self._connected
        self._connected = False
        if self._live:
            backlog = self.store.peek(len(self.store))  # normally empty: live implies drained
            self.store.remove([i for i, _ in backlog])
            self.store.append([*self._live, *(m for _, m in backlog)])
            self._live.clear()
        self._failures_in_a_row += 1
        rc = getattr(exc, "rc", None)
        code = getattr(rc, "value", rc)
        refused = isinstance(exc, MqttConnectError) and code in NOT_AUTHORISED
        if refused:
            who = self.settings.username or "an anonymous client"
            reason = f"the broker refused the credentials of {who} ({exc})"
        else:
            reason = f"{self.settings.host}:{self.settings.port}: {exc}"
        self.state.mqtt.last_error = reason
        log = _LOGGER.error if refused else _LOGGER.warning
        if was_connected or self._failures_in_a_row == 1:
            log("MQTT: %s; buffering on disk and retrying", reason)
        else:
            _LOGGER.debug("MQTT: %s", reason)
        self._update_status()

    async def _drain(self, client: aiomqtt.Client) -> None:
        """Send the disk queue in order, removing what the broker acknowledged."""
        while batch := self.store.peek(BATCH):
            window: deque[asyncio.Task[None]] = deque()
            try:
                for _, m in batch:
                    if len(window) == WINDOW:
                        await window.popleft()
                    window.append(_in_flight(self._send(client, m)))
                while window:
                    await window.popleft()
            finally:
                for task in window:
                    task.cancel()
            self.store.remove([i for i, _ in batch])
            self.state.mqtt.published += len(batch)
            self._update_status()

    @staticmethod
    async def _send(client: aiomqtt.Client, message: Message) -> None:
        await client.publish(message.topic, message.payload, qos=message.qos, retain=message.retain)

    async def _session(self, client: aiomqtt.Client) -> None:
        """Send, and take messages for the listeners, until the connection fails."""
        if not self._filters():
            await self._send_forever(client)
            return
        try:
            async with asyncio.TaskGroup() as group:
                group.create_task(self._send_forever(client))
                group.create_task(self._receive_forever(client))
        except* aiomqtt.MqttError as failed:
            raise failed.exceptions[0] from None  # the reconnect loop handles one error

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
            for listener in self.listeners:
                if any(topic.matches(f) for f in listener.subscriptions()):
                    task = asyncio.create_task(
                        self._handle(listener, topic.value, data, retained=message.retain)
                    )
                    self._handling.add(task)
                    task.add_done_callback(self._handling.discard)

    async def _handle(
        self, listener: Listener, topic: str, payload: bytes, *, retained: bool
    ) -> None:
        try:
            replies = await listener.handle(topic, payload, retained=retained)
        except Exception:
            _LOGGER.exception("MQTT: handling %s failed", topic)
            return
        if replies:
            self._enqueue(replies)

    async def _send_forever(self, client: aiomqtt.Client) -> None:
        """Send live messages in order, up to :data:`WINDOW` awaiting their PUBACK at once.

        The first messages of the live queue are the ones in flight; each leaves the queue
        only once acknowledged, so on a lost connection the unacknowledged ones go to disk
        and are sent again (QoS 1 allows the duplicate). One publish at a time moved only
        some 550 messages a second out of a gateway polling 480 devices: each PUBACK waited
        its turn in a busy event loop.

        The loop wakes on a new message as well as on an acknowledgement (a publish's end
        sets the same event), so a cycle handed over while the window waits for a PUBACK
        goes out at once, not after it. A publish carries no timer of its own: the oldest
        unacknowledged one is given :data:`CLIENT_TIMEOUT_S`, as aiomqtt gave each.
        """
        window: deque[tuple[asyncio.Task[None], float]] = deque()
        wake = self._wake
        loop = asyncio.get_running_loop()
        try:
            while True:
                if len(self.store) and not window:
                    self._connected = False  # newer messages queue on disk behind the backlog
                    await self._drain(client)  # the backlog first, before anything newer
                if not self._connected:
                    self._connected = True
                    self._update_status()
                wake.clear()
                self._retire(window)
                if len(window) < WINDOW and len(self._live) > len(window):
                    self._fill(client, window, loop.time())
                if not window:
                    self._update_status()
                    await wake.wait()
                    continue
                if wake.is_set():
                    continue
                try:
                    async with asyncio.timeout_at(window[0][1] + CLIENT_TIMEOUT_S):
                        await wake.wait()
                except TimeoutError:
                    raise aiomqtt.MqttError("Operation timed out") from None
        finally:
            for task, _ in window:
                task.cancel()

    def _retire(self, window: deque[tuple[asyncio.Task[None], float]]) -> None:
        """The acknowledged head of the window leaves it, and the live queue, in order."""
        live = self._live
        status = self.state.mqtt
        while window and window[0][0].done():
            window.popleft()[0].result()  # a failed publish ends the session
            live.popleft()
            status.published += 1

    def _fill(
        self,
        client: aiomqtt.Client,
        window: deque[tuple[asyncio.Task[None], float]],
        now: float,
    ) -> None:
        """Start the live messages behind the window until it is full."""
        live = self._live
        while len(window) < WINDOW and len(live) > len(window):
            window.append((self._start(client, live[len(window)]), now))

    def _start(self, client: aiomqtt.Client, message: Message) -> asyncio.Task[None]:
        """A live publish as a task whose end wakes the sender (ack or failure alike)."""
        task = asyncio.create_task(
            client.publish(
                message.topic,
                message.payload,
                qos=message.qos,
                retain=message.retain,
                timeout=math.inf,  # the sender times the oldest publish itself
            )
        )
        task.add_done_callback(self._published)
        return task

    def _published(self, done: asyncio.Task[None]) -> None:
        """A live publish ended: wake the sender; its failure counts as seen."""
        self._wake.set()
        if not done.cancelled():
            done.exception()


def _in_flight(publish: Coroutine[object, object, None]) -> asyncio.Task[None]:
    """A publish of the window, as a task whose failure counts as seen.

    Only the head of the window is awaited; when the connection fails, the others fail
    too and are dropped with it (their messages stay queued), which is no news to log.
    """
    task = asyncio.create_task(publish)
    task.add_done_callback(lambda done: done.cancelled() or done.exception())
    return task
