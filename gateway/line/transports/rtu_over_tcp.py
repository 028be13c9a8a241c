"""A ``socket://`` bus: RTU frames through a serial device server's transparent TCP port.

The converter passes bytes both ways and keeps its own serial side's timing; the frames,
the gap, the echo and every check of the answer are :class:`~gateway.line.transports.rtu.RtuLine`'s.
What a network peer adds is this module's: the session opened with keepalive and the user
timeout (:mod:`gateway.line.transports.tcp_session`), a pause after connecting, the least pause
between requests, and the end of a session that stays silent. An answer's arrival is not
judged by the bus's wire time: the format describes the converter's serial side, which
the gateway cannot see.
"""

from __future__ import annotations

import math
import time
from typing import TYPE_CHECKING
from urllib.parse import urlsplit

from gateway.config.echo import EchoMode
from gateway.config.network import DEFAULT_TCP
from gateway.errors import BusClosedError, BusTimeoutError, DeviceExceptionError, FrameError
from gateway.line.transports.rtu import RtuLine
from gateway.line.transports.tcp_session import (
    MS_PER_S,
    SilenceWatch,
    connect,
    session_ended,
    unread_bytes,
)

if TYPE_CHECKING:
    import asyncio
    from asyncio.trsock import TransportSocket

    from gateway.config.network import TcpSettings
    from gateway.line.boundary import Exchange, RequestOptions
    from gateway.line.stats import LineStats
    from gateway.line.transports.inbox import Inbox
    from gateway.wire import frames
    from gateway.wire.timing import LineFormat


class RtuOverTcpLine(RtuLine):
    """One ``socket://host:port`` bus: RTU over a TCP session, the session watched."""

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
        """Describe the bus (``line`` is the converter's serial side); :meth:`open` connects."""
        super().__init__(
            port=port, line=line, stats=stats, bus=bus, echo=echo, judges_by_wire=False
        )
        parts = urlsplit(port)
        self.host = parts.hostname or ""
        self.tcp_port = parts.port or 0
        self.tcp = tcp
        self.watch = SilenceWatch(port=port, limit=tcp.silent_requests)
        self._ready_at = -math.inf  # no request before the pause after connecting

    async def _connect(self, inbox: Inbox) -> asyncio.Transport:
        """Connect, keepalive and the user timeout set; then the pause after connecting."""
        try:
            transport = await connect(
                self.port,
                self.host,
                self.tcp_port,
                inbox,
                self.tcp,
                mode="transparent (RTU over TCP)",
            )
        except BusClosedError as exc:
            self.stats.closed_because(None, str(exc))
            raise
        self._ready_at = time.monotonic() + self.tcp.connect_pause_s
        return transport

    def _lost_words(self, inbox: Inbox) -> str:
        """The converter's FIN or RST, or the user timeout, in words a plant engineer can act on."""
        return session_ended(inbox)

    def tcp_socket(self) -> TransportSocket | None:
        """The session's socket (for its options), ``None`` while closed."""
        transport = self._transport
        return transport.get_extra_info("socket") if transport is not None else None

    def _unread_input(self) -> bool:
        """Whether the kernel holds received bytes the inbox has not seen (FIONREAD)."""
        return unread_bytes(self.tcp_socket())

    async def wait_gap(self, gap_s: float, *, not_before: float = 0.0, device: int = 0) -> float:
        """The line's gap, at least ``tcp.request_pause_ms``, and not within the connect pause."""
        pause_s = self.tcp.request_pause_ms / MS_PER_S
        return await super().wait_gap(
            max(gap_s, pause_s), not_before=max(not_before, self._ready_at), device=device
        )

    async def transact(self, request: frames.Request, options: RequestOptions) -> Exchange | None:
        """:meth:`RtuLine.transact`, watched: a session silent for too many requests is reopened."""
        before = self._last_byte_at()
        try:
            exchange = await super().transact(request, options)
        except BusTimeoutError as exc:
            if self._last_byte_at() > before:
                self.watch.heard()
                raise
            ended = self.watch.unheard()
            if ended is not None:
                await self.close()
                await self.open()  # fails as a closed port does: the worker's backoff
                if type(exc) is BusTimeoutError:  # a LineNoiseError keeps its kind
                    raise BusTimeoutError(f"{exc}; {ended}") from exc
            raise
        except (FrameError, DeviceExceptionError):
            self.watch.heard()  # bytes came: a wrong answer, but from a live peer
            raise
        if exchange is not None or self._last_byte_at() > before:
            self.watch.heard()
        return exchange

    def _last_byte_at(self) -> float:
        inbox = self._inbox
        return inbox.last_byte_at if inbox is not None else -math.inf
