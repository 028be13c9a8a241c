"""One client's socket: bytes read only as the server asks for them, answers out, a hard close.

asyncio's streams read ahead on their own (up to 256 KiB a time, and more until their
buffer passes twice its limit): a client that pipelines thousands of requests gets them
all taken in, however slowly they are answered. This protocol reads only when the server
asks, into a buffer the size the server gives, so what a connection holds is bounded and
a pipelining client waits in TCP's buffers (backpressure).

Closing is the other half. ``close()`` waits until every queued answer is sent, which a
client that does not read never allows: its socket stays open with megabytes queued.
:meth:`ClientConnection.abort` drops the queue and resets the connection (``SO_LINGER``
0, so not even the kernel keeps it), and :meth:`ClientConnection.gone` says when the
socket is really closed.
"""

from __future__ import annotations

import asyncio
import contextlib
import socket
import struct
from typing import TYPE_CHECKING, Final

if TYPE_CHECKING:
    from collections.abc import Callable

_LINGER_RESET: Final = struct.pack("ii", 1, 0)  # on, 0 s: close() sends RST, keeps nothing
DISCARD_CHUNK: Final = 4096  # what a closing connection reads (and drops) at a time


class ClientConnection(asyncio.BufferedProtocol):
    """One connection's socket, read on demand: :meth:`receive`, :meth:`send`, :meth:`abort`."""

    def __init__(self, on_open: Callable[[ClientConnection], None]) -> None:
        """``on_open`` gets the connection once its socket is there (and starts serving it)."""
        self._on_open = on_open
        self.transport: asyncio.Transport | None = None
        self.peer: tuple[str, int] = ("?", 0)
        self._chunk = bytearray()
        self._received = bytearray()
        self._arrived: asyncio.Event = asyncio.Event()
        self._writable = asyncio.Event()
        self._writable.set()
        self._eof = False
        self._discarding = False  # closing: what the client still sends is dropped
        self._gone: asyncio.Future[None] = asyncio.get_running_loop().create_future()

    # --- asyncio's side -------------------------------------------------------------------

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        """Read nothing until the server asks."""
        assert isinstance(transport, asyncio.Transport)  # noqa: S101 - a TCP server's
        self.transport = transport
        transport.pause_reading()
        peer = transport.get_extra_info("peername") or ("?", 0)
        self.peer = (str(peer[0]), int(peer[1]))
        self._on_open(self)

    def get_buffer(self, sizehint: int) -> bytearray:  # noqa: ARG002 - the server's size rules
        """The room the server gave for this read."""
        return self._chunk

    def buffer_updated(self, nbytes: int) -> None:
        """Keep what arrived; read no more until the server asks again."""
        if self._discarding:
            return
        self._received += self._chunk[:nbytes]
        if self.transport is not None and not self.transport.is_closing():
            self.transport.pause_reading()
        self._arrived.set()

    def eof_received(self) -> bool:
        """The client sent its last byte; it may still read the answers to what it sent.

        Kept open (``True``) for them, unless we are closing and waited for just this.
        """
        self._eof = True
        self._arrived.set()
        return not self._discarding

    def connection_lost(self, exc: Exception | None) -> None:  # noqa: ARG002 - told as EOF
        """The socket is closed: wake whoever waits on it."""
        self._eof = True
        self._arrived.set()
        self._writable.set()
        if not self._gone.done():
            self._gone.set_result(None)

    def pause_writing(self) -> None:
        """The client reads slower than answers come: :meth:`send` waits."""
        self._writable.clear()

    def resume_writing(self) -> None:
        """The client read: answers may go again."""
        self._writable.set()

    # --- the server's side ----------------------------------------------------------------

    async def receive(self, max_bytes: int) -> bytes:
        """Up to ``max_bytes`` from the socket (one read), waiting for them; ``b""`` at EOF."""
        if not self._received and not self._eof:
            self._chunk = bytearray(max_bytes)
            self._arrived.clear()
            assert self.transport is not None  # noqa: S101 - made before the server runs
            self.transport.resume_reading()
            await self._arrived.wait()
        data = bytes(self._received)
        self._received.clear()
        return data

    async def send(self, data: bytes) -> None:
        """Queue an answer; wait while the client lets answers pile up unread."""
        assert self.transport is not None  # noqa: S101 - made before the server runs
        if self.transport.is_closing():
            raise ConnectionResetError("the connection is closed")
        self.transport.write(data)
        await self._writable.wait()
        if self.transport.is_closing() and self._gone.done():
            raise ConnectionResetError("the connection was lost")

    def close(self) -> None:
        """Close at once, nothing sent (a connection refused before it is served)."""
        if self.transport is not None:
            self.transport.close()

    async def finish(self) -> None:
        """Send what is queued, then our end of the stream; wait for the client's end.

        What the client still sends meanwhile is read and dropped: a socket closed with
        bytes unread resets the connection, where a client that reads is owed an end.
        """
        transport = self.transport
        if transport is not None and self._eof:
            transport.close()  # the client ended first: ours follows what is queued
        elif transport is not None and not transport.is_closing():
            try:
                transport.write_eof()
            except OSError:  # the client reset it meanwhile: nothing to end
                transport.abort()
                return
            self._discarding = True
            self._chunk = bytearray(DISCARD_CHUNK)
            transport.resume_reading()
        await self.gone()

    def abort(self) -> None:
        """Drop what is queued and reset: nothing of the connection stays, here or in the kernel."""
        if self.transport is None:
            return
        sock = self.transport.get_extra_info("socket")
        if sock is not None:
            with contextlib.suppress(OSError):
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, _LINGER_RESET)
        self.transport.abort()

    def when_gone(self, callback: Callable[[ClientConnection], object]) -> None:
        """Call ``callback`` with this connection once its socket is closed."""
        self._gone.add_done_callback(lambda _: callback(self))

    async def gone(self) -> None:
        """Wait until the socket is closed (``connection_lost``)."""
        await asyncio.shield(self._gone)
