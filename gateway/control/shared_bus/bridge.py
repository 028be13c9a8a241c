"""Other masters' requests answered: checked, from the cache, or through their bus's queue.

Each request is checked here (unit id, function, lengths, the client's write grants, the
flash budget) and answered from the cache where the client accepts it; the rest goes to
its bus task's queue (:class:`~gateway.line.engine.foreign.ForeignQueue`), sent under the line's
timing rules within the bus time other masters may have. A client gets the device's
answer or a Modbus exception, never a value made up; nothing malformed reaches the line,
since line requests are framed anew from what was checked.
"""

from __future__ import annotations

import logging
import time
from typing import TYPE_CHECKING

from gateway.control.clock_trust import clock_refusal, time_point_touched
from gateway.control.flash import utc_today
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
from gateway.errors import (
    BusBusyError,
    BusClosedError,
    BusTimeoutError,
    CommandRejectedError,
    DeviceExceptionError,
    FrameError,
    RecordError,
)
from gateway.profiles.model import Storage
from gateway.records.actor import Actor, Via
from gateway.records.model import DeviceRef, Entry, Kind, PointChange, Result
from gateway.shared.host_clock import HostClock

if TYPE_CHECKING:
    from collections.abc import Mapping

    from gateway.control.flash import FlashLedger
    from gateway.control.shared_bus.pdu import ClientRequest
    from gateway.control.shared_bus.policy import ClientPolicy, Unit
    from gateway.line.engine.fair_share import Origin
    from gateway.line.engine.worker import BusWorker
    from gateway.records.model import Record
    from gateway.records.store import RecordStore
    from gateway.shared.state import SharedBusClient
    from gateway.wire import frames

_LOGGER = logging.getLogger(__name__)


class Bridge:
    """The way from a request's PDU to its answer's, for every unit of every bus."""

    def __init__(
        self,
        *,
        units: Mapping[int, Unit],
        workers: Mapping[str, BusWorker],
        ledger: FlashLedger,
        flash_budgets: Mapping[str, int],
        clock: HostClock | None = None,
        records: RecordStore | None = None,
    ) -> None:
        """Requests for ``units`` go to the ``workers`` of their buses.

        ``clock``: a write of a date-and-time register waits for it to be trusted.
        ``records``: where each write is recorded (client, address, unit, registers) before
        it is sent, and its outcome after.
        """
        self.units = units
        self.workers = workers
        self.ledger = ledger
        self.flash_budgets = flash_budgets
        self.clock = clock if clock is not None else HostClock()
        self.records = records

    async def answer(
        self,
        client: ClientPolicy,
        unit: int,
        pdu: bytes,
        stats: SharedBusClient,
        *,
        origin: Origin,
    ) -> tuple[bytes, bool]:
        """The answer PDU to one request for ``unit``; whether it came without the line.

        A request for the line goes in the turn of ``origin`` (the connection it came on).
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
                self._check_clock(target, request, worker)
                self._check_flash(target, request, worker)
            elif (cached := self._cached(client, target, request, worker)) is not None:
                stats.cache_answers += 1
                return cached, True
            forwarded = True
            return (
                await self._forward(client, target, request, worker, stats, origin=origin),
                False,
            )
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

    def _check_clock(self, target: Unit, request: ClientRequest, worker: BusWorker) -> None:
        """Refuse a write of a date (a clock, a calibration stamp) while the clock is a guess."""
        profile = worker.device_profile(target.device)
        point = time_point_touched(profile, request.address, request.count)
        why = point and clock_refusal(self.clock, f"writing {point.name} of {target.device}", point)
        if why:
            raise RequestRefusedError(ILLEGAL_FUNCTION, why, label="clock_unsynchronised")

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
        *,
        origin: Origin,
    ) -> bytes:
        """Send the request in ``origin``'s turn on the line; the device's answer or an exception.

        ``origin`` is the client's connection: the fair share is between clients.
        """
        line = line_request(request, target.address)
        pending = (
            self._record(client, target, request, worker, origin)
            if request.is_write and self.records is not None
            else None
        )
        try:
            response = await self._sent(target, line, worker, stats, origin)
        except RequestRefusedError as refused:
            self._outcome(pending, Result.FAILED, refused.reason)
            raise
        if isinstance(response, bytes):  # the device's exception answer
            self._outcome(pending, Result.FAILED, f"the device answered exception {response[-1]}")
            return response
        self._outcome(pending, Result.DONE, "")
        if request.is_write:
            _LOGGER.info(
                "shared bus: client %s wrote %d registers at %#06x of %s",
                client.name,
                request.count,
                request.address,
                target.device,
            )
        return answer_pdu(request, response)

    async def _sent(
        self,
        target: Unit,
        line: frames.Request,
        worker: BusWorker,
        stats: SharedBusClient,
        origin: Origin,
    ) -> frames.Response | bytes:
        """The device's response, or its exception as the answer PDU."""
        try:
            job = worker.foreign.submit(target.device, line, origin)
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
        return response

    def _record(
        self,
        client: ClientPolicy,
        target: Unit,
        request: ClientRequest,
        worker: BusWorker,
        origin: Origin,
    ) -> Record:
        """Another master's write, recorded before it is sent (else it is refused)."""
        assert self.records is not None  # noqa: S101 - called only with a store
        profile = worker.device_profile(target.device)
        touched = [
            point.name
            for point in profile.points
            if point.address <= request.last and point.last >= request.address
        ]
        entry = Entry(
            kind=Kind.WRITE,
            actor=Actor(
                user=origin.address or client.name,
                via=Via.SHARED_BUS,
                detail=f"client {client.name}, connection {origin.connection}, unit {target.unit}",
            ),
            device=DeviceRef(
                name=target.device,
                profile=profile.id,
                bus=target.bus,
                address=target.address,
            ),
            action=f"another master's write of {request.count} register(s) at "
            f"0x{request.address:04X} ({', '.join(touched) or 'no named point'})",
            result=Result.PENDING,
            points=tuple(
                PointChange(point=name, unit=profile.point(name).unit) for name in touched
            ),
            data={
                "function": request.function,
                "address": f"0x{request.address:04X}",
                "registers": [f"0x{word:04X}" for word in request.values],
            },
            note="passed through: the registers as sent; not read before or after",
        )
        try:
            return self.records.append(entry)
        except RecordError as exc:
            raise RequestRefusedError(DEVICE_FAILURE, str(exc), label="records") from exc

    def _outcome(self, pending: Record | None, result: Result, note: str) -> None:
        """What became of a recorded write (the next start says so if this fails)."""
        if pending is None or self.records is None:
            return
        device = pending.body.get("device")
        try:
            self.records.append(
                Entry(
                    kind=Kind.OUTCOME,
                    actor=Actor(user="gateway", via=Via.SHARED_BUS),
                    device=DeviceRef.from_dict(device) if isinstance(device, dict) else None,
                    action=str(pending.body.get("action", "")),
                    result=result,
                    note=note,
                    completes=pending.seq,
                )
            )
        except RecordError as exc:
            _LOGGER.error(  # noqa: TRY400 - the cause is the message
                "shared bus: the outcome of record %d was not recorded: %s", pending.seq, exc
            )
