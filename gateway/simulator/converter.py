"""The simulated line behind a serial device server in Modbus TCP mode.

What such a converter does (Moxa MGate, USR, Waveshare and the like in "Modbus TCP to
RTU" mode): takes Modbus TCP requests from any number of connections, puts them one at a
time on its RS485 side as RTU frames (unit id = address, its own inter-frame gap before
each), waits for the device's answer up to its response timeout, and sends it back with
the request's transaction id; when no valid answer came in time it answers exception 0B
(gateway target device failed to respond), and for a unit id it cannot route (outside
1..247) exception 0A (gateway path unavailable). Broadcasts (unit 0) get no answer.

The simulated bus behind it keeps refereeing the serial side: the converter keeps the
inter-frame gap itself, so what the referee can still catch is the master's, chiefly a
request inside a device's post-write wait, which the device ignores (and the converter
then answers 0B, as a real one would).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from typing import TYPE_CHECKING, Final, Protocol

from gateway.errors import FrameError, MalformedFrameError
from gateway.wire import frames, mbap

if TYPE_CHECKING:
    from collections.abc import Callable

    from gateway.simulator.bus import SimulatedBus

_LOGGER = logging.getLogger(__name__)

DEFAULT_CONVERTER_TIMEOUT_S: Final = 0.05  # after the answer's wire time; the gateway waits longer
GAP_MARGIN_S: Final = 0.0002  # event-loop timers may fire a hair early: never shave the gap
MAX_UNIT: Final = 247  # Modbus over serial line 2.2: unicast addresses 1..247


class Line(Protocol):
    """What the converter uses of the simulator's server (``transport.SimulatorServer``)."""

    @property
    def loop(self) -> asyncio.AbstractEventLoop:
        """The loop the server runs on."""

    @property
    def bus(self) -> SimulatedBus:
        """The simulated line with its devices and referee."""

    def stalled(self, now: float) -> bool:
        """Whether the loop was held up around ``now`` (the request is then not judged)."""

    def handle(
        self, frame: bytes, start: float, send: Callable[[bytes], None], *, judged: bool = True
    ) -> None:
        """Put a request on the line at ``start``; its answers go to ``send`` in time."""


class ModbusTcpConverter:
    """A converter in Modbus TCP mode in front of a simulated line."""

    def __init__(self, server: Line, *, timeout_s: float = DEFAULT_CONVERTER_TIMEOUT_S) -> None:
        """Forward to ``server``'s bus, waiting ``timeout_s`` for an answer.

        The timeout counts after the answer's wire time, as a converter set up for its
        line's longest answer waits.
        """
        self._server = server
        self.timeout_s = timeout_s
        self._queue: asyncio.Queue[tuple[mbap.MbapFrame, asyncio.StreamWriter]] = asyncio.Queue()
        self._task = server.loop.create_task(self._serve_line(), name="simulator.converter")
        self._task.add_done_callback(_report_end)
        self._connections: set[asyncio.Task[None]] = set()

    def connected(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        """A master connected: read its requests for as long as it stays."""
        task = self._server.loop.create_task(self._read(reader, writer))
        self._connections.add(task)
        task.add_done_callback(self._connections.discard)

    async def _read(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        buffer = bytearray()
        try:
            while data := await reader.read(4096):
                buffer.extend(data)
                while (cut := mbap.decode(buffer)) is not None:
                    frame, used = cut
                    del buffer[:used]
                    self._queue.put_nowait((frame, writer))
        except MalformedFrameError as exc:
            # As real converters do: a stream that is not Modbus TCP is closed.
            self._server.bus.counters["mbap_refused"] += 1
            _LOGGER.debug("closing a connection: %s", exc)
        except ConnectionError:
            pass
        finally:
            writer.close()

    async def _serve_line(self) -> None:
        while True:
            frame, writer = await self._queue.get()
            answer = await self._forward(frame)
            if answer is not None and not writer.is_closing():
                writer.write(mbap.encode(frame.transaction, frame.unit, answer))

    async def _forward(self, frame: mbap.MbapFrame) -> bytes | None:
        """The request on the serial side; the answer's PDU, an exception, or ``None``."""
        counters = self._server.bus.counters
        counters["mbap_requests"] += 1
        if frame.unit > MAX_UNIT or not frame.pdu:
            counters["mbap_0a"] += 1
            function = frame.pdu[0] if frame.pdu else 0
            return bytes((function | frames.EXCEPTION_FLAG, mbap.GATEWAY_PATH_UNAVAILABLE))
        rtu = mbap.to_rtu(frame.unit, frame.pdu)
        start = await self._line_free(frame.unit)
        loop = self._server.loop
        answered: asyncio.Future[bytes] = loop.create_future()

        def hear(data: bytes) -> None:
            """Bytes on the serial side: the converter takes a valid frame of the unit."""
            if not answered.done() and frames.crc_ok(data) and data[0] == frame.unit:
                answered.set_result(data)

        self._server.handle(rtu, start, hear, judged=not self._server.stalled(start))
        if frame.unit == frames.BROADCAST:
            return None
        deadline = start + self._wire_s(len(rtu)) + self._wire_s(_answer_length(rtu))
        try:
            async with asyncio.timeout_at(deadline + self.timeout_s):
                # Shielded: heard in the same turn of the loop as the timeout fires, the
                # answer is still taken (a cancelled wait would have cancelled it).
                data = await asyncio.shield(answered)
        except TimeoutError:
            if answered.done():
                return answered.result()[1:-2]
            answered.cancel()
            counters["mbap_0b"] += 1
            return bytes((frame.pdu[0] | frames.EXCEPTION_FLAG, mbap.GATEWAY_TARGET_FAILED))
        return data[1:-2]

    def _wire_s(self, nbytes: int) -> float:
        bus = self._server.bus
        return bus.line.wire_s(nbytes) if bus.pace else 0.0

    async def _line_free(self, unit: int) -> float:
        """Wait until the serial side has been silent for the gap; the request starts then."""
        bus = self._server.bus
        device = bus.devices.get(unit)
        gap = bus.line.frame_gap_s(device.profile.timing.min_gap_s if device else 0.0)
        referee = bus.referee
        loop = self._server.loop
        while True:
            ready = max(referee.last_frame_end, referee.answer_until) + gap + GAP_MARGIN_S
            if loop.time() >= ready:
                return loop.time()
            await asyncio.sleep(ready - loop.time())

    async def close(self) -> None:
        """Stop forwarding and reading."""
        tasks = [self._task, *self._connections]
        for task in tasks:
            task.cancel()
        for task in tasks:
            with contextlib.suppress(asyncio.CancelledError):
                await task


def _report_end(task: asyncio.Task[None]) -> None:
    """A converter that stops answering is a simulator bug: said loudly, not left silent."""
    if not task.cancelled() and (exc := task.exception()) is not None:
        _LOGGER.error("the simulated converter stopped: %r", exc, exc_info=exc)


def _answer_length(rtu: bytes) -> int:
    """The length of the device's answer to ``rtu``, as the converter can tell it."""
    try:
        request = frames.parse_request(rtu)
    except FrameError:
        return frames.EXCEPTION_FRAME_LENGTH
    if request.function in frames.READ_FUNCTIONS:
        return 5 + 2 * request.count
    return frames.WRITE_RESPONSE_LENGTH
