"""The owner of one RS485 line: the port, the inter-frame gap, and strict transactions.

Checked on pymodbus 3.16: its async serial client sends the next request as soon as a
response is parsed (no inter-frame gap), reports a CRC error as a timeout after retries,
and its RTU framer throws away a good frame that follows a garbage byte. So this module
drives the wire itself through pyserial-asyncio-fast and uses pymodbus (via
:mod:`gateway.wire.frames`) only to build requests and decode responses.

One :class:`Line` per port; nothing else touches the port. A transaction waits for the
inter-frame gap, flushes stale input, sends, and reads until the length the function
code implies, resynchronising on garbage and classifying every failure.
"""

from __future__ import annotations

import asyncio
import bisect
import contextlib
import logging
import math
import os
import select
import stat
import termios
import time
from collections import Counter, defaultdict
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Final, Protocol, cast

import serial
import serial_asyncio_fast

from gateway.errors import (
    BusClosedError,
    BusTimeoutError,
    CrcError,
    DeviceExceptionError,
    EchoMismatchError,
    FrameError,
    LineNoiseError,
    MalformedFrameError,
    PortUnavailableError,
    UnexpectedDeviceError,
)
from gateway.line import port_access
from gateway.line.answer import AnswerScan, holds_answer
from gateway.line.echo import ECHO_MARGIN_S, EchoMode, EchoPolicy, earliest_answer
from gateway.line.timer import DeadlineTimer
from gateway.wire import frames

if TYPE_CHECKING:
    from collections.abc import Mapping

    from gateway.wire.timing import LineFormat

_LOGGER = logging.getLogger(__name__)

SILENCE_CHARACTERS: Final = 3.5  # a frame ends after 3.5 silent characters (all manuals)
MIN_SILENCE_S: Final = 0.003  # event-loop and USB-adapter latency make shorter waits unreliable
CLOSE_WAIT_S: Final = 1.0  # bound on waiting for the device's close in its thread
LATENCY_BUCKETS_S: Final = (0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0, 2.0)
# The longest the line may stay busy before a request: a late answer of the longest frame
# (256 bytes) twice over, and never less than half a second. A line busy for longer is
# noise (no termination or biasing, a bad earth, another master), not an answer.
QUIET_WAIT_MIN_S: Final = 0.5
QUIET_WAIT_FRAMES: Final = 2 * 256
QUIET_WAIT_GAPS: Final = 5  # and never fewer than five of the gaps it waits for
_LATENCY_BOUNDS: Final = (*LATENCY_BUCKETS_S, math.inf)


class ErrorKind:
    """Names of the failure classes counted per bus and device."""

    TIMEOUT: Final = "timeout"
    CRC: Final = "crc"
    EXCEPTION: Final = "exception"
    WRONG_ADDRESS: Final = "wrong_address"
    STALE: Final = "stale_frame"
    NOISE: Final = "noise"
    MALFORMED: Final = "malformed"
    ECHO: Final = "echo"  # an echo of the request although the bus is set to ``echo: off``
    ECHO_MISMATCH: Final = "echo_mismatch"  # ``echo: on`` and what came back was not the request
    NO_SILENCE: Final = "no_silence"  # the line never fell silent: the request was not sent


@dataclass(slots=True)
class LineStats:
    """Counters of one line, per device address where it matters. Read by the sinks."""

    requests: Counter[int] = field(default_factory=Counter)
    responses: Counter[int] = field(default_factory=Counter)
    errors: Counter[tuple[int, str]] = field(default_factory=Counter)
    exception_codes: Counter[tuple[int, int]] = field(default_factory=Counter)
    retries: Counter[int] = field(default_factory=Counter)
    tolerated: Counter[tuple[int, str]] = field(default_factory=Counter)
    # Requests per device and latency bucket, not cumulative (the last: beyond the last
    # bound): one increment of a plain int per answer; the histogram is summed up when
    # it is read (:attr:`latency_buckets`), at a scrape, not on every transaction.
    latency_counts: dict[int, list[int]] = field(default_factory=dict)
    latency_sum_s: defaultdict[int, float] = field(default_factory=lambda: defaultdict(float))
    busy_s: float = 0.0  # time the line carried our transactions
    started: float = field(default_factory=time.monotonic)
    port_open: bool = False
    port_failures: int = 0
    noisy: str | None = None  # why the last request could not go out, while the line is noisy
    port_problem: str | None = None  # why the port is not open (port_access.PortReason)
    port_error: str = ""  # the message that says so, with its remedy
    latency_timer_s: float | None = None  # an FTDI adapter's latency timer, when read

    def closed_because(self, reason: str | None, message: str) -> None:
        """The port is not open, for this reason (``None``: no problem, it is opening)."""
        self.port_open = False
        self.port_problem = reason
        self.port_error = message

    def observe_latency(self, device: int, seconds: float) -> None:
        """Add one request-to-response time to the histogram."""
        self.latency_sum_s[device] += seconds
        counts = self.latency_counts.get(device)
        if counts is None:
            counts = self.latency_counts[device] = [0] * (len(LATENCY_BUCKETS_S) + 1)
        counts[bisect.bisect_left(LATENCY_BUCKETS_S, seconds)] += 1

    @property
    def latency_buckets(self) -> Counter[tuple[int, float]]:
        """The cumulative histogram: requests answered within each bound, per device.

        Keyed ``(device, bound)`` with ``math.inf`` for all of them; a bound no answer
        came within is left out. Safe to call from another thread (a scrape): each copy
        it takes is one step under the interpreter's lock.
        """
        buckets: Counter[tuple[int, float]] = Counter()
        for device, counts in list(self.latency_counts.items()):
            total = 0
            for bound, count in zip(_LATENCY_BOUNDS, tuple(counts), strict=True):
                total += count
                if total:
                    buckets[device, bound] = total
        return buckets

    def utilisation(self, now: float | None = None) -> float:
        """Share of wall time the line was busy with our transactions."""
        elapsed = (now if now is not None else time.monotonic()) - self.started
        return min(1.0, self.busy_s / elapsed) if elapsed > 0 else 0.0


class _Receiver(asyncio.Protocol):
    """Collects bytes from the port with the time they arrived."""

    def __init__(self) -> None:
        self.buffer = bytearray()
        self.last_byte_at = 0.0
        self.lost = asyncio.Event()
        self.lost_reason: Exception | None = None
        # The transaction waiting for bytes: a bare future, not an Event behind
        # asyncio.wait_for, which made a task per wait and cost two turns of the loop.
        self.waiter: asyncio.Future[None] | None = None

    def data_received(self, data: bytes) -> None:
        self.buffer.extend(data)
        self.last_byte_at = time.monotonic()
        self._wake()

    def connection_lost(self, exc: Exception | None) -> None:
        self.lost_reason = exc
        self.lost.set()
        self._wake()

    def _wake(self) -> None:
        waiter = self.waiter
        if waiter is not None and not waiter.done():
            waiter.set_result(None)


class WaitWatch(Protocol):
    """Told of the line's timed waits: the event loop's watch (``line/lateness``)."""

    def asleep(self) -> None:
        """A timed wait begins."""

    def awake(self, due: float, now: float) -> None:
        """The timed wait due at ``due`` ended at ``now``."""


@dataclass(frozen=True, slots=True, kw_only=True)
class LateAnswer:
    """A device's own answer that came after its request had timed out."""

    device: int
    after_s: float  # from sending the request to the answer's last byte
    timeout_s: float  # the response timeout
    waited_s: float  # from sending to giving up: the request's wire time and the timeout


@dataclass(frozen=True, slots=True, kw_only=True)
class Exchange:
    """A completed transaction: the response and when it happened on the wire."""

    response: frames.Response
    sent_at: float
    received_at: float


class Line:
    """One serial port (or ``socket://`` URL) and the transactions on it."""

    def __init__(
        self,
        *,
        port: str,
        line: LineFormat,
        stats: LineStats | None = None,
        bus: str = "",
        echo: EchoMode = EchoMode.AUTO,
        options: port_access.PortOptions | None = None,
    ) -> None:
        """Describe the line; :meth:`open` opens it. ``bus`` names it in log lines.

        ``options``: how the port is opened (RS485 mode, shared-bus hints, system roots).
        """
        self.port = port
        self.options = options or port_access.PortOptions()
        self._latency_warned = False
        self.format = line
        self.stats = stats or LineStats()
        self.echo = EchoPolicy(bus=bus, port=port, mode=echo)
        # The last request that timed out per device (when sent, how long it waited), so
        # that its answer coming later tells how late; the worker asks for it.
        self._timed_out: dict[int, tuple[float, float, float]] = {}
        self.late_answer: LateAnswer | None = None
        self._last_sent = b""
        # On a network link (``socket://``) the bus's format describes the converter's
        # serial side, which the gateway cannot see: an answer's arrival says nothing of
        # that line's speed, so no answer is judged too early by it.
        self._judge_by_wire = "://" not in port
        self.last_frame_end = float("-inf")  # monotonic time the line last fell silent
        self._transport: asyncio.Transport | None = None
        self._serial: serial.Serial | None = None
        self._receiver: _Receiver | None = None
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
        """Whether the port is open and has not been lost."""
        return self._receiver is not None and not self._receiver.lost.is_set()

    async def open(self) -> None:
        """Open the port exclusively; one that cannot be opened raises :class:`BusClosedError`.

        A serial device that is missing, not permitted, in use or without the configured
        RS485 mode raises :class:`PortUnavailableError` with its ``reason``
        (:mod:`gateway.line.port_access`); its message names the remedy.
        """
        loop = asyncio.get_running_loop()
        receiver = _Receiver()
        # A pseudo-terminal has no physical line: some kernels refuse a parity setting on
        # it (EINVAL), so parity is left off there. Timing still follows the configured
        # format, which is what the simulator on the other end referees.
        pty = _is_pseudo_terminal(self.port)
        parity = "N" if pty else self.format.parity
        try:
            if "://" in self.port:
                transport, _ = await serial_asyncio_fast.create_serial_connection(
                    loop,
                    lambda: receiver,
                    self.port,
                    baudrate=self.format.baudrate,
                    parity=parity,
                    stopbits=self.format.stopbits,
                    bytesize=8,
                )
            else:
                opened = await port_access.open_device(
                    self.port,
                    self.format,
                    parity=parity,
                    tiocexcl=not pty,
                    options=self.options,
                    protocol=receiver,
                )
                transport = opened.transport
                _direct_io(opened.transport.serial)
                self.stats.latency_timer_s = opened.latency_timer_s
                if opened.latency_advice is not None and not self._latency_warned:
                    self._latency_warned = True  # once per line, not at every reconnection
                    _LOGGER.warning("%s", opened.latency_advice)
        except PortUnavailableError as exc:
            self.stats.closed_because(exc.reason, str(exc))
            raise
        except (OSError, serial.SerialException, ValueError, termios.error) as exc:
            # termios.error is no OSError: a line setting the port refuses (tcsetattr)
            # would otherwise end the gateway instead of this bus's retry with backoff.
            message = f"cannot open {self.port}: {exc}"
            self.stats.closed_because(port_access.PortReason.DRIVER, message)
            raise BusClosedError(message) from exc
        self._transport, self._receiver = transport, receiver
        # The serial port under the transport, looked at before every request.
        self._serial = cast("serial.Serial | None", transport.get_extra_info("serial"))
        self.stats.closed_because(None, "")
        self.stats.port_open = True
        self.last_frame_end = time.monotonic()

    async def close(self) -> None:
        """Close the port (idempotent); back once the device is closed (its lock released)."""
        transport, receiver = self._transport, self._receiver
        self._transport = self._receiver = None
        self._serial = None
        self.stats.port_open = False
        self._timer.close()
        if transport is None:
            return
        port_access.release(transport.get_extra_info("serial"))  # TIOCEXCL, for a clean stop
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
        if receiver is not None:
            # The device is closed in an executor thread, and connection_lost follows.
            # Until then the port's exclusive lock is held: a reopen at once (the next
            # line format of a scan, the worker after a pause) would find it in use.
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(CLOSE_WAIT_S):
                    await receiver.lost.wait()

    def _unread_input(self) -> bool:
        """Whether bytes have arrived that the receiver has not seen (one ioctl, no read).

        The soak found a request sent 2 ms after a late answer of another device: the
        answer sat in the kernel's buffer while the event loop was busy, so the gap was
        measured from an older byte.
        """
        port = self._serial
        if port is None or not port.is_open:
            return False  # the port went away: the write or the receiver will say so
        try:
            return bool(port.in_waiting)
        except (OSError, TypeError, serial.SerialException):
            return False  # closed meanwhile (pyserial then has no file descriptor)

    def _live_receiver(self) -> _Receiver:
        receiver = self._receiver
        if receiver is None or self._transport is None:
            raise BusClosedError(f"{self.port} is not open")
        if receiver.lost.is_set():
            self.stats.port_open = False
            raise BusClosedError(f"{self.port} went away: {receiver.lost_reason}")
        return receiver

    def flush_input(self, device: int) -> None:
        """Discard whatever arrived between transactions: late answers and noise."""
        receiver = self._live_receiver()
        if receiver.buffer:
            stale = bytes(receiver.buffer)
            receiver.buffer.clear()
            if stale == self._last_sent:
                # The adapter's echo of a request that waited for no answer (a broadcast),
                # or of a read whose answer never came: the adapter's doing, not the line's.
                # (A unicast write's late answer is a copy of it too: not remembered.)
                self._echo_seen(device)
                return
            kind = ErrorKind.STALE if frames.crc_ok(stale) else ErrorKind.NOISE
            if kind == ErrorKind.STALE:
                self._note_late(stale[0], receiver.last_byte_at)
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
        receiver = self._live_receiver()
        give_up = math.inf  # set at the first wait: most gaps are over when they are asked for
        bound_s = 0.0
        while True:
            last_frame_end, last_byte_at = self.last_frame_end, receiver.last_byte_at
            ready = max(max(last_frame_end, last_byte_at) + gap_s, not_before)
            now = time.monotonic()
            if ready <= now:
                if self._unread_input():
                    # Bytes wait in the port's buffer that the event loop has not handed
                    # over yet (a late answer or noise while this process was busy
                    # elsewhere): the line was not quiet. They arrived at the latest now;
                    # the gap starts again.
                    receiver.last_byte_at = time.monotonic()
                    continue
                self.stats.noisy = None
                return ready
            # Not asyncio.sleep: its timers end up to 1 ms late (epoll counts whole
            # milliseconds), which made every gap up to 1 ms long. The timer fires within
            # tens of microseconds and costs no CPU while it waits (see line/timer).
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
            self._live_receiver()

    def _no_silence(self, device: int, gap_s: float, bound_s: float) -> None:
        receiver = self._live_receiver()
        noise = len(receiver.buffer)
        receiver.buffer.clear()
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

    async def transact(
        self,
        request: frames.Request,
        *,
        timeout_s: float,
        gap_s: float,
        not_before: float = 0.0,
        exceptions: Mapping[int, str] = frames.STANDARD_EXCEPTIONS,
        byte_count_16bit: bool = False,
        turnaround_s: float = 0.0,
    ) -> Exchange | None:
        """Send ``request`` after the gap and return its answer (``None`` for broadcasts).

        ``turnaround_s`` is the least time the device takes before it answers (a digiLine's
        minimum response time); an answer complete sooner than the request's and its own
        wire time plus that is not the device's (:func:`~gateway.line.echo.earliest_answer`).

        Raises :class:`BusTimeoutError` (:class:`LineNoiseError` when the line never fell
        silent), :class:`CrcError`, :class:`UnexpectedDeviceError`,
        :class:`MalformedFrameError`, :class:`EchoMismatchError`,
        :class:`DeviceExceptionError` or :class:`BusClosedError`; every failure is counted
        by kind for the device.
        """
        due = await self.wait_gap(gap_s, not_before=not_before, device=request.device)
        receiver = self._receiver
        assert receiver is not None  # noqa: S101 - wait_gap checked it
        if receiver.buffer:
            self.flush_input(request.device)
        assert self._transport is not None  # noqa: S101 - _live_receiver checked it
        sent_at = time.monotonic()
        if self.gap_lateness_s is not None:
            self.gap_lateness_s.append(sent_at - due)
        try:
            self._transport.write(request.frame)
        except (OSError, serial.SerialException) as exc:
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
                request,
                sent_at=sent_at,
                deadline=request_end + timeout_s,
                exceptions=exceptions,
                byte_count_16bit=byte_count_16bit,
                turnaround_s=turnaround_s,
            )
        except DeviceExceptionError as exc:
            self.stats.exception_codes[request.device, exc.code] += 1
            self.stats.errors[request.device, ErrorKind.EXCEPTION] += 1
            self._finish(sent_at)
            raise
        except (BusTimeoutError, FrameError) as exc:
            self.stats.errors[request.device, _kind(exc)] += 1
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
        stats = self.stats
        stats.busy_s += received_at - sent_at
        stats.responses[device] += 1
        stats.observe_latency(device, received_at - sent_at)
        if response.tolerated is not None:
            stats.tolerated[device, response.tolerated] += 1
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
        receiver = self._live_receiver()
        frame = request.frame
        deadline = request_end + ECHO_MARGIN_S + SILENCE_CHARACTERS * self._character_s
        while len(receiver.buffer) < len(frame):
            now = time.monotonic()
            if now >= deadline or not frame.startswith(bytes(receiver.buffer)):
                break
            await _bytes_or_timeout(receiver, deadline - now)
            self._live_receiver()
        echoed = bytes(receiver.buffer[: len(frame)])
        if echoed == frame:
            del receiver.buffer[: len(frame)]
            return
        answered = holds_answer(request, bytes(receiver.buffer))
        receiver.buffer.clear()
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
        self,
        request: frames.Request,
        *,
        sent_at: float,
        deadline: float,
        exceptions: Mapping[int, str],
        byte_count_16bit: bool,
        turnaround_s: float,
    ) -> tuple[frames.Response, float]:
        """Read until a frame answers ``request``; skip garbage, echoes and frames of others."""
        receiver = self._live_receiver()
        policy = self.echo
        expected = policy.echoes is True
        if self._judge_by_wire:
            character_s = self._character_s
            floor = earliest_answer(
                sent_at,
                request_bytes=len(request.frame),
                answer_bytes=0,
                character_s=character_s,
                turnaround_s=turnaround_s,
            )
        else:
            character_s, floor = 0.0, -math.inf
        scan = AnswerScan(
            request,
            exceptions=exceptions,
            byte_count_16bit=byte_count_16bit,
            echo=None if expected else request.frame,
            echo_known=policy.seen,
            answer_floor=floor,
            character_s=character_s,
        )
        try:
            return await self._scan_until_answer(receiver, scan, request, deadline)
        finally:
            if scan.echo_skipped:
                self._echo_seen(request.device)
            if policy.echoes is None and not request.is_write:  # ``auto``, undecided
                policy.observed_read(echoed=scan.echo_skipped)

    async def _scan_until_answer(
        self, receiver: _Receiver, scan: AnswerScan, request: frames.Request, deadline: float
    ) -> tuple[frames.Response, float]:
        while True:
            try:
                result = scan.feed(receiver.buffer, receiver.last_byte_at)
            except DeviceExceptionError:
                # An exception answer is an answer too: consumed here, or the next
                # transaction would flush it and count it a second time, as a stale frame.
                self._consume(receiver, scan, request.device)
                raise
            if result is not None:
                self._consume(receiver, scan, request.device)
                return result, receiver.last_byte_at
            now = time.monotonic()
            # A corrupted answer from the device itself is final once the line falls silent.
            # A frame of another device is not: it may be a late answer that came first,
            # with the device's own answer still to come; leaving then would put the next
            # request on the line while it answers.
            settle = receiver.last_byte_at + self._silence_s if scan.crc_bad else deadline
            wake = min(deadline, settle)
            if now >= wake:
                receiver.buffer.clear()
                raise scan.failure(self.port)
            await _bytes_or_timeout(receiver, wake - now)
            self._live_receiver()

    def _consume(self, receiver: _Receiver, scan: AnswerScan, device: int) -> None:
        """Drop the bytes up to the answer; count what was skipped on the way.

        A late answer of another device is a stale frame of that device, garbage is
        noise on this request.
        """
        del receiver.buffer[: scan.consumed]
        if scan.other_device is not None:
            self.stats.errors[scan.other_device, ErrorKind.STALE] += 1
            self._note_late(scan.other_device, receiver.last_byte_at)
        if scan.garbage:
            self.stats.errors[device, ErrorKind.NOISE] += 1


async def _bytes_or_timeout(receiver: _Receiver, timeout_s: float) -> None:
    """Return when bytes arrive, the port is lost, or after ``timeout_s``."""
    loop = asyncio.get_running_loop()
    waiter = loop.create_future()
    receiver.waiter = waiter
    timer = loop.call_later(timeout_s, _expire, waiter)
    try:
        await waiter
    finally:
        timer.cancel()
        receiver.waiter = None


def _expire(waiter: asyncio.Future[None]) -> None:
    if not waiter.done():
        waiter.set_result(None)


def _direct_io(device: serial.Serial | None) -> None:
    """Let the transport read and write the device with one ``os.read``/``os.write``.

    pyserial-asyncio-fast calls the port's ``read`` when the event loop has seen it
    readable; pyserial then makes two timeout objects, calls ``select`` once more and
    only then ``os.read`` (a system call and some 15 Python calls per answer, for what
    the loop already knew: 7.5 against 3 µs a read, measured on a pseudo-terminal); the
    replacement asks ``select`` only when a read comes back empty. Its
    non-blocking ``write`` makes a timeout object around one ``os.write``. The
    replacements keep pyserial's verdicts: nothing to read (``EAGAIN``, ``EINTR``) is
    no data, a read that fails or finds the device gone (readable, yet nothing) is a
    :class:`serial.SerialException`, which the transport turns into a lost connection;
    a write the kernel cannot take now (``EAGAIN``) is left to the transport's buffer
    (pyserial spun on it), a failed one is a :class:`serial.SerialException`. Only a
    port opened as a local device gets them.
    """
    fd = getattr(device, "fd", None)
    if device is None or not isinstance(fd, int):
        return

    def read(size: int = 1) -> bytes:
        try:
            data = os.read(fd, size)
        except (BlockingIOError, InterruptedError):
            return b""
        except OSError as exc:
            raise serial.SerialException(f"read failed: {exc}") from exc
        if not data and select.select([fd], [], [], 0)[0]:
            # Readable, yet nothing: the device is gone (a tty in raw mode reads nothing,
            # not EAGAIN, when it merely has nothing, so readiness tells the two apart).
            raise serial.SerialException(
                "device reports readiness to read but returned no data "
                "(device disconnected or multiple access on port?)"
            )
        return data

    def write(data: bytes | bytearray | memoryview) -> int:
        try:
            return os.write(fd, data)
        except (BlockingIOError, InterruptedError):
            raise
        except OSError as exc:
            raise serial.SerialException(f"write failed: {exc}") from exc

    device.read = read  # type: ignore[method-assign]
    device.write = write  # type: ignore[method-assign,assignment]


# Unix98 pseudo-terminal slaves: character devices of majors 136..143 (the kernel's
# Documentation/admin-guide/devices.txt), wherever their node is reached from.
PTY_SLAVE_MAJORS: Final = range(136, 144)


def _is_pseudo_terminal(port: str) -> bool:
    """Whether ``port`` is a pseudo-terminal, by its device number, not its path.

    A pty bound at another path (``/dev/ttyUSB0`` in a container, a bind mount) is still
    one; its path alone said otherwise, and the parity setting then failed.
    """
    if "://" in port:
        return False
    try:
        mode = Path(port).stat()
    except OSError:
        return False  # opening it will say what is wrong
    return stat.S_ISCHR(mode.st_mode) and os.major(mode.st_rdev) in PTY_SLAVE_MAJORS


def _kind(exc: Exception) -> str:
    if isinstance(exc, EchoMismatchError):
        return ErrorKind.ECHO_MISMATCH
    if isinstance(exc, CrcError):
        return ErrorKind.CRC
    if isinstance(exc, UnexpectedDeviceError):
        return ErrorKind.WRONG_ADDRESS
    if isinstance(exc, MalformedFrameError):
        return ErrorKind.MALFORMED
    return ErrorKind.TIMEOUT
