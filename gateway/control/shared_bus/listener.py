"""The shared bus: other masters' Modbus TCP (or RTU-over-TCP) connections to the lines.

The listeners and every client's connection: requests cut from its bytes, each answered
by the :class:`~gateway.control.shared_bus.bridge.Bridge` (checked, from the cache, or
through its bus's queue) and framed back, in order.

The same event loop polls the lines, so no client may hold it: every answer yields
before the next request is taken, each source address gets ``rate_limit`` requests a
second (:mod:`~gateway.control.shared_bus.throttle`), and a connection is read only as
far as ``max_in_flight`` requests ahead (:mod:`~gateway.control.shared_bus.connection`).
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import logging
import os
import time
from typing import TYPE_CHECKING, Final, Self

from gateway.control.shared_bus.bridge import Bridge
from gateway.control.shared_bus.connection import ClientConnection
from gateway.control.shared_bus.framing import FramingError, framer_for
from gateway.control.shared_bus.pdu import DEVICE_BUSY, exception_pdu
from gateway.control.shared_bus.policy import client_for, client_policies, origin_of
from gateway.control.shared_bus.throttle import Throttle
from gateway.errors import ConfigError
from gateway.line.engine.lateness import loop_watch

if TYPE_CHECKING:
    from collections.abc import Mapping

    from gateway.config.shared_bus import ListenConfig, SharedBusConfig
    from gateway.control.flash import FlashLedger
    from gateway.control.shared_bus.framing import Framer
    from gateway.control.shared_bus.policy import ClientPolicy, Unit
    from gateway.line.engine.worker import BusWorker
    from gateway.records.store import RecordStore
    from gateway.shared.host_clock import HostClock
    from gateway.shared.state import GatewayState, SharedBusClient

_LOGGER = logging.getLogger(__name__)

DRAIN_TIMEOUT_S: Final = 10.0  # a client that reads no answers for this long is reset
CLOSE_WAIT_S: Final = 2.0  # for the client's end of an orderly close, then it is reset
LOOP_SOURCE: Final = "answering other masters on the shared bus"  # named in late-poll logs


class _SilentError(Exception):
    """The client sent nothing for ``idle_timeout``."""


class _NotReadingError(Exception):
    """The client read no answer for ``DRAIN_TIMEOUT_S``."""


class SharedBusServer:
    """Serves other masters on the configured addresses while the gateway runs."""

    def __init__(
        self,
        config: SharedBusConfig,
        *,
        units: Mapping[int, Unit],
        workers: Mapping[str, BusWorker],
        ledger: FlashLedger,
        flash_budgets: Mapping[str, int],
        state: GatewayState,
        clock: HostClock | None = None,
        records: RecordStore | None = None,
    ) -> None:
        """Bridge requests for ``units`` to the ``workers`` of their buses.

        ``clock``: the host clock a write of a date register waits to be trusted by;
        ``records``: where each write is recorded.
        """
        self.config = config
        self.bridge = Bridge(
            units=units,
            workers=workers,
            ledger=ledger,
            flash_budgets=flash_budgets,
            clock=clock,
            records=records,
        )
        self.status = state.shared_bus
        self._clients = client_policies(config.clients)
        self._servers: list[asyncio.Server] = []
        self._connections: set[asyncio.Task[None]] = set()
        self._open: set[ClientConnection] = set()
        self._throttle = Throttle(max_wait_s=config.max_wait)
        self.status.enabled = True
        self.status.share = config.bus_share
        for name, worker in workers.items():
            self.status.buses[name] = worker.foreign.stats

    async def start(self) -> None:
        """Listen on every configured address; one that cannot be bound is a ConfigError."""
        loop = asyncio.get_running_loop()
        for index, listen in enumerate(self.config.listen):
            try:
                server = await loop.create_server(
                    functools.partial(
                        ClientConnection, functools.partial(self._opened, listen=listen)
                    ),
                    host=listen.host,
                    port=listen.port,
                )
            except OSError as exc:
                await self.close()
                reason = os.strerror(exc.errno).lower() if exc.errno else str(exc)
                raise ConfigError(
                    f"cannot listen on {listen.host}:{listen.port}: {reason}",
                    key=f"shared_bus.listen[{index}]",
                ) from exc
            self._servers.append(server)
            for sock in server.sockets:
                host, port = sock.getsockname()[:2]
                self.status.listening.append(f"{listen.framing}://{host}:{port}")
            _LOGGER.info(
                "shared bus: other masters reach the devices on %s:%d (%s)",
                listen.host,
                listen.port,
                "Modbus TCP" if listen.framing == "tcp" else "RTU over TCP",
            )

    async def __aenter__(self) -> Self:
        """Listen (:meth:`start`); :meth:`close` on leaving."""
        await self.start()
        return self

    async def __aexit__(self, *_: object) -> None:
        """Stop listening and end every connection."""
        await self.close()

    async def close(self) -> None:
        """Stop listening and end every connection."""
        for server in self._servers:
            server.close()
        for task in list(self._connections):
            task.cancel()
        if self._connections:
            await asyncio.wait(self._connections, timeout=1.0)
        for server in self._servers:
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(1.0):
                    await server.wait_closed()
        self._servers.clear()

    # --- connections ----------------------------------------------------------------------

    def _opened(self, connection: ClientConnection, *, listen: ListenConfig) -> None:
        """A client connected: serve it in a task of its own, or refuse it over the limit."""
        host, port = connection.peer
        if len(self._open) >= self.config.max_connections:
            _LOGGER.warning(
                "shared bus: %s:%d refused: %d connections already",
                host,
                port,
                len(self._open),
            )
            self.status.client(client_for(self._clients, host).name).closed["limit"] += 1
            connection.close()
            return
        # A socket counts until it is really closed, not until its task ends: a client
        # that reads nothing must not leave sockets behind that no limit sees.
        self._open.add(connection)
        connection.when_gone(self._open.discard)
        task = asyncio.create_task(
            self._connection(connection, listen=listen), name=f"shared_bus[{host}:{port}]"
        )
        self._connections.add(task)
        task.add_done_callback(self._connections.discard)

    async def _connection(self, connection: ClientConnection, *, listen: ListenConfig) -> None:
        host, port = connection.peer
        client = client_for(self._clients, host)
        stats = self.status.client(client.name)
        name = f"{host}:{port}"
        stats.peers[name] = time.time()
        _LOGGER.info("shared bus: %s connected (client %s)", name, client.name)
        ending = "eof"
        try:
            await self._serve(connection, framer_for(listen.framing), client, stats)
        except FramingError as exc:
            ending = "malformed_frame"
            stats.refused["malformed_frame"] += 1
            _LOGGER.warning("shared bus: %s: %s; connection closed", name, exc)
        except _SilentError:
            ending = "idle"
            _LOGGER.info("shared bus: %s silent; connection closed", name)
        except _NotReadingError:
            ending = "not_reading"
            _LOGGER.warning(
                "shared bus: %s read no answer for %.0f s; connection reset", name, DRAIN_TIMEOUT_S
            )
        except (ConnectionError, OSError) as exc:
            ending = "lost"
            _LOGGER.debug("shared bus: %s: %s", name, exc)
        except asyncio.CancelledError:
            ending = "stopped"  # the gateway stops: no time for an orderly end
            raise
        finally:
            stats.peers.pop(name, None)
            stats.closed[ending] += 1
            await self._end(connection, graceful=ending in {"eof", "idle", "malformed_frame"})
            _LOGGER.info("shared bus: %s disconnected", name)

    @staticmethod
    async def _end(connection: ClientConnection, *, graceful: bool) -> None:
        """Close the socket for good: an orderly end to a client that reads, else a reset."""
        if graceful:
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(CLOSE_WAIT_S):
                    await connection.finish()
        connection.abort()  # nothing left to send, or a client that does not take it
        with contextlib.suppress(TimeoutError):
            async with asyncio.timeout(CLOSE_WAIT_S):
                await connection.gone()

    async def _serve(
        self,
        connection: ClientConnection,
        framer: Framer,
        client: ClientPolicy,
        stats: SharedBusClient,
    ) -> None:
        """One request at a time, in order; at most ``max_in_flight`` read ahead of answers.

        Each answer yields to the event loop, so requests the gateway answers itself (a
        refusal, a cache hit) take turns with the polls however fast they come.
        """
        host = connection.peer[0]
        origin = origin_of(connection.peer)  # its turn on the line, beside other clients
        rate = client.rate_limit or self.config.rate_limit
        # One read holds at most ``max_in_flight`` requests, and the socket is read only
        # when no whole request is left: the rest waits in TCP's buffers.
        read_size = self.config.max_in_flight * framer.min_frame
        buffer = b""
        watch = loop_watch()
        while True:
            frame = framer.decode(buffer)
            if frame is None:
                chunk = await self._receive(connection, framer, buffer, read_size)
                if chunk is None:  # a silence ended the frame the buffer holds
                    frame = framer.decode(buffer, silent=True)
                else:
                    if not chunk:
                        return
                    stats.received_bytes += len(chunk)
                    buffer += chunk
                    continue
            assert frame is not None  # noqa: S101 - a silent decode returns one or raises
            buffer = buffer[frame.used :]
            wait = self._throttle.reserve(host, rate, time.monotonic())
            if wait != 0:
                # Over its rate: this connection waits, reading nothing. A request whose
                # turn comes after ``max_wait`` gets 06 then, as one the line cannot take
                # in time; it waits too, so shedding costs no more than answering.
                paused = self.config.max_wait if wait is None else wait
                stats.throttled_s += paused
                await asyncio.sleep(paused)
            started = time.perf_counter()
            if wait is None:
                function = frame.pdu[0] if frame.pdu else 0
                stats.requests[function] += 1
                stats.shed["rate_limit"] += 1
                stats.exceptions[DEVICE_BUSY] += 1
                pdu, local = exception_pdu(function, DEVICE_BUSY), True
            else:
                pdu, local = await self.bridge.answer(
                    client, frame.unit, frame.pdu, stats, origin=origin
                )
            out = framer.encode(pdu, frame.unit, frame.transaction)
            stats.sent_bytes += len(out)
            if local:
                watch.charge(LOOP_SOURCE, time.perf_counter() - started, started)
            try:
                async with asyncio.timeout(DRAIN_TIMEOUT_S):
                    await connection.send(out)
            except TimeoutError as exc:
                raise _NotReadingError from exc
            await asyncio.sleep(0)  # the polls' turn, whatever the client sends next

    async def _receive(
        self, connection: ClientConnection, framer: Framer, buffer: bytes, read_size: int
    ) -> bytes | None:
        """The next bytes (``b""`` at EOF); ``None`` when a silence ends the buffer's frame."""
        silence = framer.silence_s if buffer else None
        try:
            async with asyncio.timeout(silence or self.config.idle_timeout):
                return await connection.receive(read_size)
        except TimeoutError as exc:
            if silence is not None:
                return None
            raise _SilentError from exc
