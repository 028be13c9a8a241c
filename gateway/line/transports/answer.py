"""The answer to one request, looked for in the bytes a line has received so far.

Pure: bytes and times in, a verdict out (the answer, wait for more, or nothing here yet),
with what was passed over on the way: garbage, another device's frame, a corrupted answer
of the device itself, the request's own echo, or a frame complete before the device could
have answered (:func:`~gateway.line.transports.echo.earliest_answer`).
:class:`~gateway.line.transports.rtu.RtuLine` feeds it as bytes arrive and reads the
failure it names when the time is up.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Final

from gateway.errors import (
    BusTimeoutError,
    CrcError,
    DeviceExceptionError,
    MalformedFrameError,
    UnexpectedDeviceError,
)
from gateway.wire import frames

if TYPE_CHECKING:
    from collections.abc import Mapping


def holds_answer(request: frames.Request, data: bytes) -> bool:
    """Whether ``data`` starts with a well-formed answer to ``request`` (CRC included)."""
    try:
        need = frames.response_length(request, data)
    except MalformedFrameError:
        return False
    return 0 < need <= len(data) and frames.crc_ok(data[:need])


_WAIT: Final = object()  # a plausible answer has started: wait for the rest
_OTHERS: Final = object()  # a whole, sound frame of another device: passed over as one


class AnswerScan:
    """Looks for the answer to one request in the bytes received so far.

    Bytes before ``start`` are judged not to be the answer: an echo of the request, or a
    frame complete before any answer could be
    (:func:`~gateway.line.transports.echo.earliest_answer`).
    """

    __slots__ = (
        "_answer_floor",
        "_character_s",
        "_echo",
        "_echo_known",
        "_head",
        "_length",
        "_need",
        "byte_count_16bit",
        "consumed",
        "crc_bad",
        "early",
        "echo_skipped",
        "exceptions",
        "garbage",
        "other_device",
        "request",
        "start",
    )

    def __init__(
        self,
        request: frames.Request,
        *,
        exceptions: Mapping[int, str],
        byte_count_16bit: bool,
        echo: bytes | None = None,
        echo_known: bool = False,
        answer_floor: float = 0.0,
        character_s: float = 0.0,
    ) -> None:
        """Look for ``request``'s answer in the bytes fed from now on.

        ``echo``: the request's bytes, while its echo may still lead the answer;
        ``answer_floor``: when the line had carried the request and the device's
        turnaround; ``character_s``: what each byte of an answer adds to that.
        """
        self.request = request
        self.exceptions = exceptions
        self.byte_count_16bit = byte_count_16bit
        self.consumed = 0
        self._length = 0
        self.crc_bad = False
        self.other_device: int | None = None
        self.garbage = False
        # The request's echo to look for ahead of the answer (None: read back already).
        self._echo = echo
        self._echo_known = echo_known  # the line has echoed before: a copy is its echo
        self.echo_skipped = False
        self.early = False  # a frame complete before the device could have answered
        self._answer_floor = answer_floor  # sent + request on the wire + turnaround
        self._character_s = character_s
        self.start = 0
        # A read's own answer, as nearly every answer is: its first three bytes (device,
        # function, byte count) and its length, for the fast path of :meth:`feed`.
        if request.function in frames.READ_FUNCTIONS and not request.is_broadcast:
            self._head: bytes | None = bytes((request.device, request.function, 2 * request.count))
            self._need = 5 + 2 * request.count
        else:
            self._head, self._need = None, 0

    def _too_early(self, length: int, arrived_at: float) -> bool:
        return arrived_at < self._answer_floor + length * self._character_s

    def _skip_echo(self, data: bytes, arrived_at: float) -> bool | None:
        """Skip the request's echo at ``start``; ``None`` while it may still be coming.

        A read's echo is never its answer, so a copy of it is the echo whenever it comes.
        A single write's answer is a copy of its request (function 06, and the first bytes
        of 16): there, a copy is the echo only if it came too early to be the answer, or
        if this line is known to echo (then the device's copy follows it).
        """
        echo = self._echo
        if echo is None or self.echo_skipped:
            return False
        head = data[self.start : self.start + len(echo)]
        if len(head) < len(echo):
            return None if head and echo.startswith(head) else False
        if head != echo:
            return False
        if not self.request.is_write or self._echo_known or self._too_early(len(echo), arrived_at):
            self.start += len(echo)
            self.echo_skipped = True
            return True
        return False

    def feed(self, buffer: bytearray, arrived_at: float = math.inf) -> frames.Response | None:
        """The answer if the bytes hold one; ``None`` while more bytes are needed.

        ``arrived_at`` is when the last of the bytes came: a frame judged complete before
        the device could have answered is not its answer, and is passed over for good.
        """
        if len(buffer) <= self.start:
            return None  # nothing new since what was passed over (the scan keeps nothing else)
        answer = self._own_read_answer(buffer, arrived_at)
        if answer is not None:
            return answer
        data = bytes(buffer)
        if self._skip_echo(data, arrived_at) is None:
            return None
        offset = self.start
        while offset < len(data) - 1:
            try:
                verdict = self._try(data[offset:])
            except DeviceExceptionError:
                if self._too_early(self._length, arrived_at):
                    offset = self.start = offset + self._length
                    self.early = True
                    continue
                self.consumed = offset + self._length
                raise
            if verdict is _WAIT:
                return None
            if isinstance(verdict, frames.Response):
                if self._too_early(self._length, arrived_at):
                    offset = self.start = offset + self._length
                    self.early = True
                    continue
                self.consumed = offset + self._length
                return verdict
            # Another device's frame is passed over at once: scanned byte by byte, its own
            # bytes were taken for garbage, and a byte equal to this device's address could
            # begin a "corrupted answer" of it (noise or a CRC error where it is stale).
            offset += self._length if verdict is _OTHERS else 1
        return None

    def _own_read_answer(self, buffer: bytearray, arrived_at: float) -> frames.Response | None:
        """The read's answer at the start of ``buffer``, found without the general scan.

        The same verdict the scan below gives such a frame (its CRC checked once, not
        twice, and no PDU decoder), for the answer that comes on nearly every
        transaction; ``None`` leaves anything else (a bad CRC, an answer too early, what
        may be the request's echo) to the scan.
        """
        head, need = self._head, self._need
        if head is None or self.start or len(buffer) < need or not buffer.startswith(head):
            return None  # not a read, something passed over already, or not (all) there yet
        echo = self._echo
        if echo is not None and not self.echo_skipped and echo.startswith(buffer[: len(echo)]):
            return None  # the request's echo, or its beginning: the scan decides
        frame = buffer[:need]
        if not frames.crc_ok(frame) or self._too_early(need, arrived_at):
            return None
        self._length = self.consumed = need
        return frames.read_answer(self.request, frame)

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
            return _OTHERS
        except MalformedFrameError:
            self.garbage = True
        return None

    def failure(self, port: str) -> Exception:
        """What went wrong, once the time is up: the worst of what was passed over."""
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
