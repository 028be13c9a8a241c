"""The shared bus: other masters' Modbus TCP (or RTU-over-TCP) requests, bridged to the lines.

Each request is checked here (unit id, function, lengths, the client's write grants, the
flash budget) and answered from the cache where the client accepts it; the rest goes to
its bus task's queue (:class:`~gateway.line.foreign.ForeignQueue`), sent under the line's
timing rules within the bus time other masters may have. A client gets the device's
answer or a Modbus exception, never a value made up; nothing malformed reaches the line,
since line requests are framed anew from what was checked.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import logging
import os
import time
from typing import TYPE_CHECKING, Final, Self

from gateway.control.flash import utc_today
from gateway.control.shared_bus.connection import ClientConnection
from gateway.control.shared_bus.framing import FramingError, framer_for
from gateway.control.shared_bus.pdu import (
    DEVICE_BUSY,
    DEVICE_FAILURE,
    ILLEGAL_FUNCTION,
    PATH_UNAVAILABLE,
    TARGET_FAILED,
    WRITE_FUNCTIONS,
    RequestRefusedError,
    answer_pdu,
    cached_read_pdu,
    device_exception_pdu,
    exception_pdu,
    line_request,
    parse_request,
)
from gateway.control.shared_bus.policy import client_for, client_policies
from gateway.control.shared_bus.throttle import Throttle
from gateway.errors import (
    BusBusyError,
    BusClosedError,
    BusTimeoutError,
    CommandRejectedError,
    ConfigError,
    DeviceExceptionError,
    FrameError,
)
from gateway.line.lateness import loop_watch
from gateway.profiles.model import Storage

if TYPE_CHECKING:
    from collections.abc import Mapping

    from gateway.config.shared_bus import ListenConfig, SharedBusConfig
    from gateway.control.flash import FlashLedger
    from gateway.control.shared_bus.framing import Framer
    from gateway.control.shared_bus.pdu import ClientRequest
    from gateway.control.shared_bus.policy import ClientPolicy, Unit
    from gateway.line.worker import BusWorker
    from gateway.publish.state import GatewayState, SharedBusClient
    from gateway.wire import frames

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
    ) -> None:
        """Bridge requests for ``units`` to the ``workers`` of their buses."""
        self.config = config
        self.units = units
        self.workers = workers
        self.ledger = ledger
        self.flash_budgets = flash_budgets
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

    @property
    def open_connections(self) -> int:
        """Sockets of clients not yet closed (they count toward ``max_connections``)."""
        return len(self._open)

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
                stats.requests[frame.pdu[0] if frame.pdu else 0] += 1
                stats.shed["rate_limit"] += 1
                stats.exceptions[DEVICE_BUSY] += 1
                pdu, local = exception_pdu(frame.pdu[0] if frame.pdu else 0, DEVICE_BUSY), True
            else:
                pdu, local = await self._answer(client, frame.unit, frame.pdu, stats)
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

    # --- requests -------------------------------------------------------------------------

    async def answer(
        self, client: ClientPolicy, unit: int, pdu: bytes, stats: SharedBusClient
    ) -> bytes:
        """The answer PDU to one request of ``client`` for ``unit``."""
        answer, _ = await self._answer(client, unit, pdu, stats)
        return answer

    async def _answer(
        self, client: ClientPolicy, unit: int, pdu: bytes, stats: SharedBusClient
    ) -> tuple[bytes, bool]:
        """The answer PDU, and whether the gateway gave it itself (without the line).

        An answer given without the line is given without a pause (no ``await``): the
        caller's clock around it is the time it held the event loop.
        """
        function = pdu[0] if pdu else 0
        stats.requests[function] += 1
        forwarded = False
        try:
            target = self.units.get(unit)
            if target is None:
                raise RequestRefusedError(  # noqa: TRY301 - one place turns refusals into answers
                    PATH_UNAVAILABLE, f"no device answers to unit {unit}", label="unknown_unit"
                )
            request = parse_request(pdu)
            worker = self.workers[target.bus]
            if request.is_write:
                client.check_write(target.device, request)
                self._check_flash(target, request, worker)
            elif (cached := self._cached(client, target, request, worker)) is not None:
                stats.cache_answers += 1
                return cached, True
            forwarded = True
            return await self._forward(client, target, request, worker, stats), False
        except RequestRefusedError as refused:
            stats.exceptions[refused.code] += 1
            stats.refused[refused.label] += 1
            # A refused write is news for whoever runs the plant; a busy line is not.
            log = _LOGGER.warning if function in WRITE_FUNCTIONS else _LOGGER.debug
            log("shared bus: client %s, unit %d: %s", client.name, unit, refused.reason)
            return exception_pdu(function, refused.code), not forwarded

    def _cached(
        self, client: ClientPolicy, target: Unit, request: ClientRequest, worker: BusWorker
    ) -> bytes | None:
        if client.cache_max_age_s is None:
            return None
        registers = worker.transactions.cache.lookup(
            target.device,
            request.address,
            request.count,
            not_before=time.monotonic() - client.cache_max_age_s,
        )
        return cached_read_pdu(request, registers) if registers is not None else None

    def _check_flash(self, target: Unit, request: ClientRequest, worker: BusWorker) -> None:
        """Refuse a write over the flash budget; count it against the budget otherwise.

        The budget is the device's own (``flash_write_budget``), the one the gateway's own
        writes count against, per flash-backed point the write touches. Counted before
        sending: a write that times out may still have reached the flash.
        """
        profile = worker.device_profile(target.device)
        touched = [
            point
            for point in profile.points
            if point.storage is Storage.FLASH
            and point.address <= request.last
            and point.last >= request.address
        ]
        if not touched:
            return
        budget = self.flash_budgets.get(target.device, 0)
        today = utc_today()
        for point in touched:
            if self.ledger.count_today(target.device, point.name, today) >= budget:
                raise RequestRefusedError(
                    ILLEGAL_FUNCTION,
                    f"the flash budget of {budget} writes per day for "
                    f"{target.device}/{point.name} is spent",
                    label="flash_budget",
                )
        try:
            for point in touched:
                self.ledger.record(target.device, point.name, today)
        except CommandRejectedError as exc:  # the ledger cannot count it: it is not sent
            raise RequestRefusedError(DEVICE_FAILURE, exc.reason, label="flash_ledger") from exc

    async def _forward(
        self,
        client: ClientPolicy,
        target: Unit,
        request: ClientRequest,
        worker: BusWorker,
        stats: SharedBusClient,
    ) -> bytes:
        """Send the request in its turn on the line; the device's answer or an exception."""
        line = line_request(request, target.address)
        try:
            job = worker.foreign.submit(target.device, line)
        except BusBusyError as exc:
            raise RequestRefusedError(DEVICE_BUSY, str(exc), label="busy") from exc
        except BusClosedError as exc:
            raise RequestRefusedError(PATH_UNAVAILABLE, str(exc), label="bus_down") from exc
        try:
            response: frames.Response = await job.done
        except DeviceExceptionError as exc:
            stats.exceptions[exc.code] += 1
            return device_exception_pdu(exc)
        except BusBusyError as exc:
            raise RequestRefusedError(DEVICE_BUSY, str(exc), label="busy") from exc
        except BusClosedError as exc:
            raise RequestRefusedError(PATH_UNAVAILABLE, str(exc), label="bus_down") from exc
        except (BusTimeoutError, FrameError) as exc:
            raise RequestRefusedError(TARGET_FAILED, str(exc), label="no_answer") from exc
        finally:
            if job.sent_at is not None:
                stats.observe_wait(job.sent_at - job.queued_at)
        if request.is_write:
            _LOGGER.info(
                "shared bus: client %s wrote %d registers at %#06x of %s",
                client.name,
                request.count,
                request.address,
                target.device,
            )
        return answer_pdu(request, response)
