"""The broker client after a failed or cancelled connection attempt (``publish.mqtt.client``).

A slow broker (a cluster electing a leader answers CONNECT after seconds) is a TCP server
here that reads CONNECT and answers only when told. aiomqtt 2.5.1 alone fails these tests:
the attempt's socket stays open, and a cancelled attempt's socket logs asyncio's "Exception
in callback" (a ``CancelledError`` traceback) when the broker answers and closes; a write
queued as a drop is read meets a closed socket (an ``EBADF`` traceback).
"""

from __future__ import annotations

import asyncio
import contextlib
import gc
import select
import socket
import threading
from pathlib import Path
from typing import TYPE_CHECKING, Any, Final

import aiomqtt
import pytest

from gateway.publish.mqtt.client import BrokerClient
from tests.mqtt_broker import recording
from tests.waiting import eventually

if TYPE_CHECKING:
    from collections.abc import AsyncIterator

    from tests.mqtt_broker import Broker

CONNACK_ACCEPTED: Final = b"\x20\x02\x00\x00"
WAIT_S: Final = 5.0


class SlowBroker:
    """Accepts, reads the CONNECT, answers CONNACK and closes when :attr:`answer` is set."""

    def __init__(self) -> None:
        self.connect_read = asyncio.Event()
        self.answer = asyncio.Event()
        self.client_closed = asyncio.Event()  # the client's side of the socket is closed

    async def serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        await reader.read(1024)  # the CONNECT, whole in one small segment
        self.connect_read.set()
        answered = asyncio.ensure_future(self.answer.wait())
        eof = asyncio.ensure_future(reader.read(1024))
        await asyncio.wait({answered, eof}, return_when=asyncio.FIRST_COMPLETED)
        if eof.done() and eof.result() == b"":
            self.client_closed.set()
        if not answered.done():
            answered.cancel()
        else:
            with contextlib.suppress(ConnectionError):
                writer.write(CONNACK_ACCEPTED)
                await writer.drain()
        eof.cancel()
        writer.close()
        with contextlib.suppress(ConnectionError):
            await writer.wait_closed()


@contextlib.asynccontextmanager
async def slow_broker() -> AsyncIterator[tuple[SlowBroker, int]]:
    broker = SlowBroker()
    server = await asyncio.start_server(broker.serve, "127.0.0.1", 0)
    port = server.sockets[0].getsockname()[1]
    async with server:
        yield broker, port


@contextlib.contextmanager
def loop_errors() -> Any:
    """Every context the event loop's exception handler got meanwhile."""
    loop = asyncio.get_running_loop()
    seen: list[dict[str, Any]] = []
    previous = loop.get_exception_handler()
    loop.set_exception_handler(lambda _loop, context: seen.append(context))
    try:
        yield seen
    finally:
        loop.set_exception_handler(previous)


async def cancelled_attempt(broker: SlowBroker, port: int) -> None:
    """Connect to ``broker`` and cancel the attempt once the broker has read CONNECT."""
    client = BrokerClient("127.0.0.1", port, timeout=WAIT_S)
    attempt = asyncio.create_task(client.__aenter__())
    await asyncio.wait_for(broker.connect_read.wait(), WAIT_S)
    attempt.cancel()  # a stop or a reload while connecting
    with pytest.raises(asyncio.CancelledError):
        await attempt


async def test_a_cancelled_attempt_logs_nothing_when_the_broker_answers_late() -> None:
    async with slow_broker() as (broker, port):
        with loop_errors() as errors:
            await cancelled_attempt(broker, port)
            broker.answer.set()  # CONNACK, then the broker closes
            for _ in range(20):  # the loop's turns in which the answer would be read
                await asyncio.sleep(0.01)
        assert errors == []


async def test_a_cancelled_attempt_is_closed() -> None:
    async with slow_broker() as (broker, port):
        await cancelled_attempt(broker, port)
        await asyncio.wait_for(broker.client_closed.wait(), WAIT_S)


async def test_a_timed_out_attempt_is_closed() -> None:
    async with slow_broker() as (broker, port):
        with loop_errors() as errors:
            client = BrokerClient("127.0.0.1", port, timeout=0.3)
            with pytest.raises(aiomqtt.MqttError, match="timed out"):
                await client.__aenter__()
            await asyncio.wait_for(broker.client_closed.wait(), WAIT_S)
        assert errors == []


async def test_entering_again_meanwhile_is_refused_and_leaves_the_attempt_be() -> None:
    async with slow_broker() as (broker, port):
        client = BrokerClient("127.0.0.1", port, timeout=WAIT_S)
        attempt = asyncio.create_task(client.__aenter__())
        await asyncio.wait_for(broker.connect_read.wait(), WAIT_S)
        with pytest.raises(aiomqtt.MqttReentrantError):
            await client.__aenter__()
        # The attempt under way is not closed: a close would reach the broker at once.
        await asyncio.sleep(0.2)
        assert not broker.client_closed.is_set()
        attempt.cancel()
        with pytest.raises(asyncio.CancelledError):
            await attempt
        await asyncio.wait_for(broker.client_closed.wait(), WAIT_S)


async def _closes_after_connack(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
    """Accepts the connection and closes it at once (a broker stopping as it accepts)."""
    await reader.read(1024)  # CONNECT
    writer.write(CONNACK_ACCEPTED)
    writer.close()
    with contextlib.suppress(ConnectionError):
        await writer.wait_closed()


async def test_a_connection_closed_as_it_is_made_is_not_forgotten() -> None:
    """The CONNACK and the close may come in one turn of the loop, before aiomqtt's connect
    returns; aiomqtt then forgot the drop, and the client waited on a dead socket."""
    server = await asyncio.start_server(_closes_after_connack, "127.0.0.1", 0)
    port = server.sockets[0].getsockname()[1]
    async with server:
        with loop_errors() as errors:
            for _ in range(10):  # either ordering of the loop's callbacks, whichever comes
                client = BrokerClient("127.0.0.1", port, timeout=WAIT_S)
                with pytest.raises(aiomqtt.MqttError):
                    async with client:
                        await asyncio.wait_for(anext(aiter(client.messages)), WAIT_S)
            del client
            gc.collect()  # a future whose exception nobody read says so when it is freed
            await asyncio.sleep(0)
        assert errors == []


def syn_sent_to(port: int) -> bool:
    """Whether a TCP connect to ``port`` on this machine waits for its SYN's answer."""
    for line in Path("/proc/net/tcp").read_text(encoding="ascii").splitlines()[1:]:
        fields = line.split()
        remote_port = int(fields[2].split(":")[1], 16)
        if remote_port == port and fields[3] == "02":  # TCP_SYN_SENT
            return True
    return False


async def test_an_attempt_cancelled_while_connecting_in_its_thread_is_closed_after_it() -> None:
    """A stop while paho's connect still waits in its thread: the session is not kept.

    The broker's accept queue is full (a listener with a backlog of 0, one connection
    queued), so the kernel drops the client's SYN and paho's connect waits in its thread
    for the retransmission, as it would for a far broker. The attempt is cancelled then;
    the queue is emptied, the SYN sent again gets through, and the socket is closed before
    or just after paho writes its CONNECT. Before the fix the broker kept that connection
    (under the gateway's client id, with its will) until it stopped, and the drop was then
    reported as an exception nobody retrieved.
    """
    loop = asyncio.get_running_loop()
    with socket.socket() as listener:
        listener.bind(("127.0.0.1", 0))
        listener.listen(0)
        listener.setblocking(False)  # noqa: FBT003 - the socket API's own
        port = listener.getsockname()[1]
        filler = socket.create_connection(("127.0.0.1", port))  # the accept queue is full
        with loop_errors() as errors:
            client = BrokerClient("127.0.0.1", port, timeout=WAIT_S)
            attempt = asyncio.create_task(client.__aenter__())
            await eventually(lambda: syn_sent_to(port), within_s=WAIT_S)
            attempt.cancel()  # a stop, with paho's connect waiting in its thread
            queued, _ = await loop.sock_accept(listener)
            queued.close()
            filler.close()
            connection, _ = await asyncio.wait_for(loop.sock_accept(listener), WAIT_S)
            with connection:  # paho's connect got through: its socket is closed at once
                sent = b""
                while chunk := await asyncio.wait_for(loop.sock_recv(connection, 1024), WAIT_S):
                    sent += chunk
            assert sent == b"" or sent[:1] == b"\x10"  # nothing, or its CONNECT
            with pytest.raises(asyncio.CancelledError):
                await attempt
            del client, attempt
            gc.collect()  # a future whose exception nobody read says so when it is freed
            await asyncio.sleep(0)
        assert errors == []


async def _closes_at_subscribe(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
    """Accepts the connection, then closes it when the SUBSCRIBE comes (as a RabbitMQ node
    refuses a QoS 1 subscription whose queue's node is down)."""
    await reader.read(1024)  # CONNECT
    writer.write(CONNACK_ACCEPTED)
    await writer.drain()
    await reader.read(1024)  # SUBSCRIBE
    writer.close()
    with contextlib.suppress(ConnectionError):
        await writer.wait_closed()


async def test_a_connection_closed_during_a_subscribe_fails_it_at_once_and_logs_nothing() -> None:
    server = await asyncio.start_server(_closes_at_subscribe, "127.0.0.1", 0)
    port = server.sockets[0].getsockname()[1]
    async with server:
        with loop_errors() as errors:
            loop = asyncio.get_running_loop()
            client = BrokerClient("127.0.0.1", port, timeout=WAIT_S)
            async with contextlib.AsyncExitStack() as stack:
                await stack.enter_async_context(client)
                started = loop.time()
                with pytest.raises(aiomqtt.MqttError, match="Disconnected while subscribing"):
                    await client.subscribe("gw/cmd/#", qos=1, timeout=15)
                took_s = loop.time() - started
            del client, stack
            gc.collect()  # a future whose exception nobody read says so when it is freed
            await asyncio.sleep(0)
        assert took_s < 1.0  # not the subscribe timeout of 15 s
        assert errors == []


class ThreadedBroker:
    """Accepts one connection in a thread, answers CONNACK, and closes it when told.

    In a thread, not the loop: the test can then wait for the close to be readable on the
    client's socket while the loop has not yet run its reader.
    """

    def __init__(self) -> None:
        self._listener = socket.create_server(("127.0.0.1", 0))
        self.port: int = self._listener.getsockname()[1]
        self.close_now = threading.Event()
        self._thread = threading.Thread(target=self._serve, daemon=True)
        self._thread.start()

    def _serve(self) -> None:
        connection, _ = self._listener.accept()
        with connection:
            connection.recv(1024)  # CONNECT
            connection.sendall(CONNACK_ACCEPTED)
            self.close_now.wait(WAIT_S)

    def stop(self) -> None:
        self.close_now.set()
        self._thread.join(WAIT_S)
        self._listener.close()


async def loop_turned() -> None:
    """Return once every callback queued before this call ran (the loop runs them in order)."""
    loop = asyncio.get_running_loop()
    done: asyncio.Future[None] = loop.create_future()
    loop.call_soon_threadsafe(done.set_result, None)
    await done


async def test_a_publish_queued_as_the_drop_is_read_logs_nothing() -> None:
    """A NATS node killed while the gateway published: paho queued its write, the loop read
    the close in the same turn, and aiomqtt's queued writer met a closed socket (asyncio's
    "Exception in callback", ``EBADF``)."""
    broker = ThreadedBroker()
    try:
        with loop_errors() as errors:
            client = BrokerClient("127.0.0.1", broker.port, identifier="cab2-gw", timeout=WAIT_S)
            await client.__aenter__()
            paho = client._client  # the two steps of one turn, as paho takes them
            sock = paho.socket()
            assert isinstance(sock, socket.socket)
            broker.close_now.set()
            readable, _, _ = select.select([sock], [], [], WAIT_S)  # the loop not told yet
            assert readable == [sock]
            paho.publish("cab2/oxygen", b"8.1", qos=1)  # queues the writer, as aiomqtt's publish
            paho.loop_read()  # the loop's reader next, in the same turn: reads the close
            assert paho.socket() is None  # closed
            await loop_turned()  # the queued writer has run
            with contextlib.suppress(aiomqtt.MqttError):
                await client.__aexit__(None, None, None)
            del client, paho
            gc.collect()
            await asyncio.sleep(0)
        assert errors == []
    finally:
        broker.stop()


@pytest.mark.broker
async def test_a_publish_larger_than_the_socket_takes_goes_out_whole(broker: Broker) -> None:
    """A publish of the loop's own is written in the loop's next pass, with no writer added.

    What the socket does not take at once (16 MiB, beyond any loopback send buffer) goes
    out as it drains: a writer is added for the rest. Without it the message was cut short
    and never acknowledged.
    """
    payload = "0123456789abcdef" * (1024 * 1024)
    async with recording(broker.port, "big/#") as recorder:
        async with BrokerClient("127.0.0.1", broker.port, identifier="big-publisher") as client:
            await client.publish("big/one", payload, qos=1, timeout=30)
        await recorder.wait_for("big/one", within_s=30)
    assert recorder.on("big/one") == [payload]
