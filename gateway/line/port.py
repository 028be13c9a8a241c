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
import stat
import termios
import time
from collections import Counter, defaultdict
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Final

import serial
import serial_asyncio_fast

from gateway.errors import (
    BusClosedError,
    BusTimeoutError,
    CrcError,
    DeviceExceptionError,
    FrameError,
    MalformedFrameError,
    PortUnavailableError,
    UnexpectedDeviceError,
)
from gateway.line import port_access
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


class ErrorKind:
    """Names of the failure classes counted per bus and device."""

    TIMEOUT: Final = "timeout"
    CRC: Final = "crc"
    EXCEPTION: Final = "exception"
    WRONG_ADDRESS: Final = "wrong_address"
    STALE: Final = "stale_frame"
    NOISE: Final = "noise"
    MALFORMED: Final = "malformed"


@dataclass(slots=True)
class LineStats:
    """Counters of one line, per device address where it matters. Read by the sinks."""

    requests: Counter[int] = field(default_factory=Counter)
    responses: Counter[int] = field(default_factory=Counter)
    errors: Counter[tuple[int, str]] = field(default_factory=Counter)
    exception_codes: Counter[tuple[int, int]] = field(default_factory=Counter)
    retries: Counter[int] = field(default_factory=Counter)
    tolerated: Counter[tuple[int, str]] = field(default_factory=Counter)
    latency_buckets: Counter[tuple[int, float]] = field(default_factory=Counter)
    latency_sum_s: defaultdict[int, float] = field(default_factory=lambda: defaultdict(float))
    busy_s: float = 0.0  # time the line carried our transactions
    started: float = field(default_factory=time.monotonic)
    port_open: bool = False
    port_failures: int = 0
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
        buckets = self.latency_buckets
        for bound in LATENCY_BUCKETS_S[bisect.bisect_left(LATENCY_BUCKETS_S, seconds) :]:
            buckets[device, bound] += 1
        buckets[device, math.inf] += 1

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
        options: port_access.PortOptions | None = None,
    ) -> None:
        """Describe the line; :meth:`open` opens it (``options``: RS485 mode, hints, roots)."""
        self.port = port
        self.options = options or port_access.PortOptions()
        self._latency_warned = False
        self.format = line
        self.stats = stats or LineStats()
        self.last_frame_end = float("-inf")  # monotonic time the line last fell silent
        self._transport: asyncio.Transport | None = None
        self._receiver: _Receiver | None = None
        self._character_s = line.character_s
        self._silence_s = max(SILENCE_CHARACTERS * self._character_s, MIN_SILENCE_S)
        self._timer = DeadlineTimer()
        # How late each request started after its gap was due (seconds), kept only when
        # a benchmark sets a list here; nothing in the gateway reads it.
        self.gap_lateness_s: list[float] | None = None

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
        self.stats.closed_because(None, "")
        self.stats.port_open = True
        self.last_frame_end = time.monotonic()

    async def close(self) -> None:
        """Close the port (idempotent); back once the device is closed (its lock released)."""
        transport, receiver = self._transport, self._receiver
        self._transport = self._receiver = None
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
        port = self._transport.get_extra_info("serial") if self._transport else None
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
            kind = ErrorKind.STALE if frames.crc_ok(stale) else ErrorKind.NOISE
            self.stats.errors[device, kind] += 1
            _LOGGER.debug(
                "%s: discarded %d %s bytes: %s", self.port, len(stale), kind, stale.hex(" ")
            )

    async def wait_gap(self, gap_s: float, *, not_before: float = 0.0) -> float:
        """Keep the line silent for ``gap_s`` after its last frame (and until ``not_before``).

        Returns when the gap was due, for the lateness of the request that follows.
        """
        receiver = self._live_receiver()
        while True:
            quiet_since = max(self.last_frame_end, receiver.last_byte_at)
            ready = max(quiet_since + gap_s, not_before)
            if ready <= time.monotonic():
                if self._unread_input():
                    # Bytes wait in the port's buffer that the event loop has not handed
                    # over yet (a late answer or noise while this process was busy
                    # elsewhere): the line was not quiet. They arrived at the latest now;
                    # the gap starts again.
                    receiver.last_byte_at = time.monotonic()
                    continue
                return ready
            # Not asyncio.sleep: its timers end up to 1 ms late (epoll counts whole
            # milliseconds), which made every gap up to 1 ms long. The timer fires within
            # tens of microseconds and costs no CPU while it waits (see line/timer).
            await self._timer.sleep_until(ready)
            self._live_receiver()

    async def transact(
        self,
        request: frames.Request,
        *,
        timeout_s: float,
        gap_s: float,
        not_before: float = 0.0,
        exceptions: Mapping[int, str] = frames.STANDARD_EXCEPTIONS,
        byte_count_16bit: bool = False,
    ) -> Exchange | None:
        """Send ``request`` after the gap and return its answer (``None`` for broadcasts).

        Raises :class:`BusTimeoutError`, :class:`CrcError`, :class:`UnexpectedDeviceError`,
        :class:`MalformedFrameError`, :class:`DeviceExceptionError` or
        :class:`BusClosedError`; every failure is counted by kind for the device.
        """
        due = await self.wait_gap(gap_s, not_before=not_before)
        self.flush_input(request.device)
        assert self._transport is not None  # noqa: S101 - _live_receiver checked it
        sent_at = time.monotonic()
        if self.gap_lateness_s is not None:
            self.gap_lateness_s.append(sent_at - due)
        try:
            self._transport.write(request.frame)
        except (OSError, serial.SerialException) as exc:
            raise BusClosedError(f"{self.port}: write failed: {exc}") from exc
        self.stats.requests[request.device] += 1
        request_end = sent_at + len(request.frame) * self._character_s
        if request.is_broadcast:
            self.last_frame_end = request_end
            self.stats.busy_s += request_end - sent_at
            return None
        try:
            response, received_at = await self._receive(
                request,
                deadline=request_end + timeout_s,
                exceptions=exceptions,
                byte_count_16bit=byte_count_16bit,
            )
        except DeviceExceptionError as exc:
            self.stats.exception_codes[request.device, exc.code] += 1
            self.stats.errors[request.device, ErrorKind.EXCEPTION] += 1
            self._finish(sent_at)
            raise
        except (BusTimeoutError, FrameError) as exc:
            self.stats.errors[request.device, _kind(exc)] += 1
            self._finish(sent_at)
            raise
        self._finish(sent_at, line_quiet_at=received_at)
        self.stats.responses[request.device] += 1
        self.stats.observe_latency(request.device, received_at - sent_at)
        if response.tolerated is not None:
            self.stats.tolerated[request.device, response.tolerated] += 1
        return Exchange(response=response, sent_at=sent_at, received_at=received_at)

    def _finish(self, sent_at: float, *, line_quiet_at: float | None = None) -> None:
        """The line is silent from the answer's last byte (or now, after a failure)."""
        end = line_quiet_at if line_quiet_at is not None else time.monotonic()
        self.last_frame_end = end
        self.stats.busy_s += end - sent_at

    async def _receive(
        self,
        request: frames.Request,
        *,
        deadline: float,
        exceptions: Mapping[int, str],
        byte_count_16bit: bool,
    ) -> tuple[frames.Response, float]:
        """Read until a frame answers ``request``; skip garbage and frames of others."""
        receiver = self._live_receiver()
        scan = _Scan(request, exceptions=exceptions, byte_count_16bit=byte_count_16bit)
        while True:
            try:
                result = scan.feed(receiver.buffer)
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

    def _consume(self, receiver: _Receiver, scan: _Scan, device: int) -> None:
        """Drop the bytes up to the answer; count what was skipped on the way.

        A late answer of another device is a stale frame of that device, garbage is
        noise on this request.
        """
        del receiver.buffer[: scan.consumed]
        if scan.other_device is not None:
            self.stats.errors[scan.other_device, ErrorKind.STALE] += 1
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


_WAIT: Final = object()  # a plausible answer has started: wait for the rest


class _Scan:
    """Looks for the answer to one request in the bytes received so far."""

    def __init__(
        self, request: frames.Request, *, exceptions: Mapping[int, str], byte_count_16bit: bool
    ) -> None:
        self.request = request
        self.exceptions = exceptions
        self.byte_count_16bit = byte_count_16bit
        self.consumed = 0
        self._length = 0
        self.crc_bad = False
        self.other_device: int | None = None
        self.garbage = False

    @property
    def suspect(self) -> bool:
        return self.crc_bad or self.other_device is not None

    def feed(self, buffer: bytearray) -> frames.Response | None:
        """The answer if the bytes hold one; ``None`` while more bytes are needed."""
        data = bytes(buffer)
        for offset in range(len(data) - 1):
            try:
                verdict = self._try(data[offset:])
            except DeviceExceptionError:
                self.consumed = offset + self._length
                raise
            if verdict is _WAIT:
                return None
            if isinstance(verdict, frames.Response):
                self.consumed = offset + self._length
                return verdict
        return None

    def _try(self, head: bytes) -> frames.Response | object | None:
        """Judge a candidate frame at the start of ``head``: the answer, wait, or skip."""
        request = self.request
        try:
            need = frames.response_length(request, head, byte_count_16bit=self.byte_count_16bit)
        except MalformedFrameError:
            self.garbage = True
            return None
        if need == 0 or len(head) < need:
            return _WAIT if head[0] == request.device else None
        candidate = head[:need]
        if not frames.crc_ok(candidate):
            self.crc_bad |= head[0] == request.device
            self.garbage = True
            return None
        self._length = need
        try:
            return frames.parse_response(
                request,
                candidate,
                exceptions=self.exceptions,
                byte_count_16bit=self.byte_count_16bit,
            )
        except UnexpectedDeviceError:
            self.other_device = head[0]
        except MalformedFrameError:
            self.garbage = True
        return None

    def failure(self, port: str) -> Exception:
        request = self.request
        what = f"device {request.device} function {request.function:#04x} at {request.address:#06x}"
        if self.crc_bad:
            return CrcError(f"{port}: answer of {what} failed its CRC")
        if self.other_device is not None:
            return UnexpectedDeviceError(
                f"{port}: device {self.other_device} answered a request for {what}",
                expected=request.device,
                received=self.other_device,
            )
        if self.garbage:
            return MalformedFrameError(f"{port}: no valid answer of {what}, only noise")
        return BusTimeoutError(f"{port}: no answer of {what}")


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
    if isinstance(exc, CrcError):
        return ErrorKind.CRC
    if isinstance(exc, UnexpectedDeviceError):
        return ErrorKind.WRONG_ADDRESS
    if isinstance(exc, MalformedFrameError):
        return ErrorKind.MALFORMED
    return ErrorKind.TIMEOUT
