"""The simulator's wire: a pseudo-terminal or a TCP socket carrying Modbus RTU, or Modbus TCP.

Bytes are cut into frames the way a slave's UART does it: a silence of 3.5 character
times ends a burst. A burst that holds more than one request means the master left no
gap; the bus's referee sees each of them with the arrival time of the burst.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import math
import os
import termios
import tty
from pathlib import Path
from typing import TYPE_CHECKING, Final

from gateway.errors import GatewayError
from gateway.simulator.converter import DEFAULT_CONVERTER_TIMEOUT_S, ModbusTcpConverter
from gateway.wire import frames

if TYPE_CHECKING:
    from collections.abc import Callable

    from gateway.simulator.bus import Reply, SimulatedBus

_LOGGER = logging.getLogger(__name__)
MIN_SILENCE_S: Final = 0.0015  # below this, event-loop timers are not reliable
STATS_INTERVAL_S: Final = 0.25
TIMER_GRANULARITY_S: Final = 0.0012  # epoll waits in whole milliseconds, rounded up
# The referee's watch on its own event loop: a tick every WATCH_S; a tick overdue by more
# than STALL_S means the loop was held up (a busy harness in the same process, a thread
# holding the GIL, a fork), so what arrived meanwhile has no trustworthy arrival time.
WATCH_S: Final = 0.005
STALL_S: Final = 0.003


class SimulatorError(GatewayError):
    """The simulator cannot serve: a pty that cannot be created, a port in use."""


class _Burst:
    """Collects bytes until the line has been silent for 3.5 characters."""

    def __init__(self, server: SimulatorServer, send: Callable[[bytes], None]) -> None:
        self._server = server
        self._send = send
        self._buffer = bytearray()
        self._start = 0.0
        self._judged = True  # False: the burst came in while the loop was held up
        self._timer: asyncio.TimerHandle | None = None

    def feed(self, data: bytes) -> None:
        loop = self._server.loop
        now = loop.time()
        if not self._buffer:
            self._start = now
            self._judged = True
        # Bytes read while the loop catches up may have waited in the kernel: the burst's
        # times say nothing of the master's gaps then. That holds for any read of a burst,
        # not only its first: a loop held up between two requests reads the second before
        # it runs the overdue flush of the first (a pty's reader comes before the loop's
        # timers), and judged as one burst the second would follow the first with no gap.
        self._judged = self._judged and not self._server.stalled(now)
        self._buffer.extend(data)
        if self._timer is not None:
            self._timer.cancel()
        self._timer = loop.call_later(self._server.silence_s, self._flush)

    def _flush(self) -> None:
        self._timer = None
        burst, self._buffer = bytes(self._buffer), bytearray()
        start = self._start
        line = self._server.bus.line
        while burst:
            need = frames.request_length(burst)
            frame = burst if need == 0 or need > len(burst) else burst[:need]
            if not frames.crc_ok(frame):
                frame = burst  # a slave cannot find frames inside garbage: all of it is one
            burst = burst[len(frame) :]
            self._server.handle(frame, start, self._send, judged=self._judged)
            if self._server.bus.pace:
                start += line.wire_s(len(frame))


class SimulatorServer:
    """Runs a :class:`SimulatedBus` on the event loop: receives, schedules, replies."""

    def __init__(self, bus: SimulatedBus, *, stats_path: Path | None = None) -> None:
        """Serve ``bus``; with ``stats_path`` keep a JSON stats file up to date."""
        self.bus = bus
        self.loop = asyncio.get_running_loop()
        self.silence_s = max(bus.line.wire_s(1) * 3.5, MIN_SILENCE_S)
        self.stats_path = stats_path
        self._pty: _PtyEndpoint | None = None
        self._servers: list[asyncio.Server] = []
        self._converter: ModbusTcpConverter | None = None
        self._stats_task: asyncio.Task[None] | None = None
        bus.start(self.loop.time())
        self._watch_due = self.loop.time() + WATCH_S
        self._watch = self.loop.call_at(self._watch_due, self._tick)
        self._caught_up_at = -math.inf

    def _tick(self) -> None:
        now = self.loop.time()
        if now - self._watch_due > STALL_S:
            self.bus.counters["referee_stalls"] += 1
            self._caught_up_at = now
        self._watch_due = now + WATCH_S
        self._watch = self.loop.call_at(self._watch_due, self._tick)

    def stalled(self, now: float) -> bool:
        """Whether the loop is only now catching up after being held up.

        An overdue watch tick at the moment bytes are taken means they may have waited in
        the kernel. Bytes taken just after the tick found the stall may have too: a stream
        reader hands them over one loop turn after they were read.
        """
        return now - self._watch_due > STALL_S or now - self._caught_up_at < STALL_S

    def handle(
        self, frame: bytes, start: float, send: Callable[[bytes], None], *, judged: bool = True
    ) -> None:
        """Give a received frame to the bus and schedule its replies on the line.

        ``judged=False``: the frame came in while this loop was held up, so its arrival
        time says nothing about the master's timing; it is answered but not refereed.
        """
        for reply in self.bus.on_frame(frame, start, judged=judged):
            # Timers fire up to 1 ms late; wake a little early and finish the wait by
            # yielding, so the simulated device answers when its timing says.
            self.loop.call_at(reply.at - TIMER_GRANULARITY_S, self._emit_on_time, reply, send)

    def _emit_on_time(self, reply: Reply, send: Callable[[bytes], None]) -> None:
        if self.loop.time() < reply.at:
            self.loop.call_soon(self._emit_on_time, reply, send)
            return
        self._emit(reply, send)

    def _emit(self, reply: Reply, send: Callable[[bytes], None]) -> None:
        # The time is taken before the write: if this process is preempted right after
        # writing, a time taken then would be later than the master saw the reply, and the
        # referee would blame a master that kept the gap. The referee must never do that.
        sent = self.loop.time()
        try:
            send(reply.data)
        except OSError as exc:  # the master went away; the line is simply not listened to
            _LOGGER.debug("reply not delivered: %s", exc)
        # Held up past its time, the reply is late by the simulator's fault: a master that
        # gave up and moved on collides with it, and is not to blame.
        self.bus.on_sent(reply, sent, late=sent - reply.at > STALL_S)

    # --- endpoints -----------------------------------------------------------------------

    def open_pty(self, path: Path) -> Path:
        """Create a pty pair and link its slave end at ``path`` for a master to open."""
        self._pty = _PtyEndpoint(self, path)
        self._pty.open()
        return self._pty.slave_name

    def unplug_pty(self) -> None:
        """Make the port disappear, as an unplugged USB adapter does."""
        if self._pty is not None:
            self._pty.close()

    def replug_pty(self) -> None:
        """Bring the port back at the same path."""
        if self._pty is not None:
            self._pty.open()

    async def open_tcp(
        self,
        host: str,
        port: int,
        *,
        framing: str = "rtu",
        converter_timeout_s: float = DEFAULT_CONVERTER_TIMEOUT_S,
    ) -> int:
        """Serve on TCP; returns the port.

        ``framing="rtu"``: RTU over TCP, what converters in transparent mode pass on;
        ``"tcp"``: Modbus TCP, as a converter in Modbus TCP mode (MBAP, unit id = address,
        0B after ``converter_timeout_s`` without an answer; see ``simulator/converter``).
        """

        def connected(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
            burst = _Burst(self, writer.write)
            self._servers[-1].get_loop().create_task(_pump(reader, writer, burst))

        if framing == "tcp":
            if self._converter is None:
                self._converter = ModbusTcpConverter(self, timeout_s=converter_timeout_s)
            handler = self._converter.connected
        else:
            handler = connected
        try:
            server = await asyncio.start_server(handler, host, port)
        except OSError as exc:
            raise SimulatorError(f"cannot listen on {host}:{port}: {exc}") from exc
        self._servers.append(server)
        return int(server.sockets[0].getsockname()[1])

    def start_stats(self) -> None:
        """Write the stats file now and every 250 ms while serving."""
        if self.stats_path is not None:
            self._stats_task = self.loop.create_task(self._stats_loop(), name="simulator.stats")

    async def _stats_loop(self) -> None:
        while True:
            self.write_stats()
            await asyncio.sleep(STATS_INTERVAL_S)

    def write_stats(self) -> None:
        """Replace the stats file atomically, so readers never see half of it."""
        if self.stats_path is None:
            return
        temporary = self.stats_path.with_suffix(self.stats_path.suffix + ".tmp")
        temporary.write_text(json.dumps(self.bus.stats(), indent=1), encoding="utf-8")
        temporary.replace(self.stats_path)

    async def close(self) -> None:
        """Stop serving, write the final stats, remove the pty link."""
        self._watch.cancel()
        if self._stats_task is not None:
            self._stats_task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._stats_task
        for server in self._servers:
            server.close()
        if self._converter is not None:
            await self._converter.close()
        for server in self._servers:
            await server.wait_closed()
        if self._pty is not None:
            self._pty.close()
        self.write_stats()


async def _pump(reader: asyncio.StreamReader, writer: asyncio.StreamWriter, burst: _Burst) -> None:
    try:
        while data := await reader.read(4096):
            burst.feed(data)
    except ConnectionError:
        pass
    finally:
        writer.close()


class _PtyEndpoint:
    """A pseudo-terminal pair whose slave end is linked at a path, socat-style."""

    def __init__(self, server: SimulatorServer, path: Path) -> None:
        self._server = server
        self.path = path
        self.slave_name = Path()
        self._master = -1
        self._slave = -1
        self._burst = _Burst(server, self._write)

    def open(self) -> None:
        if self.path.is_symlink():
            self.path.unlink()
        elif self.path.exists():
            raise SimulatorError(f"{self.path} exists and is not a link; refusing to replace it")
        master, slave = os.openpty()
        tty.setraw(slave, termios.TCSANOW)  # no echo, no line discipline: bytes as they come
        os.set_blocking(master, False)
        self.slave_name = Path(os.ttyname(slave))
        try:
            self.path.symlink_to(self.slave_name)
        except OSError as exc:
            os.close(master)
            os.close(slave)
            raise SimulatorError(f"cannot create {self.path}: {exc.strerror}") from exc
        self._master, self._slave = master, slave
        self._server.loop.add_reader(master, self._readable)

    def _readable(self) -> None:
        try:
            data = os.read(self._master, 4096)
        except BlockingIOError:
            return
        except OSError:  # EIO: no master has the port open right now
            return
        if data:
            self._burst.feed(data)

    def _write(self, data: bytes) -> None:
        if self._master >= 0:
            os.write(self._master, data)

    def close(self) -> None:
        if self._master >= 0:
            self._server.loop.remove_reader(self._master)
            os.close(self._master)
            os.close(self._slave)
            self._master = self._slave = -1
        if self.path.is_symlink():
            self.path.unlink()
