"""aiomqtt's client, mended where a connection attempt fails or a connection drops early.

aiomqtt 2.5.1 leaves the socket of a failed attempt open and watched by the event loop,
and when the attempt was cancelled (a stop or a reload while connecting; a broker that took
longer than the connect timeout to answer, in one ordering of the loop's callbacks), the
socket's next read raised ``CancelledError`` out of its disconnect callback: the log showed
asyncio's "Exception in callback" with a traceback. It was seen with a clustered broker
(NATS) that answered CONNECT slowly while it elected a leader. Left open, the attempt's
socket could also complete a session on that server later, under the gateway's client id,
beside the one it made on the next server.

A broker that closes the connection while a SUBSCRIBE waits for its SUBACK (a RabbitMQ
cluster refuses a QoS 1 subscription whose queue's node is down) left the gateway waiting
the whole subscribe timeout, 15 s per attempt, and the client's "unexpected disconnection"
was logged as an error nobody retrieved ("Future exception was never retrieved"). A
broker that closed the connection right after its CONNACK, before aiomqtt's connect had
returned, was forgotten: aiomqtt replaces the future that said so, and the client waited
on a dead socket.

paho's connect runs in an executor thread, and a cancellation that came while it ran
(a stop, a reload, a Sparkplug session moving to its next server as the gateway stopped)
found no socket yet to close: the thread went on, the broker accepted the session under the
gateway's client id and kept it (with its will) until the broker itself stopped, and the
drop was then logged as an exception nobody retrieved. The attempt now waits for the thread
(paho gives up connecting after 5 s) and closes what it made.

aiomqtt adds the socket's writer to the loop in a callback it queues when paho has something
to send. A drop read in the same turn of the loop (a NATS node killed while the gateway
published to it) closed the socket first, and asyncio logged "Exception in callback" with
an ``EBADF`` traceback; had the number been reused meanwhile, the writer would have watched
another socket. The writer is now added only to the socket still open for the connection.

The same callback cost every burst of publishes two turns of the loop and five system
calls: a byte through the loop's self-pipe to run it, a turn to add the writer, a turn for
the socket to say it is writable (it nearly always is), and the writer's add and removal.
Asked from the loop's own thread (a publish of the session's), the packets are now written
in the loop's next pass, and a writer is added only for what the socket did not take.

All are mended here, at the one place where the gateway makes a client, so that the
reconnect loops above it see only :class:`aiomqtt.MqttError`, at once, and a closed socket.
"""

from __future__ import annotations

import asyncio
import contextlib
import threading
from typing import TYPE_CHECKING, Any, Self

import aiomqtt

if TYPE_CHECKING:
    from types import TracebackType

    import paho.mqtt.client as mqtt
    from aiomqtt.types import PahoSocket, SubscribeTopic
    from paho.mqtt.properties import Properties
    from paho.mqtt.reasoncodes import ReasonCode
    from paho.mqtt.subscribeoptions import SubscribeOptions


class ConnectCall:
    """The blocking paho connect in its executor thread: whether it began, and when it ended.

    The lock orders a cancellation against the thread's start: either the call never
    begins, or the attempt knows it did and waits for :attr:`ended` before closing.
    """

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._began = False
        self._abandoned = False
        self.ended = asyncio.Event()

    def begin(self) -> bool:
        """In the thread: whether to connect (not if the attempt was given up first)."""
        with self._lock:
            self._began = not self._abandoned
            return self._began

    def abandon(self) -> bool:
        """In the loop: give the call up; whether it began (then wait for :attr:`ended`)."""
        with self._lock:
            self._abandoned = True
            return self._began


class BrokerClient(aiomqtt.Client):
    """An :class:`aiomqtt.Client` whose failed or cancelled connection attempt is closed."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:  # noqa: ANN401 - aiomqtt's own
        """Make aiomqtt's client (in the running loop), with a record of its connect call."""
        super().__init__(*args, **kwargs)
        # The loop's thread (aiomqtt makes the client in it): told from paho's connect
        # thread by its id, not by asking for the running loop, a system call a burst.
        self._loop_thread = threading.get_ident()
        self._connect_call = ConnectCall()
        self._entering = False
        self._dropped_entering: BaseException | None = None

    async def __aenter__(self) -> Self:
        """Connect; on any failure, close the attempt's socket before raising.

        If paho's connect is still running in its thread (a cancellation came meanwhile),
        the socket it is making is closed once it returns.
        """
        if self._lock.locked():  # aiomqtt refuses to enter again: leave the one under way be
            return await super().__aenter__()
        call = self._connect_call = ConnectCall()  # this attempt's
        self._entering, self._dropped_entering = True, None
        try:
            entered = await super().__aenter__()
            self._raise_if_dropped_entering()
        except BaseException:
            try:
                if call.abandon():
                    await call.ended.wait()
            finally:
                self._close_attempt()
            raise
        finally:
            self._entering = False
        return entered

    def _raise_if_dropped_entering(self) -> None:
        """The broker closed the connection before aiomqtt's connect returned: say so.

        aiomqtt has forgotten it (it replaced the future that said so).
        """
        if self._dropped_entering is None:
            return
        self._lock.release()  # held by aiomqtt for the connection, which is gone
        msg = "Disconnected as the connection was made"
        raise aiomqtt.MqttError(msg) from self._dropped_entering

    def _client_connect(self) -> None:
        """Run paho's connect, in the executor's thread; the loop is told when it returns."""
        call = self._connect_call
        if not call.begin():
            msg = "connection attempt given up before it began"
            raise OSError(msg)
        try:
            super()._client_connect()
        finally:
            self._loop.call_soon_threadsafe(call.ended.set)

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        """Disconnect; a connection the broker dropped has told its reason already."""
        if self._disconnected.done() and not self._disconnected.cancelled():
            self._disconnected.exception()  # retrieved: the caller learnt it as an MqttError
        await super().__aexit__(exc_type, exc, tb)

    async def subscribe(
        self,
        /,
        topic: SubscribeTopic,
        qos: int = 0,
        options: SubscribeOptions | None = None,
        properties: Properties | None = None,
        *args: Any,  # noqa: ANN401 - passed on to paho, as aiomqtt types them
        timeout: float | None = None,  # noqa: ASYNC109 - aiomqtt's own parameter
        **kwargs: Any,  # noqa: ANN401
    ) -> tuple[int, ...] | list[ReasonCode]:
        """Subscribe, or raise :class:`aiomqtt.MqttError` as soon as the connection drops."""
        subscribing = asyncio.ensure_future(
            super().subscribe(topic, qos, options, properties, *args, timeout=timeout, **kwargs)
        )
        try:
            dropped: asyncio.Future[Any] = self._disconnected
            await asyncio.wait({subscribing, dropped}, return_when=asyncio.FIRST_COMPLETED)
        finally:
            if not subscribing.done():
                subscribing.cancel()
                with contextlib.suppress(asyncio.CancelledError, aiomqtt.MqttError):
                    await subscribing
        if subscribing.cancelled():
            reason = None if self._disconnected.cancelled() else self._disconnected.exception()
            msg = "Disconnected while subscribing"
            raise aiomqtt.MqttError(msg) from reason
        return subscribing.result()

    def _close_attempt(self) -> None:
        # paho's own close: it also unregisters the socket from the loop (aiomqtt's
        # socket-close callback) and stops aiomqtt's housekeeping task.
        # A client is not entered again after a failed attempt: the gateway makes a new one.
        with contextlib.suppress(OSError):
            self._client._sock_close()  # noqa: SLF001 - paho has no public close without a DISCONNECT

    def _on_socket_register_write(
        self,
        client: mqtt.Client,
        userdata: Any,  # noqa: ANN401, ARG002 - paho's user data, as aiomqtt types it
        sock: PahoSocket,
    ) -> None:
        # As aiomqtt's: paho may ask from the connect thread, so the writer is added in a
        # callback of the loop. Unlike it: by then the socket may be closed (a drop read
        # in between), and its number free or another socket's.
        def write() -> None:
            # A failed write (a broken pipe) is the connection's end: told as aiomqtt does.
            try:
                client.loop_write()
            except Exception as exc:  # noqa: BLE001 - every failure ends the connection
                if not self._disconnected.done():
                    self._disconnected.set_exception(exc)

        def add_writer() -> None:
            current = client.socket()  # paho forgets a socket as it closes it
            if current is not None and current is sock:
                self._loop.add_writer(current.fileno(), write)

        def write_now() -> None:
            if client.socket() is not sock:  # closed meanwhile (a drop read in between)
                return
            write()  # a socket that is writable nearly always: no turn of the loop to ask
            if client.want_write():  # the socket took part: the rest as it can take more
                add_writer()  # to the socket still open only: a failed write closed it

        if threading.get_ident() == self._loop_thread:  # a publish of the session's
            self._loop.call_soon(write_now)
        else:
            self._loop.call_soon_threadsafe(add_writer)

    def _on_disconnect(
        self,
        client: mqtt.Client,
        userdata: Any,  # noqa: ANN401 - paho's user data, as aiomqtt types it
        flags: mqtt.DisconnectFlags,
        reason_code: ReasonCode,
        properties: Properties | None = None,
    ) -> None:
        # aiomqtt asks a cancelled attempt's future for its exception, which raises.
        if self._connected.cancelled():
            return
        super()._on_disconnect(client, userdata, flags, reason_code, properties)
        dropped = self._disconnected
        if self._entering and dropped.done() and not dropped.cancelled():
            # Between the CONNACK and the end of __aenter__, which then replaces this
            # future: the drop would be lost, and the client would wait on a dead socket.
            self._dropped_entering = dropped.exception()


__all__ = ["BrokerClient"]
