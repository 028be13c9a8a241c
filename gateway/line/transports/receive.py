"""What comes back for a request on an RTU stream: the adapter's echo, then the answer.

The answer is read until a frame answers the request (:class:`~gateway.line.transports.answer.
AnswerScan` passes over garbage, other devices' frames, an unexpected echo and frames too
early), a corrupted answer of the device's own is final once the line falls silent, and at
a deadline the kernel is asked once more for bytes the event loop has not handed over.
Answers that come late are told apart from the current one and remembered: which request
of which device timed out last, and how late its answer came (for the hint to raise the
timeout).
"""

from __future__ import annotations

import asyncio
import logging
import math
import time
from typing import TYPE_CHECKING

from gateway.errors import BusTimeoutError, DeviceExceptionError, EchoMismatchError, FrameError
from gateway.line.boundary import LateAnswer
from gateway.line.stats import ErrorKind
from gateway.line.transports.answer import AnswerScan, holds_answer
from gateway.line.transports.echo import ECHO_MARGIN_S, earliest_answer
from gateway.line.transports.inbox import LAST_LOOK_S, LAST_LOOKS
from gateway.line.transports.owed import OwedAnswer
from gateway.wire import frames
from gateway.wire.timing import FRAME_GAP_CHARACTERS

if TYPE_CHECKING:
    from collections.abc import Callable

    from gateway.line.boundary import RequestOptions
    from gateway.line.stats import LineStats
    from gateway.line.transports.echo import EchoPolicy
    from gateway.line.transports.inbox import Inbox

_LOGGER = logging.getLogger(__name__)


class Receiver:
    """Reads the echo and the answer of each request of one RTU line; remembers late ones."""

    def __init__(
        self,
        *,
        port: str,
        stats: LineStats,
        echo: EchoPolicy,
        character_s: float,
        silence_s: float,
        judges_by_wire: bool,
        live: Callable[[], Inbox],
        unread_input: Callable[[], bool],
    ) -> None:
        """Read for the line on ``port``; ``live`` gives its inbox (or raises: it went away).

        ``unread_input`` asks the kernel whether bytes wait that the inbox has not seen.
        """
        self.port = port
        self.stats = stats
        self.echo = echo
        self.judges_by_wire = judges_by_wire
        self._character_s = character_s
        self._silence_s = silence_s
        self._live = live
        self._unread_input = unread_input
        # The last request that timed out per device (when sent, how long it waited), so
        # that its answer coming later tells how late; the worker asks for it.
        self._timed_out: dict[int, tuple[float, float, float]] = {}
        self.late_answer: LateAnswer | None = None
        # A cancelled transaction's answer still due (:meth:`settle_owed`).
        self.owed: OwedAnswer | None = None

    def timed_out(self, device: int, sent_at: float, timeout_s: float, waited_s: float) -> None:
        """The device's request sent at ``sent_at`` got no answer of its own in time."""
        self._timed_out[device] = (sent_at, timeout_s, waited_s)

    def answered(self, device: int) -> None:
        """The device answered: an answer of it that comes later is no late one of before."""
        if self._timed_out:
            self._timed_out.pop(device, None)

    def echo_seen(self, device: int) -> None:
        """An echo where none was expected: counted once the bus has settled on no echo."""
        if self.echo.echoes is False:
            self.stats.errors[device, ErrorKind.ECHO] += 1
            self.echo.unexpected()
        else:
            self.echo.seen = True

    def note_late(self, device: int, arrived_at: float) -> None:
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

    def discard(self, inbox: Inbox, device: int, last_sent: bytes) -> None:
        """Drop, judged, what came before ``device``'s request (``last_sent``: an echo's copy)."""
        stale = bytes(inbox.buffer)
        inbox.buffer.clear()
        if stale == last_sent:
            # The adapter's echo of a request that waited for no answer (a broadcast),
            # or of a read whose answer never came: the adapter's doing, not the line's.
            # (A unicast write's late answer is a copy of it too: not remembered.)
            self.echo_seen(device)
            return
        kind = ErrorKind.STALE if frames.crc_ok(stale) else ErrorKind.NOISE
        if kind == ErrorKind.STALE:
            self.note_late(stale[0], inbox.last_byte_at)
        self.stats.errors[device, kind] += 1
        _LOGGER.debug("%s: discarded %d %s bytes: %s", self.port, len(stale), kind, stale.hex(" "))

    def owe(
        self, request: frames.Request, options: RequestOptions, deadline: float, inbox: Inbox
    ) -> None:
        """``request`` went out and its transaction was cancelled: its answer is still due."""
        self.owed = OwedAnswer(request=request, options=options, deadline=deadline, inbox=inbox)

    async def settle_owed(self, inbox: Inbox, quiet_since: float) -> float:
        """Wait for the answer still due on ``inbox`` (:mod:`~gateway.line.transports.owed`).

        When the line fell quiet: ``quiet_since`` if nothing is due on this stream.
        """
        owed, self.owed = self.owed, None
        if owed is None or owed.inbox is not inbox:
            return quiet_since
        try:
            _, quiet_at = await self._scan_until_answer(
                inbox, owed.scan(), owed.request, owed.deadline
            )
        except asyncio.CancelledError:
            self.owed = owed  # still due, for the next transaction
            raise
        except (BusTimeoutError, FrameError, DeviceExceptionError) as exc:
            _LOGGER.debug("%s: a cancelled request's answer: %s", self.port, exc)
            return time.monotonic()
        _LOGGER.debug("%s: a cancelled request's answer dropped", self.port)
        return quiet_at

    async def read_echo(self, request: frames.Request, request_end: float) -> None:
        """``echo: on``: read the request back, byte for byte, before its answer.

        The echo is complete once the request is on the wire; the adapter may hand it over
        later (USB latency), so the wait has a margin. Anything else is a mismatch: the
        bytes are dropped and the transaction fails, since an answer read after a garbled
        echo cannot be trusted to be in step.
        """
        inbox = self._live()
        frame = request.frame
        deadline = request_end + ECHO_MARGIN_S + FRAME_GAP_CHARACTERS * self._character_s
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
            self._live()
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

    async def receive(
        self, request: frames.Request, options: RequestOptions, *, sent_at: float, deadline: float
    ) -> tuple[frames.Response, float]:
        """Read until a frame answers ``request``; skip garbage, echoes and frames of others."""
        inbox = self._live()
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
                self.echo_seen(request.device)
            if policy.echoes is None and not request.is_write:  # ``auto``, undecided
                policy.observed_read(echoed=scan.echo_skipped)

    async def _scan_until_answer(
        self, inbox: Inbox, scan: AnswerScan, request: frames.Request, deadline: float
    ) -> tuple[frames.Response, float]:
        looks = 0  # at the deadline, for bytes the kernel holds that the loop has not handed over
        while True:
            try:
                # Fed only what is new: the first pass, before the answer came, has nothing.
                result = (
                    scan.feed(inbox.buffer, inbox.last_byte_at)
                    if len(inbox.buffer) > scan.start
                    else None
                )
            except DeviceExceptionError:
                # An exception answer is an answer too: consumed here, or the next
                # transaction would flush it and count it a second time, as a stale frame.
                self._consume(inbox, scan, request.device)
                raise
            if result is not None:
                self._consume(inbox, scan, request.device)
                if len(inbox.buffer) > 1:  # more than the answer came: a later one?
                    result = self._later_answer(inbox, scan, result)
                return result, inbox.last_byte_at
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
            if inbox.gone:  # ``_live`` only then: a method call less on every answer
                self._live()

    async def _handed_over_late(self, inbox: Inbox) -> bool:
        """At a deadline: whether bytes waited in the kernel, now handed to ``inbox``.

        The event loop woke the wait on its timer before it handed the bytes over: a
        process held up (a CPU quota, a busy machine) came back to both at once, and the
        timer was due in the pass it was held in. One ioctl; only at a deadline.
        """
        if not self._unread_input():
            return False
        await inbox.wait(LAST_LOOK_S)
        self._live()
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
            self.note_late(request.device, inbox.last_byte_at)
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
            self.note_late(scan.other_device, inbox.last_byte_at)
        if scan.garbage:
            self.stats.errors[device, ErrorKind.NOISE] += 1
