"""A bus behind a serial device server in Modbus TCP mode (``tcp://host:502``).

The converter takes Modbus TCP frames (MBAP header, unit id = device address), puts each
on its RS485 side as an RTU frame with its own inter-frame gap, waits for the device, and
sends the answer back with the request's transaction id. So on this side there is no gap
to keep and no CRC to check; what still holds is above the line, in
:mod:`gateway.line.engine.transactions`: the device's post-write waits and, after no answer of its
own, its late-answer window (both arrive here as ``not_before``). The response timeout
allows for the converter: the request's RTU time on the wire, the converter's gap, then
the timeout the transactions give (the answer's wire time, the device's t1, a margin that
covers a LAN's round trip; a slower network needs the bus's ``timeout``).

Stale-frame protection is the transaction id: an answer to an older request (a late
answer of a device, a converter's 0B after the gateway gave up) is dropped and counted
as a stale frame of its unit; a request whose own answer never came says so, since a
converter that does not return the transaction id it is given looks like that too. The
converter's own exceptions, 0A (no path to its serial side) and 0B (the device did not
answer it), are failures like a timeout with their own names
(:class:`~gateway.errors.ConverterError`), never device exceptions that would split a
read. Stray bytes before an answer are passed over up to the answer's header (its
transaction id), not with everything held.

It stands behind the line's boundary (:class:`gateway.line.boundary.Line`) beside the
RTU lines and shares nothing with them but the boundary, the counters
(:mod:`gateway.line.stats`), the inbox of received bytes and the deadline timer.
"""

from __future__ import annotations

import asyncio
import logging
import math
import struct
import time
from typing import TYPE_CHECKING
from urllib.parse import urlsplit

from gateway.config.network import DEFAULT_TCP
from gateway.errors import (
    BusClosedError,
    BusTimeoutError,
    ConverterError,
    DeviceExceptionError,
    FrameError,
    MalformedFrameError,
)
from gateway.line.boundary import Exchange
from gateway.line.stats import ErrorKind, LineStats, failure_kind
from gateway.line.transports.inbox import LAST_LOOK_S, LAST_LOOKS, Inbox
from gateway.line.transports.tcp_session import (
    MS_PER_S,
    SilenceWatch,
    connect,
    session_ended,
    unread_bytes,
)
from gateway.line.transports.timer import DeadlineTimer
from gateway.wire import frames, mbap

if TYPE_CHECKING:
    from collections.abc import Mapping

    from gateway.config.network import TcpSettings
    from gateway.line.boundary import LateAnswer, RequestOptions, WaitWatch
    from gateway.wire.timing import LineFormat

_LOGGER = logging.getLogger(__name__)
_HEAD = struct.Struct(">HH")  # an MBAP header's transaction id and protocol id, its start


class ModbusTcpLine:
    """One ``tcp://`` bus: Modbus TCP to a serial device server, one transaction at a time."""

    def __init__(
        self,
        *,
        port: str,
        line: LineFormat,
        stats: LineStats | None = None,
        tcp: TcpSettings = DEFAULT_TCP,
        bus: str = "",  # noqa: ARG002 - as the other lines take it; nothing here logs by it
    ) -> None:
        """Describe the bus (``line`` is the converter's serial side); :meth:`open` connects.

        No echo setting: a Modbus TCP session carries no echo of the serial side's.
        """
        self.port = port
        self.format = line
        self.stats = stats or LineStats()
        self.late_answer: LateAnswer | None = None  # a transaction id tells late from stale
        self.wait_watch: WaitWatch | None = None  # no gap to sleep through: never told
        self.last_frame_end = -math.inf
        self._timer = DeadlineTimer()
        parts = urlsplit(port)
        self.host = parts.hostname or ""
        self.tcp_port = parts.port or mbap.DEFAULT_PORT
        self.tcp = tcp
        self.watch = SilenceWatch(port=port, limit=tcp.silent_requests)
        self._session: Inbox | None = None
        self._link: asyncio.Transport | None = None
        self._transaction = 0
        self._ready_at = -math.inf
        # The converter's own gap before it puts a request on its serial side.
        self._converter_gap_s = line.frame_gap_s()

    @property
    def is_open(self) -> bool:
        """Whether the session is up and the converter has not ended it."""
        return self._session is not None and not self._session.lost.is_set()

    def tcp_socket(self) -> asyncio.trsock.TransportSocket | None:
        """The session's socket (for its options), ``None`` while closed."""
        link = self._link
        return link.get_extra_info("socket") if link is not None else None

    async def open(self) -> None:
        """Connect, with keepalive and the user timeout; a failure is a :class:`BusClosedError`."""
        session = Inbox(asyncio.get_running_loop())
        try:
            link = await connect(
                self.port, self.host, self.tcp_port, session, self.tcp, mode="Modbus TCP"
            )
        except BusClosedError as exc:
            self.stats.closed_because(None, str(exc))
            raise
        self._link, self._session = link, session
        self.stats.closed_because(None, "")
        self.stats.port_open = True
        now = time.monotonic()
        self.last_frame_end = now
        self._ready_at = now + self.tcp.connect_pause_s

    def rest(self) -> None:
        """Nothing to stop: this line's timer never looks for the loop's watch."""

    async def close(self) -> None:
        """End the session (idempotent); nothing in flight matters after a stop."""
        link, self._link, self._session = self._link, None, None
        self.stats.port_open = False
        self._timer.close()
        if link is not None and not link.is_closing():
            link.abort()
            await asyncio.sleep(0)

    def _live(self) -> Inbox:
        session = self._session
        if session is None:
            raise BusClosedError(f"{self.port} is not open")
        if session.lost.is_set():
            self.stats.port_open = False
            raise BusClosedError(f"{self.port} went away: {session_ended(session)}")
        return session

    def flush_input(self, device: int) -> None:
        """Drop what arrived between transactions: late answers (stale) and anything else."""
        session = self._live()
        while session.buffer:
            try:
                cut = mbap.decode(session.buffer)
            except MalformedFrameError:
                cut = None
            if cut is None:
                self.stats.errors[device, ErrorKind.NOISE] += 1
                _LOGGER.debug("%s: discarded %s", self.port, session.buffer.hex(" "))
                session.buffer.clear()
                return
            frame, used = cut
            del session.buffer[:used]
            self._stale(frame)

    def _stale(self, frame: mbap.MbapFrame) -> None:
        """An answer to an older request: counted as a stale frame of its unit, dropped."""
        self.stats.errors[frame.unit, ErrorKind.STALE] += 1
        _LOGGER.debug(
            "%s: dropped an answer of unit %d to transaction %d (now %d): %s",
            self.port,
            frame.unit,
            frame.transaction,
            self._transaction,
            frame.pdu.hex(" "),
        )

    async def wait_gap(
        self,
        gap_s: float,  # noqa: ARG002 - no gap on the socket: the converter keeps it
        *,
        not_before: float = 0.0,
        device: int = 0,  # noqa: ARG002 - no noise on a socket to name a device for
    ) -> float:
        """Wait for ``not_before``, the pause after connecting and ``tcp.request_pause_ms``.

        No inter-frame gap (``gap_s``) on the socket: the converter keeps it on its serial
        side. Returns when the request was due.
        """
        self._live()
        pause_s = self.tcp.request_pause_ms / MS_PER_S
        ready = max(not_before, self._ready_at, self.last_frame_end + pause_s)
        await self._timer.sleep_until(ready)
        self._live()
        return ready

    async def transact(self, request: frames.Request, options: RequestOptions) -> Exchange | None:
        """Send ``request`` in an MBAP frame and return its answer (``None`` for broadcasts).

        Raises what :meth:`Line.transact` raises, and a :class:`ConverterError` for the
        converter's exceptions 0A and 0B; every failure is counted by kind for the device.
        """
        await self.wait_gap(options.gap_s, not_before=options.not_before)
        self.flush_input(request.device)
        self._transaction = (self._transaction + 1) & mbap.MAX_TRANSACTION_ID
        transaction = self._transaction
        assert self._link is not None  # noqa: S101 - _live checked it
        sent_at = time.monotonic()
        self._link.write(mbap.from_rtu(transaction, request.frame))
        self.stats.requests[request.device] += 1
        # On the serial side: the converter's gap, then the request on the wire.
        request_end = sent_at + self._converter_gap_s + self.format.wire_s(len(request.frame))
        if request.is_broadcast:
            # No answer says when the converter put it on its serial side: the broadcast
            # is taken to be there until its gap and wire time have passed, so that the
            # turnaround and post-write waits that follow count from its end, not from
            # the moment it left here (the converter may still be waiting for its gap).
            await self._timer.sleep_until(request_end)
            self.last_frame_end = request_end
            self.stats.busy_s += request_end - sent_at
            return None
        heard_before = self._live().last_byte_at
        try:
            response, received_at = await self._await_answer(
                request,
                transaction,
                deadline=request_end + options.timeout_s,
                exceptions=options.exceptions,
                byte_count_16bit=options.byte_count_16bit,
            )
        except ConverterError as exc:
            self.stats.errors[request.device, exc.kind] += 1
            self._failed(sent_at, heard=True)
            raise
        except DeviceExceptionError as exc:
            self.stats.exception_codes[request.device, exc.code] += 1
            self.stats.errors[request.device, ErrorKind.EXCEPTION] += 1
            self._failed(sent_at, heard=True)
            raise
        except FrameError as exc:
            self.stats.errors[request.device, failure_kind(exc, otherwise=ErrorKind.NOISE)] += 1
            self._failed(sent_at, heard=True)
            raise
        except BusTimeoutError as exc:
            self.stats.errors[request.device, ErrorKind.TIMEOUT] += 1
            session = self._session
            heard = session is not None and session.last_byte_at > heard_before
            ended = self._failed(sent_at, heard=heard)
            if ended is not None:
                await self.close()
                await self.open()  # fails as a closed port does: the worker's backoff
                raise BusTimeoutError(f"{exc}; {ended}") from exc
            raise
        self._finish(sent_at, line_quiet_at=received_at)
        self.watch.heard()
        self.stats.answered(request.device, received_at - sent_at, response.tolerated)
        return Exchange(response=response, sent_at=sent_at, received_at=received_at)

    def _finish(self, sent_at: float, *, line_quiet_at: float | None = None) -> None:
        """The session is quiet from the answer (or now, after a failure); its time counted."""
        end = line_quiet_at if line_quiet_at is not None else time.monotonic()
        self.last_frame_end = end
        self.stats.busy_s += end - sent_at

    def _failed(self, sent_at: float, *, heard: bool) -> str | None:
        """Book a failed transaction; why the session is to be reopened (silence), else ``None``."""
        self._finish(sent_at)
        if heard:
            self.watch.heard()
            return None
        return self.watch.unheard()

    async def _await_answer(
        self,
        request: frames.Request,
        transaction: int,
        *,
        deadline: float,
        exceptions: Mapping[int, str],
        byte_count_16bit: bool,
    ) -> tuple[frames.Response, float]:
        """Read frames until the one with ``transaction`` (and when it came); older are stale."""
        noise = False
        others: list[int] = []  # the transaction ids of the answers dropped meanwhile
        looks = 0  # at the deadline, for bytes the kernel holds that the loop has not handed over
        while True:
            session = self._live()
            try:
                cut = mbap.decode(session.buffer)
            except MalformedFrameError:
                self._resync(session.buffer, transaction)
                noise = True
                continue
            if cut is not None:
                frame, used = cut
                del session.buffer[:used]
                if frame.transaction != transaction:
                    self._stale(frame)
                    others.append(frame.transaction)
                    continue
                if noise:  # stray bytes came before the answer: dropped, counted
                    self.stats.errors[request.device, ErrorKind.NOISE] += 1
                answer = mbap.parse_answer(
                    request,
                    frame,
                    where=self.port,
                    exceptions=exceptions,
                    byte_count_16bit=byte_count_16bit,
                )
                return answer, session.last_byte_at
            now = time.monotonic()
            if now >= deadline:
                if looks < LAST_LOOKS and unread_bytes(self.tcp_socket()):
                    # As on an RTU line (line/transports/rtu): the answer waits in the
                    # socket, and the loop ran this wait's timer first. It is taken, not a
                    # timeout.
                    looks += 1
                    await session.wait(LAST_LOOK_S)
                    continue
                held = bytes(session.buffer)
                session.buffer.clear()
                raise _no_answer(
                    self.port,
                    request,
                    transaction=transaction,
                    noise=noise,
                    held=held,
                    others=others,
                )
            await session.wait(deadline - now)

    def _resync(self, buffer: bytearray, transaction: int) -> None:
        """Drop what cannot start an MBAP frame, up to where this transaction's answer may.

        A byte stream has no silence to resynchronise on. Dropping all that was held lost
        a good answer that came right behind a few stray bytes (a converter's trailing
        garbage after its previous answer): the answer awaited begins with its transaction
        id and protocol 0, so that is looked for; the last three bytes stay if it is not
        found, as they may be the beginning of it.
        """
        start = buffer.find(_HEAD.pack(transaction, mbap.MBAP_PROTOCOL_MODBUS), 1)
        keep = start if start >= 0 else max(1, len(buffer) - (_HEAD.size - 1))
        _LOGGER.debug("%s: not an MBAP frame: %s", self.port, buffer[:keep].hex(" "))
        del buffer[:keep]


def _what(request: frames.Request) -> str:
    return f"device {request.device} function {request.function:#04x} at {request.address:#06x}"


def _no_answer(
    port: str,
    request: frames.Request,
    *,
    transaction: int,
    noise: bool,
    held: bytes,
    others: list[int],
) -> FrameError | BusTimeoutError:
    """The failure of a request whose answer did not come in time, saying what did come.

    "No answer" alone misled where bytes came: a frame cut short (its header announcing
    more than was sent: a converter's wrong length field, or a network slower than the
    timeout) or answers with other transaction ids (late answers, or a converter that
    does not return the id it is given: then every request ends so).
    """
    what = _what(request)
    if noise:
        return MalformedFrameError(f"{port}: no valid answer of {what}, only noise")
    if held:
        if len(held) >= mbap.MBAP_HEADER_LENGTH - 1:
            need = mbap.MBAP_HEADER_LENGTH - 1 + int.from_bytes(held[4:6], "big")
            came = f"{len(held)} of the {need} bytes its MBAP header announces"
        else:
            came = f"{len(held)} bytes of an MBAP header"
        return BusTimeoutError(f"{port}: an incomplete answer of {what}: {came}")
    if others:
        ids = ", ".join(str(other) for other in others)
        came = (
            f"an answer came with transaction id {ids}"
            if len(others) == 1
            else f"{len(others)} answers came with transaction ids {ids}"
        )
        return BusTimeoutError(
            f"{port}: no answer of {what}: {came}, this request's is {transaction}: a late "
            "answer to an earlier request, or a converter that does not return the "
            "transaction id it is given (if every request ends so: a firmware upgrade of "
            "the converter, or its transparent mode with a socket:// port, helps)"
        )
    return BusTimeoutError(f"{port}: no answer of {what}")
