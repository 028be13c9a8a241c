"""Sessions with serial device servers: keepalive, user timeout, silence, a pause after connecting.

A converter on the network can vanish without a word (powered off, a cable pulled, a
firewall that forgets the connection); Linux keeps such a session for some 15 minutes of
retransmissions, or for ever while nothing is sent. TCP keepalive ends it while the line
is idle and TCP_USER_TIMEOUT while requests go unacknowledged (tcp(7)), both within the
bounds of ``buses[].tcp``. A converter that stays connected but answers nothing (its
serial side hung, a session it no longer serves) is found by :class:`SilenceWatch`:
requests in a row without a byte back end the session, which is opened again at once.

Both network lines use this module: :class:`SocketLine` here (``socket://``, RTU over TCP
through pyserial's socket under the port's transport) and
:class:`gateway.line.mbap.MbapLine` (``tcp://``, Modbus TCP).
"""

from __future__ import annotations

import logging
import math
import socket
import time
from typing import TYPE_CHECKING, Any, Final

from gateway.config.network import DEFAULT_TCP
from gateway.errors import BusTimeoutError, DeviceExceptionError, FrameError
from gateway.line.echo import EchoMode
from gateway.line.port import Line

if TYPE_CHECKING:
    from asyncio.trsock import TransportSocket

    from gateway.config.network import TcpSettings
    from gateway.line.port import Exchange, LineStats
    from gateway.wire import frames
    from gateway.wire.timing import LineFormat

_LOGGER = logging.getLogger(__name__)

MS_PER_S: Final = 1000  # TCP_USER_TIMEOUT is in milliseconds (tcp(7))


def configure_socket(sock: socket.socket | TransportSocket, settings: TcpSettings) -> None:
    """Keepalive and the user timeout on a connected socket (tcp(7), Linux 2.6.37+).

    With requests in flight, their data unacknowledged for ``user_timeout_s`` ends the
    session; idle, the first unanswered keepalive probe past ``user_timeout_s`` does (the
    probes start after ``keepalive_s`` and follow every ``keepalive_interval_s``; Linux
    counts ``keepalive_count`` of them only without a user timeout). Measured on loopback
    with the peer's packets dropped: 3 s of user timeout ended a busy session after 3.6 s
    and an idle one after 3.1 s. The kernel reports ETIMEDOUT; the bus reopens on its backoff.
    """
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_KEEPALIVE, 1)
    sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_KEEPIDLE, settings.keepalive_s)
    sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_KEEPINTVL, settings.keepalive_interval_s)
    sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_KEEPCNT, settings.keepalive_count)
    timeout_ms = round(settings.user_timeout_s * MS_PER_S)
    sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_USER_TIMEOUT, timeout_ms)
    # Requests are a few bytes each and wait for their answer: Nagle's delay only adds
    # latency (asyncio sets it for its own transports; pyserial's socket:// does not).
    sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)


class SilenceWatch:
    """Counts requests in a row that got no byte back; says when the session is to end.

    Logged once per silent stretch: a warning when the limit is first reached, debug for
    every further reopening while the peer stays silent, info when it answers again.
    """

    def __init__(self, *, port: str, limit: int) -> None:
        """Watch ``port``'s session; ``limit`` silent requests end it (0: never)."""
        self.port = port
        self.limit = limit
        self.silent = 0  # requests in a row without a byte back
        self.reopened = 0  # sessions ended for silence in this stretch
        self.ended_at: list[float] = []  # monotonic times a session was ended for silence

    def heard(self) -> None:
        """A byte came back: the session is alive."""
        if self.reopened:
            _LOGGER.info(
                "%s: the peer answers again (after %d silent sessions)", self.port, self.reopened
            )
        self.silent = self.reopened = 0

    def unheard(self) -> bool:
        """A request got no byte back; ``True`` when the session is to be ended now."""
        self.silent += 1
        if not self.limit or self.silent < self.limit:
            return False
        log = _LOGGER.warning if not self.reopened else _LOGGER.debug
        log(
            "%s: no byte back for %d requests in a row: the converter keeps the session "
            "but answers nothing (or every device behind it is away); reopening the "
            "session (tcp.silent_requests: %d)",
            self.port,
            self.silent,
            self.limit,
        )
        self.silent = 0
        self.reopened += 1
        self.ended_at.append(time.monotonic())
        return True


class SocketLine(Line):
    """A ``socket://`` bus (RTU over TCP): the serial :class:`Line` with a watched session.

    Framing, gaps and every check of the answer are :class:`Line`'s (pyserial's socket
    stands where the serial port would); this adds what a network peer needs: keepalive
    and the user timeout on pyserial's socket, the pause after connecting, the least pause
    between requests, and the end of a session that stays silent.
    """

    def __init__(
        self,
        *,
        port: str,
        line: LineFormat,
        stats: LineStats | None = None,
        tcp: TcpSettings = DEFAULT_TCP,
        bus: str = "",
        echo: EchoMode = EchoMode.AUTO,
    ) -> None:
        """Describe the bus; :meth:`open` connects."""
        super().__init__(port=port, line=line, stats=stats, bus=bus, echo=echo)
        self.tcp = tcp
        self.watch = SilenceWatch(port=port, limit=tcp.silent_requests)
        self._ready_at = -math.inf  # no request before the pause after connecting

    async def open(self) -> None:
        """Connect, set keepalive and the user timeout, then start the pause after connecting."""
        await super().open()
        sock = self.tcp_socket()
        if sock is not None:
            configure_socket(sock, self.tcp)
        self._ready_at = time.monotonic() + self.tcp.connect_pause_s

    def tcp_socket(self) -> socket.socket | None:
        """The socket of pyserial under the transport: ``serial_for_url`` keeps it as ``_socket``.

        pyserial offers no public way to it; its socket:// handler has kept this name
        since 2.7. ``None`` when the port is closed.
        """
        transport = self._transport
        port = transport.get_extra_info("serial") if transport is not None else None
        sock = getattr(port, "_socket", None)
        return sock if isinstance(sock, socket.socket) else None

    async def wait_gap(self, gap_s: float, *, not_before: float = 0.0, device: int = 0) -> float:
        """The line's gap, at least ``tcp.request_pause_ms``, and not within the connect pause."""
        pause_s = self.tcp.request_pause_ms / MS_PER_S
        return await super().wait_gap(
            max(gap_s, pause_s), not_before=max(not_before, self._ready_at), device=device
        )

    async def transact(self, request: frames.Request, **options: Any) -> Exchange | None:  # noqa: ANN401
        """:meth:`Line.transact`, watched: a session silent for too many requests is reopened.

        The options pass through unchanged (``timeout_s``, ``gap_s``, ...): this class adds
        nothing to a transaction, it only watches whether the peer said anything.
        """
        before = self._last_byte_at()
        try:
            exchange = await super().transact(request, **options)
        except BusTimeoutError:
            if self._last_byte_at() > before:
                self.watch.heard()
            elif self.watch.unheard():
                await self.close()
                await self.open()  # fails as a closed port does: the worker's backoff
            raise
        except (FrameError, DeviceExceptionError):
            self.watch.heard()  # bytes came: a wrong answer, but from a live peer
            raise
        if exchange is not None or self._last_byte_at() > before:
            self.watch.heard()
        return exchange

    def _last_byte_at(self) -> float:
        receiver = self._receiver
        return receiver.last_byte_at if receiver is not None else -math.inf
