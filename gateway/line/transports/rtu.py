"""Modbus RTU on a byte stream: the inter-frame gap and strict transactions.

Checked on pymodbus 3.16: its async serial client sends the next request as soon as a
response is parsed (no inter-frame gap), reports a CRC error as a timeout after retries,
and its RTU framer throws away a good frame that follows a garbage byte. So the gateway
drives the wire itself and frames requests and parses answers on its own
(:mod:`gateway.wire.frames`, :mod:`gateway.line.transports.answer`).

:class:`RtuLine` is the engine both RTU lines share: a transaction waits for the
inter-frame gap, flushes stale input, sends, and reads until the length the function code
implies, resynchronising on garbage and classifying every failure; it reads the adapter's
echo where there is one (:mod:`gateway.line.transports.echo`). What carries the bytes is its
subclasses': a local serial device (:class:`gateway.line.transports.serial_line.SerialLine`) or a
serial device server's TCP port (:class:`gateway.line.transports.rtu_over_tcp.RtuOverTcpLine`).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import time
from abc import ABC, abstractmethod
from typing import TYPE_CHECKING, Final

from gateway.config.echo import EchoMode
from gateway.errors import (
    BusClosedError,
    BusTimeoutError,
    DeviceExceptionError,
    EchoMismatchError,
    FrameError,
    LineNoiseError,
)
from gateway.line.boundary import Exchange, LateAnswer
from gateway.line.stats import ErrorKind, LineStats, failure_kind
from gateway.line.transports.echo import EchoPolicy
from gateway.line.transports.inbox import Inbox
from gateway.line.transports.receive import Receiver
from gateway.line.transports.timer import DeadlineTimer
from gateway.wire.timing import FRAME_GAP_CHARACTERS

if TYPE_CHECKING:
    from gateway.line.boundary import RequestOptions, WaitWatch
    from gateway.wire import frames
    from gateway.wire.timing import LineFormat

_LOGGER = logging.getLogger(__name__)

MIN_SILENCE_S: Final = 0.003  # event-loop and USB-adapter latency make shorter waits unreliable
CLOSE_WAIT_S: Final = 1.0  # bound on waiting for the transport's end after an abort
# The longest the line may stay busy before a request: a late answer of the longest frame
# (256 bytes) twice over, and never less than half a second. A line busy for longer is
# noise (no termination or biasing, a bad earth, another master), not an answer.
QUIET_WAIT_MIN_S: Final = 0.5
QUIET_WAIT_FRAMES: Final = 2 * 256
QUIET_WAIT_GAPS: Final = 5  # and never fewer than five of the gaps it waits for


def no_silence_words(port: str, device: int, gap_s: float, bound_s: float, noise: int) -> str:
    """Why a request was not sent: the line never fell silent, and what to check."""
    return (
        f"{port}: the line never fell silent for the {gap_s * 1000:.1f} ms gap in "
        f"{bound_s:.1f} s ({noise} bytes of noise); the request to device "
        f"{device} was not sent. Check the termination (120 ohm at both ends only), "
        "the bias resistors, the earth (GND) wire, and that no other master drives "
        "the line"
    )


class RtuLine(ABC):
    """RTU frames on one byte stream, one strict transaction at a time.

    Its :class:`~gateway.line.transports.receive.Receiver` reads each answer (and echo).
    Subclasses open the stream (:meth:`_connect`), say whether bytes wait unread in the
    kernel (:meth:`_unread_input`) and release what they hold at a close (:meth:`_release`).
    """

    def __init__(
        self,
        *,
        port: str,
        line: LineFormat,
        stats: LineStats | None = None,
        bus: str = "",
        echo: EchoMode = EchoMode.AUTO,
        judges_by_wire: bool = True,
    ) -> None:
        """Describe the line; :meth:`open` opens it. ``bus`` names it in log lines.

        ``judges_by_wire``: whether an answer's arrival may be judged by the wire time of the
        bus's format, which holds only where the gateway sees that line itself. Behind a
        converter the format describes its serial side, and an answer's arrival over the
        network says nothing of that line's speed.
        """
        self.port = port
        self.format = line
        self.stats = stats or LineStats()
        self.echo = EchoPolicy(bus=bus, port=port, mode=echo)
        self._last_sent = b""
        self.last_frame_end = float("-inf")  # monotonic time the line last fell silent
        self._transport: asyncio.Transport | None = None
        self._inbox: Inbox | None = None
        self._character_s = line.character_s
        self._quiet_max_s = max(QUIET_WAIT_MIN_S, QUIET_WAIT_FRAMES * self._character_s)
        self.receiver = Receiver(
            port=port,
            stats=self.stats,
            echo=self.echo,
            character_s=self._character_s,
            silence_s=max(FRAME_GAP_CHARACTERS * self._character_s, MIN_SILENCE_S),
            judges_by_wire=judges_by_wire,
            live=self._live_inbox,
            unread_input=self._unread_input,
        )
        self._timer = DeadlineTimer()
        # How late each request started after its gap was due (seconds), kept only when
        # a benchmark sets a list here; nothing in the gateway reads it.
        self.gap_lateness_s: list[float] | None = None
        # The loop's watch, which the line's timer looks for while a worker polls (to rest()).
        self.wait_watch: WaitWatch | None = None

    @property
    def late_answer(self) -> LateAnswer | None:
        """A device's own answer that came after its request had timed out, until taken."""
        return self.receiver.late_answer

    @late_answer.setter
    def late_answer(self, value: LateAnswer | None) -> None:
        self.receiver.late_answer = value

    @property
    def is_open(self) -> bool:
        """Whether the stream is open and has not been lost."""
        return self._inbox is not None and not self._inbox.gone

    @abstractmethod
    async def _connect(self, inbox: Inbox) -> asyncio.Transport:
        """Open the stream with ``inbox`` as its protocol; a failure is a :class:`BusClosedError`.

        The failure is also recorded in :attr:`stats` (``closed_because``).
        """

    @abstractmethod
    def _unread_input(self) -> bool:
        """Whether bytes have arrived that the inbox has not seen (asked of the kernel).

        The soak found a request sent 2 ms after a late answer of another device: the
        answer sat in the kernel's buffer while the event loop was busy, so the gap was
        measured from an older byte.
        """

    def _release(self, transport: asyncio.Transport) -> None:  # noqa: B027 - a hook
        """Let go of what the open holds beyond the transport, before it is aborted."""

    async def open(self) -> None:
        """Open the stream; one that cannot be opened raises :class:`BusClosedError`."""
        inbox = Inbox(asyncio.get_running_loop(), timer=self._timer)
        transport = await self._connect(inbox)
        self._transport, self._inbox = transport, inbox
        self.stats.closed_because(None, "")
        self.stats.port_open = True
        self.last_frame_end = time.monotonic()

    def rest(self) -> None:
        """The worker sleeps, or stops: the line's timer looks for the loop's watch no more."""
        self._timer.rest()

    async def close(self) -> None:
        """Close the stream (idempotent); back once it is closed (a device's lock released)."""
        transport, inbox = self._transport, self._inbox
        self._transport = self._inbox = None
        if inbox is not None:
            inbox.gone = True  # a transaction waiting on it ends at its next look
        self.stats.port_open = False
        self._timer.close()
        if transport is None:
            return
        self._release(transport)
        if not transport.is_closing():
            # abort(), not close(): close() drains the output first (tcdrain in a thread),
            # which can wait for ever on a line nobody reads, and a thread stuck there
            # keeps the process from exiting. Nothing still queued matters after a stop.
            # A transport that is closing already (a read error makes
            # pyserial-asyncio-fast 0.16 close it when the port goes away) is not aborted
            # again: its closing task would run twice and the second would call
            # connection_lost on the protocol the first one cleared.
            transport.abort()
        await asyncio.sleep(0)
        if inbox is not None:
            # A serial device is closed in an executor thread, and connection_lost follows.
            # Until then the port's exclusive lock is held: a reopen at once (the next
            # line format of a scan, the worker after a pause) would find it in use.
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(CLOSE_WAIT_S):
                    await inbox.lost.wait()

    def _live_inbox(self) -> Inbox:
        inbox = self._inbox
        if inbox is None or self._transport is None:
            raise BusClosedError(f"{self.port} is not open")
        if inbox.gone:
            self.stats.port_open = False
            raise BusClosedError(f"{self.port} went away: {self._lost_words(inbox)}")
        return inbox

    def _lost_words(self, inbox: Inbox) -> str:
        """Why the stream ended, for the failure that says the line went away."""
        return inbox.why_lost()

    def flush_input(self, device: int) -> None:
        """Discard whatever arrived between transactions: late answers and noise."""
        inbox = self._live_inbox()
        if inbox.buffer:
            self.receiver.discard(inbox, device, self._last_sent)

    async def wait_gap(self, gap_s: float, *, not_before: float = 0.0, device: int = 0) -> float:
        """Keep the line silent for ``gap_s`` after its last frame (and until ``not_before``).

        Returns when the gap was due, for the lateness of the request that follows. A line
        that does not fall silent within a bound (``_quiet_max_s`` or five gaps after it could
        go) raises :class:`LineNoiseError`: a request sent into noise is lost anyway, and
        waiting without end held up every other device (a request went out 2.6 s late).
        """
        inbox = self._live_inbox()
        if self.receiver.owed is not None:  # a cancelled transaction's answer still to come
            self.last_frame_end = await self.receiver.settle_owed(inbox, self.last_frame_end)
        give_up = math.inf  # set at the first wait: most gaps are over when they are asked for
        bound_s = 0.0
        read_at = -math.inf  # when the loop had surely read all the port held
        while True:
            last_frame_end, last_byte_at = self.last_frame_end, inbox.last_byte_at
            # max(max(last_frame_end, last_byte_at) + gap_s, not_before), without max()'s calls
            ready = (last_frame_end if last_frame_end > last_byte_at else last_byte_at) + gap_s  # noqa: FURB136
            if ready < not_before:  # noqa: PLR1730 - see above
                ready = not_before
            now = time.monotonic()
            if ready <= now:
                # Bytes the loop has not read (a late answer, noise, while the process
                # was busy): the line was not quiet. The kernel is asked, unless the
                # timer woke this wait less than a character ago: the loop read the port
                # in that pass (one system call less, ~5 % of a transaction's CPU).
                if now - read_at > self._character_s and self._unread_input():
                    inbox.last_byte_at = time.monotonic()  # at the latest: the gap anew
                    continue
                self.stats.noisy = None
                return ready
            # Not asyncio.sleep, up to 1 ms late (epoll counts whole milliseconds): the
            # timer fires within tens of microseconds (line/transports/timer).
            if give_up == math.inf:
                bound_s = max(self._quiet_max_s, QUIET_WAIT_GAPS * gap_s)
                give_up = max(now, not_before) + bound_s
            if now >= give_up:
                self._no_silence(device, gap_s, bound_s)
            wake_at = min(ready, give_up)
            self._timer.look(self.wait_watch)  # for the loop's watch too, till the worker rests
            woken = await self._timer.sleep_until(wake_at, inbox.loop)
            read_at = wake_at if woken else read_at  # read at wake_at or later if woken
            if inbox.gone or self._inbox is not inbox:  # lost, or closed, meanwhile
                self._live_inbox()

    def _no_silence(self, device: int, gap_s: float, bound_s: float) -> None:
        inbox = self._live_inbox()
        noise = len(inbox.buffer)
        inbox.buffer.clear()
        self.stats.errors[device, ErrorKind.NO_SILENCE] += 1
        message = no_silence_words(self.port, device, gap_s, bound_s, noise)
        if self.stats.noisy is None:
            _LOGGER.warning("%s", message)
        self.stats.noisy = message
        raise LineNoiseError(message)

    async def transact(self, request: frames.Request, options: RequestOptions) -> Exchange | None:
        """Send ``request`` after the gap and return its answer (``None`` for broadcasts).

        ``options.turnaround_s`` is the least time the device takes before it answers (a
        digiLine's minimum response time); an answer complete sooner than the request's and
        its own wire time plus that is not the device's
        (:func:`~gateway.line.transports.echo.earliest_answer`).

        Raises :class:`BusTimeoutError` (:class:`LineNoiseError` when the line never fell
        silent), :class:`CrcError`, :class:`UnexpectedDeviceError`,
        :class:`MalformedFrameError`, :class:`EchoMismatchError`,
        :class:`DeviceExceptionError` or :class:`BusClosedError`; every failure is counted
        by kind for the device.
        """
        timeout_s = options.timeout_s
        due = await self.wait_gap(
            options.gap_s, not_before=options.not_before, device=request.device
        )
        inbox = self._inbox
        assert inbox is not None  # noqa: S101 - wait_gap checked it
        if inbox.buffer:
            self.flush_input(request.device)
        assert self._transport is not None  # noqa: S101 - _live_inbox checked it
        sent_at = time.monotonic()
        if self.gap_lateness_s is not None:
            self.gap_lateness_s.append(sent_at - due)
        try:
            self._transport.write(request.frame)
        except OSError as exc:  # pyserial's SerialException is one too
            raise BusClosedError(f"{self.port}: write failed: {exc}") from exc
        self._last_sent = b"" if request.is_write and not request.is_broadcast else request.frame
        self.stats.requests[request.device] += 1
        request_end = sent_at + len(request.frame) * self._character_s
        if request.is_broadcast:
            await self._broadcast_sent(request, sent_at, request_end)
            return None
        try:
            if self.echo.echoes is True:  # ``expected``, without the property's call
                await self.receiver.read_echo(request, request_end)
            response, received_at = await self.receiver.receive(
                request, options, sent_at=sent_at, deadline=request_end + timeout_s
            )
        except DeviceExceptionError as exc:
            self.stats.exception_codes[request.device, exc.code] += 1
            self.stats.errors[request.device, ErrorKind.EXCEPTION] += 1
            self._finish(sent_at)
            raise
        except asyncio.CancelledError:  # the device answers all the same: the line waits for it
            self.receiver.owe(request, options, request_end + timeout_s, inbox)
            raise
        except (BusTimeoutError, FrameError) as exc:
            kind = failure_kind(exc, otherwise=ErrorKind.TIMEOUT)
            self.stats.errors[request.device, kind] += 1
            self._finish(sent_at)
            if isinstance(exc, BusTimeoutError):
                waited_s = request_end + timeout_s - sent_at
                self.receiver.timed_out(request.device, sent_at, timeout_s, waited_s)
            raise
        return self._answered(request.device, response, sent_at, received_at)

    def _answered(
        self, device: int, response: frames.Response, sent_at: float, received_at: float
    ) -> Exchange:
        """The device answered: the line is silent from the answer's last byte; counted."""
        self.receiver.answered(device)
        self.last_frame_end = received_at
        self.stats.busy_s += received_at - sent_at
        self.stats.answered(device, received_at - sent_at, response.tolerated)
        return Exchange(response=response, sent_at=sent_at, received_at=received_at)

    async def _broadcast_sent(
        self, request: frames.Request, sent_at: float, request_end: float
    ) -> None:
        """No answer comes to a broadcast; its echo, where the adapter makes one, does."""
        self.last_frame_end = request_end
        self.stats.busy_s += request_end - sent_at
        if self.echo.expected:
            try:
                await self.receiver.read_echo(request, request_end)
            except EchoMismatchError:
                self.stats.errors[request.device, ErrorKind.ECHO_MISMATCH] += 1
                raise

    def _finish(self, sent_at: float, *, line_quiet_at: float | None = None) -> None:
        """The line is silent from the answer's last byte (or now, after a failure)."""
        end = line_quiet_at if line_quiet_at is not None else time.monotonic()
        self.last_frame_end = end
        self.stats.busy_s += end - sent_at
