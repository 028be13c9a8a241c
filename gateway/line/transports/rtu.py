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
from gateway.line.transports.answer import AnswerScan, holds_answer
from gateway.line.transports.echo import ECHO_MARGIN_S, EchoPolicy, earliest_answer
from gateway.line.transports.inbox import LAST_LOOK_S, LAST_LOOKS, Inbox
from gateway.line.transports.timer import DeadlineTimer
from gateway.wire import frames

if TYPE_CHECKING:
    from gateway.line.boundary import RequestOptions, WaitWatch
    from gateway.wire.timing import LineFormat

_LOGGER = logging.getLogger(__name__)

SILENCE_CHARACTERS: Final = 3.5  # a frame ends after 3.5 silent characters (all manuals)
MIN_SILENCE_S: Final = 0.003  # event-loop and USB-adapter latency make shorter waits unreliable
CLOSE_WAIT_S: Final = 1.0  # bound on waiting for the transport's end after an abort
# The longest the line may stay busy before a request: a late answer of the longest frame
# (256 bytes) twice over, and never less than half a second. A line busy for longer is
# noise (no termination or biasing, a bad earth, another master), not an answer.
QUIET_WAIT_MIN_S: Final = 0.5
QUIET_WAIT_FRAMES: Final = 2 * 256
QUIET_WAIT_GAPS: Final = 5  # and never fewer than five of the gaps it waits for


class RtuLine(ABC):
    """RTU frames on one byte stream, one strict transaction at a time.

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
        self.judges_by_wire = judges_by_wire
        self.format = line
        self.stats = stats or LineStats()
        self.echo = EchoPolicy(bus=bus, port=port, mode=echo)
        # The last request that timed out per device (when sent, how long it waited), so
        # that its answer coming later tells how late; the worker asks for it.
        self._timed_out: dict[int, tuple[float, float, float]] = {}
        self.late_answer: LateAnswer | None = None
        self._last_sent = b""
        self.last_frame_end = float("-inf")  # monotonic time the line last fell silent
        self._transport: asyncio.Transport | None = None
        self._inbox: Inbox | None = None
        self._character_s = line.character_s
        self._silence_s = max(SILENCE_CHARACTERS * self._character_s, MIN_SILENCE_S)
        self._quiet_max_s = max(QUIET_WAIT_MIN_S, QUIET_WAIT_FRAMES * self._character_s)
        self._timer = DeadlineTimer()
        # How late each request started after its gap was due (seconds), kept only when
        # a benchmark sets a list here; nothing in the gateway reads it.
        self.gap_lateness_s: list[float] | None = None
        # Told when the gap's wait sleeps and wakes (the bus worker sets it while it runs).
        self.wait_watch: WaitWatch | None = None

    @property
    def is_open(self) -> bool:
        """Whether the stream is open and has not been lost."""
        return self._inbox is not None and not self._inbox.lost.is_set()

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
        inbox = Inbox()
        transport = await self._connect(inbox)
        self._transport, self._inbox = transport, inbox
        self.stats.closed_because(None, "")
        self.stats.port_open = True
        self.last_frame_end = time.monotonic()

    async def close(self) -> None:
        """Close the stream (idempotent); back once it is closed (a device's lock released)."""
        transport, inbox = self._transport, self._inbox
        self._transport = self._inbox = None
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
        if inbox.lost.is_set():
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
            stale = bytes(inbox.buffer)
            inbox.buffer.clear()
            if stale == self._last_sent:
                # The adapter's echo of a request that waited for no answer (a broadcast),
                # or of a read whose answer never came: the adapter's doing, not the line's.
                # (A unicast write's late answer is a copy of it too: not remembered.)
                self._echo_seen(device)
                return
            kind = ErrorKind.STALE if frames.crc_ok(stale) else ErrorKind.NOISE
            if kind == ErrorKind.STALE:
                self._note_late(stale[0], inbox.last_byte_at)
            self.stats.errors[device, kind] += 1
            _LOGGER.debug(
                "%s: discarded %d %s bytes: %s", self.port, len(stale), kind, stale.hex(" ")
            )

    def _echo_seen(self, device: int) -> None:
        """An echo where none was expected: counted once the bus has settled on no echo."""
        if self.echo.echoes is False:
            self.stats.errors[device, ErrorKind.ECHO] += 1
            self.echo.unexpected()
        else:
            self.echo.seen = True

    def _note_late(self, device: int, arrived_at: float) -> None:
        """A stale frame of a device that timed out last: how late its answer came."""
        timed_out = self._timed_out.pop(device, None)
        if timed_out is not None:
            sent_at, timeout_s, waited_s = timed_out
            self.late_answer = LateAnswer(
                device=device,
                after_s=arrived_at - sent_at,
                timeout_s=timeout_s,
                waited_s=waited_s,
            )

    async def wait_gap(self, gap_s: float, *, not_before: float = 0.0, device: int = 0) -> float:
        """Keep the line silent for ``gap_s`` after its last frame (and until ``not_before``).

        Returns when the gap was due, for the lateness of the request that follows. A line
        that does not fall silent within a bound (``_quiet_max_s`` or five gaps after it could
        go) raises :class:`LineNoiseError`: a request sent into noise is lost anyway, and
        waiting without end held up every other device (a request went out 2.6 s late).
        """
        inbox = self._live_inbox()
        give_up = math.inf  # set at the first wait: most gaps are over when they are asked for
        bound_s = 0.0
        while True:
            last_frame_end, last_byte_at = self.last_frame_end, inbox.last_byte_at
            ready = max(max(last_frame_end, last_byte_at) + gap_s, not_before)
            now = time.monotonic()
            if ready <= now:
                if self._unread_input():
                    # Bytes wait in the port's buffer that the event loop has not handed
                    # over yet (a late answer or noise while this process was busy
                    # elsewhere): the line was not quiet. They arrived at the latest now;
                    # the gap starts again.
                    inbox.last_byte_at = time.monotonic()
                    continue
                self.stats.noisy = None
                return ready
            # Not asyncio.sleep: its timers end up to 1 ms late (epoll counts whole
            # milliseconds), which made every gap up to 1 ms long. The timer fires within
            # tens of microseconds and costs no CPU while it waits (see line/transports/timer).
            if give_up == math.inf:
                bound_s = max(self._quiet_max_s, QUIET_WAIT_GAPS * gap_s)
                give_up = max(now, not_before) + bound_s
            if now >= give_up:
                self._no_silence(device, gap_s, bound_s)
            wake_at = min(ready, give_up)
            watch = self.wait_watch
            if watch is None:
                await self._timer.sleep_until(wake_at)
            else:
                watch.asleep()
                try:
                    await self._timer.sleep_until(wake_at)
                finally:
                    watch.awake(wake_at, time.monotonic())
            self._live_inbox()

    def _no_silence(self, device: int, gap_s: float, bound_s: float) -> None:
        inbox = self._live_inbox()
        noise = len(inbox.buffer)
        inbox.buffer.clear()
        self.stats.errors[device, ErrorKind.NO_SILENCE] += 1
        message = (
            f"{self.port}: the line never fell silent for the {gap_s * 1000:.1f} ms gap in "
            f"{bound_s:.1f} s ({noise} bytes of noise); the request to device "
            f"{device} was not sent. Check the termination (120 ohm at both ends only), "
            "the bias resistors, the earth (GND) wire, and that no other master drives "
            "the line"
        )
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
            if self.echo.expected:
                await self._read_echo(request, request_end)
            response, received_at = await self._receive(
                request, options, sent_at=sent_at, deadline=request_end + timeout_s
            )
        except DeviceExceptionError as exc:
            self.stats.exception_codes[request.device, exc.code] += 1
            self.stats.errors[request.device, ErrorKind.EXCEPTION] += 1
            self._finish(sent_at)
            raise
        except (BusTimeoutError, FrameError) as exc:
            kind = failure_kind(exc, otherwise=ErrorKind.TIMEOUT)
            self.stats.errors[request.device, kind] += 1
            self._finish(sent_at)
            if isinstance(exc, BusTimeoutError):
                waited_s = request_end + timeout_s - sent_at
                self._timed_out[request.device] = (sent_at, timeout_s, waited_s)
            raise
        return self._answered(request.device, response, sent_at, received_at)

    def _answered(
        self, device: int, response: frames.Response, sent_at: float, received_at: float
    ) -> Exchange:
        """The device answered: the line is silent from the answer's last byte; counted."""
        if self._timed_out:
            self._timed_out.pop(device, None)
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
                await self._read_echo(request, request_end)
            except EchoMismatchError:
                self.stats.errors[request.device, ErrorKind.ECHO_MISMATCH] += 1
                raise

    def _finish(self, sent_at: float, *, line_quiet_at: float | None = None) -> None:
        """The line is silent from the answer's last byte (or now, after a failure)."""
        end = line_quiet_at if line_quiet_at is not None else time.monotonic()
        self.last_frame_end = end
        self.stats.busy_s += end - sent_at

    async def _read_echo(self, request: frames.Request, request_end: float) -> None:
        """``echo: on``: read the request back, byte for byte, before its answer.

        The echo is complete once the request is on the wire; the adapter may hand it over
        later (USB latency), so the wait has a margin. Anything else is a mismatch: the
        bytes are dropped and the transaction fails, since an answer read after a garbled
        echo cannot be trusted to be in step.
        """
        inbox = self._live_inbox()
        frame = request.frame
        deadline = request_end + ECHO_MARGIN_S + SILENCE_CHARACTERS * self._character_s
        looks = 0  # at the deadline, for bytes the kernel holds that the loop has not handed over
        while len(inbox.buffer) < len(frame):
            now = time.monotonic()
            if not frame.startswith(bytes(inbox.buffer)):
                break
            if now >= deadline:
                # The echo in the port's buffer but not handed over yet was reported as an
                # adapter that does not echo, with the advice to set `echo: off`.
                if looks < LAST_LOOKS and await self._handed_over_late(inbox):
                    looks += 1
                    continue
                break
            await inbox.wait(deadline - now)
            self._live_inbox()
        echoed = bytes(inbox.buffer[: len(frame)])
        if echoed == frame:
            del inbox.buffer[: len(frame)]
            return
        answered = holds_answer(request, bytes(inbox.buffer))
        inbox.buffer.clear()
        if not echoed or answered:
            came = "the device's answer came instead" if answered else "nothing came"
            raise EchoMismatchError(
                f"{self.port}: {self.echo.setting} is set to `echo: on` but the request to "
                f"device {request.device} did not come back ({came}): this adapter does "
                "not echo what it sends; set `echo: off` (or `auto`) for the bus"
            )
        raise EchoMismatchError(
            f"{self.port}: the echo of the request to device {request.device} differs from "
            f"what was sent (sent {frame.hex(' ')}, read back {echoed.hex(' ')}): a "
            "collision with another master or noise on the line"
        )

    async def _receive(
        self, request: frames.Request, options: RequestOptions, *, sent_at: float, deadline: float
    ) -> tuple[frames.Response, float]:
        """Read until a frame answers ``request``; skip garbage, echoes and frames of others."""
        inbox = self._live_inbox()
        policy = self.echo
        expected = policy.echoes is True
        if self.judges_by_wire:
            character_s = self._character_s
            floor = earliest_answer(
                sent_at,
                request_bytes=len(request.frame),
                answer_bytes=0,
                character_s=character_s,
                turnaround_s=options.turnaround_s,
            )
        else:
            character_s, floor = 0.0, -math.inf
        scan = AnswerScan(
            request,
            exceptions=options.exceptions,
            byte_count_16bit=options.byte_count_16bit,
            echo=None if expected else request.frame,
            echo_known=policy.seen,
            answer_floor=floor,
            character_s=character_s,
        )
        try:
            return await self._scan_until_answer(inbox, scan, request, deadline)
        finally:
            if scan.echo_skipped:
                self._echo_seen(request.device)
            if policy.echoes is None and not request.is_write:  # ``auto``, undecided
                policy.observed_read(echoed=scan.echo_skipped)

    async def _scan_until_answer(
        self, inbox: Inbox, scan: AnswerScan, request: frames.Request, deadline: float
    ) -> tuple[frames.Response, float]:
        looks = 0  # at the deadline, for bytes the kernel holds that the loop has not handed over
        while True:
            try:
                result = scan.feed(inbox.buffer, inbox.last_byte_at)
            except DeviceExceptionError:
                # An exception answer is an answer too: consumed here, or the next
                # transaction would flush it and count it a second time, as a stale frame.
                self._consume(inbox, scan, request.device)
                raise
            if result is not None:
                self._consume(inbox, scan, request.device)
                return self._later_answer(inbox, scan, result), inbox.last_byte_at
            now = time.monotonic()
            # A corrupted answer from the device itself is final once the line falls silent.
            # A frame of another device is not: it may be a late answer that came first,
            # with the device's own answer still to come; leaving then would put the next
            # request on the line while it answers.
            settle = inbox.last_byte_at + self._silence_s if scan.crc_bad else deadline
            wake = min(deadline, settle)
            if now >= wake:
                # Giving up with the answer in the port's buffer counted a timeout, and the
                # answer, read a moment later, a stale frame; the device was held for its
                # late-answer window and missed a cycle (bench/budget.py, 16 x 16 under a
                # CPU quota: 7 runs of 35).
                if looks < LAST_LOOKS and await self._handed_over_late(inbox):
                    looks += 1
                    continue
                inbox.buffer.clear()
                raise scan.failure(self.port)
            await inbox.wait(wake - now)
            self._live_inbox()

    async def _handed_over_late(self, inbox: Inbox) -> bool:
        """At a deadline: whether bytes waited in the kernel, now handed to ``inbox``.

        The event loop woke the wait on its timer before it handed the bytes over: a
        process held up (a CPU quota, a busy machine) came back to both at once, and the
        timer was due in the pass it was held in. One ioctl; only at a deadline.
        """
        if not self._unread_input():
            return False
        await inbox.wait(LAST_LOOK_S)
        self._live_inbox()
        return True

    def _later_answer(
        self, inbox: Inbox, scan: AnswerScan, response: frames.Response
    ) -> frames.Response:
        """The last of the read's answers that came together: the earlier ones are stale.

        A converter that held a late answer sends it with the next one in one TCP segment
        (the same device's, the same shape: nothing in the frame tells them apart), and
        the first one was taken for the answer to the current request. The stream keeps
        the order of the bytes, and the device answers this request only after it came,
        so of two complete answers in a row the later is its answer; the earlier is counted
        as a stale frame of the device. Reads only: a write's answer is a copy of its
        request, which an adapter's echo can be too.
        """
        request = scan.request
        if request.function not in frames.READ_FUNCTIONS:
            return response
        while len(inbox.buffer) > 1:
            data = bytes(inbox.buffer)
            try:
                need = frames.response_length(request, data, byte_count_16bit=scan.byte_count_16bit)
                if not 0 < need <= len(data) or not frames.crc_ok(data[:need]):
                    return response
                later = frames.parse_response(
                    request,
                    data[:need],
                    exceptions=scan.exceptions,
                    byte_count_16bit=scan.byte_count_16bit,
                )
            except (FrameError, DeviceExceptionError):
                return response  # not an answer to it: the next request's flush counts it
            del inbox.buffer[:need]
            self.stats.errors[request.device, ErrorKind.STALE] += 1
            self._note_late(request.device, inbox.last_byte_at)
            _LOGGER.debug(
                "%s: of two answers of device %d in a row the later taken",
                self.port,
                request.device,
            )
            response = later
        return response

    def _consume(self, inbox: Inbox, scan: AnswerScan, device: int) -> None:
        """Drop the bytes up to the answer; count what was skipped on the way.

        A late answer of another device is a stale frame of that device, garbage is
        noise on this request.
        """
        del inbox.buffer[: scan.consumed]
        if scan.other_device is not None:
            self.stats.errors[scan.other_device, ErrorKind.STALE] += 1
            self._note_late(scan.other_device, inbox.last_byte_at)
        if scan.garbage:
            self.stats.errors[device, ErrorKind.NOISE] += 1
