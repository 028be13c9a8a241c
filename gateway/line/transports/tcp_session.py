"""Sessions with serial device servers: connecting, keepalive, user timeout, silence.

A converter on the network can vanish without a word (powered off, a cable pulled, a
firewall that forgets the connection); Linux keeps such a session for some 15 minutes of
retransmissions, or for ever while nothing is sent. TCP keepalive ends it while the line
is idle and TCP_USER_TIMEOUT while requests go unacknowledged (tcp(7)), both within the
bounds of ``buses[].tcp``. A converter that stays connected but answers nothing (its
serial side hung, a session it no longer serves) is found by :class:`SilenceWatch`:
requests in a row without a byte back end the session, which is opened again at once.

Both network lines use this module: :class:`gateway.line.transports.rtu_over_tcp.RtuOverTcpLine`
(``socket://``, RTU frames through the converter) and
:class:`gateway.line.transports.modbus_tcp.ModbusTcpLine` (``tcp://``, Modbus TCP).
"""

from __future__ import annotations

import array
import asyncio
import errno
import fcntl
import logging
import os
import socket
import termios
import time
from typing import TYPE_CHECKING, Final

from gateway.errors import BusClosedError

if TYPE_CHECKING:
    from asyncio.trsock import TransportSocket

    from gateway.config.network import TcpSettings
    from gateway.line.transports.inbox import Inbox

_LOGGER = logging.getLogger(__name__)

MS_PER_S: Final = 1000  # TCP_USER_TIMEOUT is in milliseconds (tcp(7))


async def connect(
    url: str, host: str, port: int, inbox: Inbox, settings: TcpSettings, *, mode: str
) -> asyncio.Transport:
    """A session to ``host:port`` with ``inbox`` as its protocol, keepalive and user timeout set.

    A failure is a :class:`BusClosedError` in a user's words; ``mode`` names the converter's
    mode its port must be in ("Modbus TCP", "transparent (RTU over TCP)").
    """
    loop = asyncio.get_running_loop()
    limit_s = settings.connect_timeout_s
    try:
        async with asyncio.timeout(limit_s):
            transport, _ = await loop.create_connection(lambda: inbox, host, port)
    except TimeoutError as exc:
        raise BusClosedError(
            f"cannot connect to {url}: no answer within {limit_s:g} s (tcp.connect_timeout_s)"
        ) from exc
    except OSError as exc:
        raise BusClosedError(f"cannot connect to {url}: {_reason(exc, mode)}") from exc
    configure_socket(transport.get_extra_info("socket"), settings)
    return transport


def _reason(exc: OSError, mode: str) -> str:
    """Why a connection failed, in the words a user can act on."""
    if exc.errno == errno.ECONNREFUSED:
        return (
            "connection refused (nothing listens there: check the converter's address, "
            f"its port and that it is in {mode} mode)"
        )
    if exc.errno is not None and exc.errno > 0:
        return os.strerror(exc.errno)
    return exc.strerror or str(exc)  # a name that does not resolve: the resolver's words


def unread_bytes(sock: socket.socket | TransportSocket | None) -> bool:
    """Whether the kernel holds received bytes that the event loop has not read (FIONREAD).

    One ioctl, no read: the bytes stay for the transport, which hands them over in the
    loop's next pass. A closed socket holds none.
    """
    if sock is None:
        return False
    waiting = array.array("i", [0])
    try:
        fcntl.ioctl(sock.fileno(), termios.FIONREAD, waiting)
    except (OSError, ValueError):
        return False  # closed meanwhile: the write or the inbox will say so
    return waiting[0] > 0


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


def session_ended(inbox: Inbox) -> str:
    """Why a converter's session ended and what to check, in a plant engineer's words.

    The stream's own words were a programmer's: ``[Errno 104] Connection reset by peer``,
    and for a converter's orderly close nothing at all (the line said "went away: None").
    """
    reason = inbox.lost_reason
    if isinstance(reason, TimeoutError):
        return (
            "the converter stopped acknowledging what was sent (tcp.user_timeout_s): it "
            "lost power, a cable is out, or the network between is down"
        )
    if isinstance(reason, ConnectionResetError):
        what = "the converter reset the connection (RST)"
    elif reason is None and inbox.peer_closed:
        what = "the converter closed the connection"
    else:
        return inbox.why_lost()
    return (
        f"{what}; it is opened again. If this repeats, check that no other client (a "
        "second gateway, a configuration tool, a SCADA) takes the converter's connection, "
        "and the converter's limit of connections and its idle timeout"
    )


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

    def unheard(self) -> str | None:
        """A request got no byte back; why the session is to be ended now, else ``None``.

        The words go into the failure of the request that ends it as well as the log: a
        device's offline reason that said only "no answer" left a session the converter
        no longer serves looking like a sensor fault.
        """
        self.silent += 1
        if not self.limit or self.silent < self.limit:
            return None
        message = (
            f"no byte back for {self.silent} requests in a row: the converter keeps the "
            "connection open but answers nothing (or no device behind it answers); the "
            f"connection is closed and opened again (tcp.silent_requests: {self.limit}). "
            "If this repeats, restart the converter (it may hold a dead session of its "
            "own) and check its serial side: the wiring, the baud rate and parity set as "
            "the bus's, and the devices' power"
        )
        log = _LOGGER.warning if not self.reopened else _LOGGER.debug
        log("%s: %s", self.port, message)
        self.silent = 0
        self.reopened += 1
        self.ended_at.append(time.monotonic())
        return message
