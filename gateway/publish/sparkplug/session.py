"""The edge node's MQTT session: will, births, seq, the primary host, commands, reconnects.

One client of its own (not the plain topics' one: its last will is the NDEATH). Each
connection takes the next ``bdSeq`` (0..255, kept on disk across restarts) and registers
the NDEATH with it as the will, then subscribes NCMD, DCMD and, with a primary host, its
STATE. Births go out when the host is online (at once without a primary host): NBIRTH with
``seq`` 0, a DBIRTH per device born, then what was stored while the host or the broker was
away (historical DDATA), then live messages; every message after the NBIRTH takes the next
``seq``, 0..255 wrapping. A host that goes offline ends the session (the gateway publishes
its NDEATH itself): messages are stored until it is back, and the new session births anew.
A rebirth (NCMD ``Node Control/Rebirth``) sends the births again in the same session.

With several servers (``sparkplug.servers``, else ``mqtt.servers``) the edge node is
connected to one at a time (Sparkplug 3.0, 5.10,
``tck-id-operational-behavior-primary-application-state-with-multiple-servers-single-server``);
a host offline on it, or not online within ``sparkplug.host_wait_s``, ends the session
with an NDEATH and the next server is tried (``...-multiple-servers-walk``), where the
births again wait for the host's STATE online (``...-edge-node-birth-sequence-wait``).
Every CONNECT takes the next ``bdSeq``; a rebirth keeps it. A host's STATE online that
arrives live, and a rebirth request, reach every edge node of a plant at once: each waits
a random time up to ``sparkplug.birth_delay_max_s`` before its births, sending no data
meanwhile.

The host's STATE is judged by its timestamp (Sparkplug 3.0,
``tck-id-operational-behavior-edge-node-termination-host-offline-timestamp``) against the
one acted on last on the same server, as a host keeps one series per server
(``...-host-application-multi-server-timestamp``): an older one is ignored, so a stale
retained will of the host (after its restart, or of the other host of a redundant pair)
does not end a session the host is in, and its online STATE on a server it joined long
ago still counts after a newer will on another.

It speaks under the gateway's identity once the plain connection's owner claim has
stood, and stands down with it (a copied config) until a reload
(:mod:`~gateway.publish.sparkplug.identity` says why, and when an NDEATH is sent).

Messages are published with QoS 0 and never retained (Sparkplug 3.0, 7.1); the will and
the NDEATH with QoS 1.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import random
from collections import deque
from datetime import UTC, datetime
from typing import TYPE_CHECKING, Final, Protocol

import aiomqtt

from gateway.errors import CommandRejectedError
from gateway.publish.mqtt.connection import broker_client
from gateway.publish.mqtt.outbox import SUBSCRIBE_TIMEOUT_S
from gateway.publish.mqtt.servers import ServerWalk
from gateway.publish.sparkplug import payloads
from gateway.publish.sparkplug.catalogue import REBIRTH
from gateway.publish.sparkplug.identity import IdentityConflictError
from gateway.publish.sparkplug.reports import ndeath_payload
from gateway.shared.state import SparkplugStatus

if TYPE_CHECKING:
    from pathlib import Path

    from gateway.config import MqttConfig, SparkplugConfig
    from gateway.publish.message import Message
    from gateway.publish.sparkplug.identity import IdentityWatch
    from gateway.publish.sparkplug.topics import SparkplugTopics
    from gateway.publish.store import MessageStore

_LOGGER = logging.getLogger(__name__)

BACKOFF_FIRST_S: Final = 0.5
BATCH: Final = 100  # stored messages read at a time while they drain
BD_SEQ_MODULUS: Final = 256  # bdSeq runs 0..255 (Sparkplug 3.0, 6.4.3)


class HostOfflineError(Exception):
    """The primary host said it is offline: the session ends, and the next one waits."""


class HostAbsentError(HostOfflineError):
    """The primary host was not online on this server within ``host_wait_s``."""


class TimeUpError(Exception):
    """The session's time on another server than the first is up."""


class Births(Protocol):
    """What the session asks for at every birth: the node's and its devices' births."""

    def births(self, bd_seq: int, now_ms: int) -> list[Message]:
        """NBIRTH, then a DBIRTH per device born; payloads without ``seq``."""
        ...

    def born_devices(self) -> set[str]:
        """The devices born: stored data of others is not forwarded."""
        ...


class DeviceCommands(Protocol):
    """Who takes the DCMDs (the control floor's writes)."""

    async def device_command(self, device: str, payload: bytes) -> None:
        """Take one DCMD payload for ``device``."""
        ...


def rejected(what: str, reason: str) -> None:
    """The log line of a refused command (the caller counts it)."""
    _LOGGER.warning("Sparkplug: %s refused, nothing written: %s", what, reason)


class SparkplugSession:
    """Keeps the edge node's session with the broker, in order, with its ``seq``."""

    def __init__(
        self,
        broker: MqttConfig,
        settings: SparkplugConfig,
        topics: SparkplugTopics,
        store: MessageStore,
        *,
        births: Births,
        client_id: str,
        bd_seq_path: Path,
        on_rejected: DeviceCommandCounter | None = None,
        status: SparkplugStatus | None = None,
        identity: IdentityWatch | None = None,
    ) -> None:
        """Connect to ``broker`` as ``client_id``; keep messages in ``store`` while away.

        ``identity``: the gateway's, to connect once it is held and stand down with it
        (None: no guard).
        """
        self.broker = broker
        self.settings = settings
        self.topics = topics
        self.store = store
        self.births = births
        self.client_id = client_id
        self.bd_seq_path = bd_seq_path
        self.on_rejected = on_rejected
        self.status = status or SparkplugStatus()
        self.status.enabled = True
        self.commands: DeviceCommands | None = None
        self.identity = identity
        self.bd_seq = _read_bd_seq(bd_seq_path)
        self._born = False  # births went out on the connection now up
        self.seq = 0
        self.connected = False
        self.host_online = topics.host is None
        # The timestamp of the host's STATE acted on last, by server (kept across
        # sessions): a host keeps one series per server (Sparkplug 3.0,
        # tck-id-operational-behavior-host-application-multi-server-timestamp).
        self.host_timestamps: dict[str, int] = {}
        self._live: deque[Message] = deque()
        self._wake = asyncio.Event()
        self._rebirth = False
        self._handling: set[asyncio.Task[None]] = set()
        self._rng = random.Random()  # noqa: S311 - jitter only
        self._failures_in_a_row = 0
        self._birth_delay = 0.0  # before the next births: a host back, or a rebirth
        self.walk = ServerWalk(
            settings.server_list(broker), return_to_first_s=broker.return_to_first_s
        )
        self.status.servers = tuple(server.address for server in self.walk.servers)
        self.status.server = self.walk.current.address

    @property
    def host_timestamp(self) -> int | None:
        """The timestamp of the host's STATE acted on last on the current server."""
        return self.host_timestamps.get(self.walk.current.address)

    @property
    def live(self) -> bool:
        """Whether a message goes out as it is: once the births are out (else: history)."""
        return self.connected and self.host_online and self._born

    def enqueue(self, messages: list[Message]) -> None:
        """Live messages to the sender; otherwise DDATA to the store (births are redone)."""
        if not messages:
            return
        if self.live:
            self._live.extend(messages)
        else:
            data = [m for m in messages if self.topics.device_of_data(m.topic) is not None]
            dropped = self.store.append(data)
            if dropped:
                _LOGGER.warning("Sparkplug queue full: dropped the %d oldest messages", dropped)
            self._update_status()
        self._wake.set()

    def _update_status(self) -> None:
        """What ``/healthz`` and the metrics show of the session."""
        status = self.status
        status.connected = self.connected
        status.host_online = self.host_online
        status.bd_seq = self.bd_seq
        status.queue_depth = len(self.store)
        status.dropped = self.store.dropped

    def rebirth(self, *, delay: bool = False) -> None:
        """Send the births again, in this session (NCMD ``Node Control/Rebirth``).

        ``delay``: after a random wait up to ``birth_delay_max_s`` (a fleet-wide request).
        """
        if delay:
            self._birth_delay = self._rng.uniform(0, self.settings.birth_delay_max_s)
        self._rebirth = True
        self._wake.set()

    # --- the connection --------------------------------------------------------------

    def _next_bd_seq(self) -> int:
        self.bd_seq = (self.bd_seq + 1) % BD_SEQ_MODULUS
        with contextlib.suppress(OSError):
            self.bd_seq_path.write_text(f"{self.bd_seq}\n", encoding="utf-8")
        self.status.bd_seq = self.bd_seq
        return self.bd_seq

    def _client(self, bd_seq: int) -> aiomqtt.Client:
        return broker_client(
            self.broker,
            self.walk.current,
            client_id=self.client_id,
            will=aiomqtt.Will(self.topics.ndeath, ndeath_payload(bd_seq, _now_ms()), qos=1),
            clean_session=True,  # Sparkplug 3.0, 7.1: a clean session at every connect
        )

    async def run(self) -> None:
        """Keep the session, reconnecting on a capped jittered backoff, until cancelled.

        On cancellation the NDEATH is published (a clean disconnect does not fire the will).
        The first connection waits until the gateway's identity is held; a conflict found
        then or later stands the session down until a reload.
        """
        delay = BACKOFF_FIRST_S
        try:
            if self.identity is not None:
                await self.identity.held()
            while True:
                if await self._connection(self._next_bd_seq()):
                    delay = BACKOFF_FIRST_S
                    continue  # the next server (or the first again) at once
                if self.walk.next():  # every server failed once: wait, longer each round
                    await asyncio.sleep(delay * self._rng.uniform(0.8, 1.2))
                    delay = min(delay * 2, self.broker.reconnect_max_s)
                else:
                    await asyncio.sleep(BACKOFF_FIRST_S * self._rng.uniform(0.2, 0.4))
        except IdentityConflictError as conflict:
            await self._stand_down(str(conflict))
        finally:
            for task in self._handling:
                task.cancel()
            self.store.close()

    async def _connection(self, bd_seq: int) -> bool:
        """One connection to the current server; whether the next follows at once.

        True after a session ended on purpose with an NDEATH (the host offline or absent:
        the next server; time up: the first); False after a failure. A stand-down leaves
        with a DISCONNECT (no will), after an NDEATH only if births went out, and is raised.
        """
        walk = self.walk
        self.status.server = walk.current.address
        self.status.switches = walk.switches
        try:
            async with self._client(bd_seq) as client:
                try:
                    await self._session(client, bd_seq)
                except asyncio.CancelledError:
                    await self._say_dead(client, bd_seq)
                    raise
                except HostOfflineError:
                    await self._say_dead(client, bd_seq)
                    if walk.several:
                        walk.next()
                    return True
                except TimeUpError:
                    _LOGGER.info(
                        "Sparkplug: %.0f s on %s: back to the first server, %s",
                        walk.stay_for() or 0.0,
                        walk.current.address,
                        walk.servers[0].address,
                    )
                    await self._say_dead(client, bd_seq)
                    walk.first()
                    return True
                except IdentityConflictError:
                    if self._born:
                        await self._say_dead(client, bd_seq)
                    raise
        except aiomqtt.MqttError as exc:
            self._lost(exc)
        finally:
            self._end_session()
        return False

    async def _stand_down(self, conflict: str) -> None:
        """Another gateway holds this identity: publish nothing until a reload.

        Data goes on to the store, within its bound, as while the host is away.
        """
        why = (
            f"edge node {self.topics.group}/{self.topics.edge} stood down with the MQTT "
            f"connection (a copied config?): {conflict}"
        )
        self.status.identity_conflict = why
        self.status.last_error = why
        self._update_status()
        _LOGGER.error("Sparkplug: %s", why)
        await asyncio.Event().wait()  # until a reload or a stop cancels the session

    def _end_session(self) -> None:
        """Unsent live messages go to the store, as history, ahead of anything newer."""
        self.connected = False
        if self.topics.host is not None:
            self.host_online = False
        if self._live:
            backlog = self.store.peek(len(self.store))
            self.store.remove([i for i, _ in backlog])
            live = [m for m in self._live if self.topics.device_of_data(m.topic) is not None]
            self.store.append([*live, *(m for _, m in backlog)])
            self._live.clear()
        self._update_status()

    async def _say_dead(self, client: aiomqtt.Client, bd_seq: int) -> None:
        with contextlib.suppress(aiomqtt.MqttError, TimeoutError):
            async with asyncio.timeout(2):
                await client.publish(self.topics.ndeath, ndeath_payload(bd_seq, _now_ms()), qos=1)

    def _lost(self, exc: aiomqtt.MqttError) -> None:
        self._failures_in_a_row += 1
        reason = f"{self.walk.current.address}: {exc}"
        self.status.last_error = reason
        if self._failures_in_a_row == 1:
            _LOGGER.warning("Sparkplug: %s; storing data and retrying", reason)
        else:
            _LOGGER.debug("Sparkplug: %s", reason)

    async def _on_connect(self, client: aiomqtt.Client) -> None:
        """Subscribe NCMD, DCMD and the primary host's STATE (before any birth)."""
        if self._failures_in_a_row:
            _LOGGER.info("Sparkplug: connected to %s again", self.walk.current.address)
        elif self.walk.several:
            _LOGGER.info("Sparkplug: connected to %s", self.walk.current.address)
        self._failures_in_a_row = 0
        self.status.last_error = None
        self._born = False
        topics = self.topics
        await client.subscribe(topics.ncmd, qos=1, timeout=SUBSCRIBE_TIMEOUT_S)
        await client.subscribe(topics.dcmd_filter, qos=1, timeout=SUBSCRIBE_TIMEOUT_S)
        if topics.state is not None:
            await client.subscribe(topics.state, qos=1, timeout=SUBSCRIBE_TIMEOUT_S)
        self.connected = True
        self._update_status()

    async def _session(self, client: aiomqtt.Client, bd_seq: int) -> None:
        await self._on_connect(client)
        try:
            async with asyncio.TaskGroup() as group:
                group.create_task(self._send_forever(client, bd_seq))
                group.create_task(self._receive_forever(client))
                if self.walk.several and self.topics.host is not None:
                    group.create_task(self._host_awaited(self.settings.host_wait_s))
                stay = self.walk.stay_for()
                if stay is not None:
                    group.create_task(_time_up(stay))
                if self.identity is not None:
                    group.create_task(self.identity.contested())
        except* _ENDINGS as ended:
            # One handler: two endings at once (the host's offline STATE as the connection
            # drops) would each raise, and leave as a group that nothing catches.
            raise _deciding(ended) from None

    # --- sending ---------------------------------------------------------------------

    async def _host_awaited(self, wait_s: float) -> None:
        """End the session if the primary host is not online on this server in time."""
        await asyncio.sleep(wait_s)
        if not self.host_online:
            _LOGGER.warning(
                "Sparkplug: primary host %s not online on %s within %.0f s; next server",
                self.topics.host,
                self.walk.current.address,
                wait_s,
            )
            raise HostAbsentError

    async def _send_forever(self, client: aiomqtt.Client, bd_seq: int) -> None:
        """Births once the host is online, then the stored history, then live messages."""
        wake = self._wake
        while not self.host_online:
            wake.clear()
            await wake.wait()
        await self._births_delayed()
        await self._birth(client, bd_seq)
        await self._drain(client)
        while True:
            wake.clear()
            if self._rebirth:
                await self._births_delayed()
                await self._birth(client, bd_seq)
            while self._live:
                await self._publish(client, self._live[0])
                self._live.popleft()
                if self._rebirth:
                    break
            if not self._live and not self._rebirth:
                await wake.wait()

    async def _births_delayed(self) -> None:
        """The random wait a fleet-wide event asked for, if any; no data is sent meanwhile."""
        delay, self._birth_delay = self._birth_delay, 0.0
        if delay > 0:
            _LOGGER.info("Sparkplug: births in %.1f s (spread over the fleet)", delay)
            await asyncio.sleep(delay)

    async def _birth(self, client: aiomqtt.Client, bd_seq: int) -> None:
        self._rebirth = False
        self.seq = 0
        # Data queued before the births is older than them: the births carry its values.
        self._live.clear()
        self._born = True
        for message in self.births.births(bd_seq, _now_ms()):
            await self._publish(client, message)
        self.status.births += 1
        _LOGGER.info("Sparkplug: births sent (bdSeq %d)", bd_seq)

    async def _drain(self, client: aiomqtt.Client) -> None:
        """The stored history, in order, of the devices born; removed once sent."""
        born = self.births.born_devices()
        while batch := self.store.peek(BATCH):
            for _, message in batch:
                if self.topics.device_of_data(message.topic) in born:
                    await self._publish(client, message)
            self.store.remove([i for i, _ in batch])
            self._update_status()

    async def _publish(self, client: aiomqtt.Client, message: Message) -> None:
        payload = payloads.with_seq(message.payload, self.seq)
        self.seq = (self.seq + 1) % payloads.SEQ_MODULUS
        await client.publish(message.topic, payload, qos=0, retain=False)
        self.status.published += 1
        _cancelled_meanwhile()

    # --- receiving -------------------------------------------------------------------

    async def _receive_forever(self, client: aiomqtt.Client) -> None:
        async for message in client.messages:
            topic = message.topic.value
            payload = message.payload
            data = payload if isinstance(payload, bytes) else str(payload or "").encode()
            if topic == self.topics.state:
                self._host_state(data, retained=message.retain)
            elif topic == self.topics.ncmd:
                self._node_command(data)
            elif (device := self.topics.device_of(topic)) is not None:
                self._device_command(device, data)

    def _host_state(self, payload: bytes, *, retained: bool = False) -> None:
        """``{"online": true|false, "timestamp": …}`` (3.0), or ``ONLINE``/``OFFLINE`` (2.2).

        A 3.0 STATE older than the one acted on last on this server is ignored; an equal
        one is not (a host's will carries the timestamp of the birth it ends). A live (not
        retained) online is the host coming back, seen by the whole fleet at once: the
        births wait a random time first.
        """
        text = payload.decode("utf-8", "replace").strip()
        timestamp = None
        try:
            data = json.loads(text)
        except ValueError:
            online = text.upper() == "ONLINE"
        else:
            online = bool(data.get("online")) if isinstance(data, dict) else False
            stamp = data.get("timestamp") if isinstance(data, dict) else None
            if isinstance(stamp, int) and not isinstance(stamp, bool):
                timestamp = stamp
        if timestamp is not None:
            last = self.host_timestamp
            if last is not None and timestamp < last:
                _LOGGER.info(
                    "Sparkplug: ignored a STATE of %s (online %s) of %d, older than the one "
                    "of %d acted on",
                    self.topics.host,
                    online,
                    timestamp,
                    last,
                )
                return
            self.host_timestamps[self.walk.current.address] = timestamp
        if online and not self.host_online:
            _LOGGER.info("Sparkplug: primary host %s is online", self.topics.host)
            if not retained:
                self._birth_delay = self._rng.uniform(0, self.settings.birth_delay_max_s)
            self.host_online = True
            self._update_status()
            self._wake.set()
        elif not online and self.host_online:
            _LOGGER.warning("Sparkplug: primary host %s is offline; storing data", self.topics.host)
            self.host_online = False
            self._update_status()
            raise HostOfflineError

    def _node_command(self, payload: bytes) -> None:
        try:
            metrics = _node_command_metrics(payload)
        except CommandRejectedError as exc:
            rejected("NCMD", str(exc))
            if self.on_rejected is not None:
                self.on_rejected(self.topics.edge)
            return
        if any(metrics):
            _LOGGER.info("Sparkplug: rebirth requested")
            self.rebirth(delay=True)

    def _device_command(self, device: str, payload: bytes) -> None:
        if self.commands is None:
            rejected(f"DCMD to {device}", "commands are disabled (commands.enabled: false)")
            if self.on_rejected is not None:
                self.on_rejected(device)
            return
        task = asyncio.create_task(self._handle(self.commands, device, payload))
        self._handling.add(task)
        task.add_done_callback(self._handling.discard)

    @staticmethod
    async def _handle(commands: DeviceCommands, device: str, payload: bytes) -> None:
        try:
            await commands.device_command(device, payload)
        except Exception:
            _LOGGER.exception("Sparkplug: DCMD to %s failed", device)


class DeviceCommandCounter(Protocol):
    """Counts a refused command of a device (or of the node, by its id)."""

    def __call__(self, device: str) -> None:
        """Count one."""


def _node_command_metrics(payload: bytes) -> list[bool]:
    """The values of an NCMD's metrics: ``Node Control/Rebirth`` (Boolean) is the one known."""
    values = []
    for metric in payloads.decode_command(payload):
        if metric.name != REBIRTH:  # by name: the rebirth metric has no alias
            raise CommandRejectedError(f"the node has no metric {metric.label} to command")
        values.append(bool(payloads.command_value(metric, payloads.SpType.BOOLEAN)))
    return values


# What ends a session, the one that decides most first: a stand-down, the host's STATE,
# the time away from the first server, a failure.
_ENDINGS: Final = (IdentityConflictError, HostOfflineError, TimeUpError, aiomqtt.MqttError)


def _deciding(ended: BaseExceptionGroup[Exception]) -> Exception:
    """The exception of ``ended`` (a session's task group) that decides what comes next."""
    leaves = [e for e in ended.exceptions if not isinstance(e, BaseExceptionGroup)]
    for kind in _ENDINGS:
        for exc in leaves:
            if isinstance(exc, kind):
                return exc
    return ended.exceptions[0]  # type: ignore[return-value]


async def _time_up(stay_s: float) -> None:
    """End the session after ``stay_s`` on another server than the first."""
    await asyncio.sleep(stay_s)
    raise TimeUpError


def _read_bd_seq(path: Path) -> int:
    """The last ``bdSeq`` used (the next session takes the one after); 255 if none."""
    try:
        return int(path.read_text(encoding="utf-8").strip()) % BD_SEQ_MODULUS
    except (OSError, ValueError):
        return BD_SEQ_MODULUS - 1


def _now_ms() -> int:
    return payloads.epoch_ms(datetime.now(UTC))


def _cancelled_meanwhile() -> None:
    """Re-raise a cancellation that a publish swallowed.

    aiomqtt waits for a publish with ``asyncio.wait_for``, which on Python 3.11 returns the
    result, not the cancellation, when both arrive together: the sender would then wait for
    the next message with its cancellation lost, and a stop would hang on it (seen while a
    device was reborn). The task still counts the request (``cancelling()``).
    """
    task = asyncio.current_task()
    if task is not None and task.cancelling():
        raise asyncio.CancelledError
