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
from gateway.errors import (
    BusBusyError,
    BusClosedError,
    BusTimeoutError,
    CommandRejectedError,
    ConfigError,
    DeviceExceptionError,
    FrameError,
)
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

READ_CHUNK: Final = 4096
DRAIN_TIMEOUT_S: Final = 10.0  # a client that reads no answers for this long is dropped


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
        self.status.enabled = True
        self.status.share = config.bus_share
        for name, worker in workers.items():
            self.status.buses[name] = worker.foreign.stats

    async def start(self) -> None:
        """Listen on every configured address; one that cannot be bound is a ConfigError."""
        for index, listen in enumerate(self.config.listen):
            try:
                server = await asyncio.start_server(
                    functools.partial(self._connection, listen=listen),
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

    async def _connection(
        self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter, *, listen: ListenConfig
    ) -> None:
        task = asyncio.current_task()
        peer = writer.get_extra_info("peername") or ("?", 0)
        host, port = str(peer[0]), int(peer[1])
        client = client_for(self._clients, host)
        if len(self._connections) >= self.config.max_connections:
            _LOGGER.warning(
                "shared bus: %s:%d refused: %d connections already",
                host,
                port,
                len(self._connections),
            )
            writer.close()
            return
        assert task is not None  # noqa: S101 - a connection runs in its own task
        self._connections.add(task)
        stats = self.status.client(client.name)
        name = f"{host}:{port}"
        stats.peers[name] = time.time()
        _LOGGER.info("shared bus: %s connected (client %s)", name, client.name)
        try:
            await self._serve(reader, writer, framer_for(listen.framing), client, stats)
        except FramingError as exc:
            stats.refused["malformed_frame"] += 1
            _LOGGER.warning("shared bus: %s: %s; connection closed", name, exc)
        except TimeoutError:
            _LOGGER.info("shared bus: %s silent or not reading; connection closed", name)
        except (ConnectionError, OSError) as exc:
            _LOGGER.debug("shared bus: %s: %s", name, exc)
        finally:
            stats.peers.pop(name, None)
            self._connections.discard(task)
            writer.close()
            with contextlib.suppress(ConnectionError, OSError, TimeoutError):
                async with asyncio.timeout(1.0):
                    await writer.wait_closed()
            _LOGGER.info("shared bus: %s disconnected", name)

    async def _serve(
        self,
        reader: asyncio.StreamReader,
        writer: asyncio.StreamWriter,
        framer: Framer,
        client: ClientPolicy,
        stats: SharedBusClient,
    ) -> None:
        """One request at a time, in order: the next is read once this one is answered."""
        buffer = b""
        while True:
            frame = framer.decode(buffer)
            if frame is None:
                async with asyncio.timeout(self.config.idle_timeout):
                    chunk = await reader.read(READ_CHUNK)
                if not chunk:
                    return
                stats.received_bytes += len(chunk)
                buffer += chunk
                continue
            buffer = buffer[frame.used :]
            pdu = await self.answer(client, frame.unit, frame.pdu, stats)
            out = framer.encode(pdu, frame.unit, frame.transaction)
            writer.write(out)
            stats.sent_bytes += len(out)
            async with asyncio.timeout(DRAIN_TIMEOUT_S):
                await writer.drain()

    # --- requests -------------------------------------------------------------------------

    async def answer(
        self, client: ClientPolicy, unit: int, pdu: bytes, stats: SharedBusClient
    ) -> bytes:
        """The answer PDU to one request of ``client`` for ``unit``."""
        function = pdu[0] if pdu else 0
        stats.requests[function] += 1
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
                return cached
            return await self._forward(client, target, request, worker, stats)
        except RequestRefusedError as refused:
            stats.exceptions[refused.code] += 1
            stats.refused[refused.label] += 1
            # A refused write is news for whoever runs the plant; a busy line is not.
            log = _LOGGER.warning if function in WRITE_FUNCTIONS else _LOGGER.debug
            log("shared bus: client %s, unit %d: %s", client.name, unit, refused.reason)
            return exception_pdu(function, refused.code)

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
