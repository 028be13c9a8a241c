"""The bytes a line has received, with when the last of them arrived, and a wait for more.

Every kind of line reads through one: the RTU lines (a serial device or a socket under an
asyncio transport) and Modbus TCP. A transaction waits on a bare future that the next
bytes, the end of the connection or a timer resolve: not an Event behind
``asyncio.wait_for``, which made a task per wait and cost two turns of the loop.
"""

from __future__ import annotations

import asyncio
import math
import time
from typing import TYPE_CHECKING, Final

if TYPE_CHECKING:
    from gateway.line.transports.timer import DeadlineTimer

# Past an answer's deadline, while the kernel holds bytes the event loop has not handed
# over: this many more passes of the loop, each waiting at most this long for them. A
# process held up (a CPU quota, a busy machine) comes back to a wait's timer and the
# answer at once, and the loop may run the timer first; the answer the port already holds
# is then taken, not counted a timeout. A line that keeps sending (noise) cannot keep a
# transaction open for longer than the passes.
LAST_LOOKS: Final = 3
LAST_LOOK_S: Final = 0.05


class Inbox(asyncio.Protocol):
    """Collects bytes from a transport with the time they arrived (the transport's protocol).

    An end of input from the peer (a converter that closes its side) is not answered: the
    transport closes ours and :meth:`connection_lost` follows.
    """

    def __init__(
        self, loop: asyncio.AbstractEventLoop | None = None, *, timer: DeadlineTimer | None = None
    ) -> None:
        """Nothing received yet; not lost. ``loop``: the one the transport runs on.

        Known, it spares each wait asking for the running loop, a system call (``getpid``,
        asyncio's check for a fork) that is dear on a virtual machine. ``timer``: the
        line's own, which ends a wait at its timeout (an RTU line's): no timer of the loop
        to set and cancel for every answer.
        """
        self.loop = loop
        self.buffer = bytearray()
        self.last_byte_at = -math.inf
        self.lost = asyncio.Event()
        # ``lost`` as a plain flag, for the looks of every transaction (a method call less)
        self.gone = False
        self.lost_reason: Exception | None = None
        self.peer_closed = False  # the peer ended its side (a FIN) before the stream ended
        self._waiter: asyncio.Future[None] | None = None
        self.timer = timer

    def data_received(self, data: bytes) -> None:
        """Keep the bytes, note when they came, wake a waiting transaction."""
        self.buffer.extend(data)
        self.last_byte_at = time.monotonic()
        self._wake()

    def eof_received(self) -> None:
        """The peer closed its side: noted for :meth:`why_lost`; the transport closes ours.

        Without the note a converter's FIN ended the stream with no reason at all, and the
        line said it "went away: None".
        """
        self.peer_closed = True

    def why_lost(self) -> str:
        """Why the stream ended, in words: the error that ended it, or the peer's close."""
        reason = self.lost_reason
        if reason is not None:
            return str(reason) or type(reason).__name__
        return "the other end closed it" if self.peer_closed else "it was closed"

    def connection_lost(self, exc: Exception | None) -> None:
        """The stream ended (``exc``: why, if it failed); a waiting transaction wakes to it."""
        self.lost_reason = exc
        self.gone = True
        self.lost.set()
        self._wake()

    def _wake(self) -> None:
        waiter = self._waiter
        if waiter is not None and not waiter.done():
            waiter.set_result(None)

    async def wait(self, timeout_s: float) -> None:
        """Return when bytes arrive, the connection ends, or after ``timeout_s``.

        On the line's own timer where it has one (:attr:`timer`; it may end the wait
        sooner, to look for the loop's watch), else on a timer of the loop.
        """
        loop = self.loop or asyncio.get_running_loop()
        waiter = self._waiter = loop.create_future()
        own = self.timer
        if own is not None:
            now = time.monotonic()
            if not own.wake(waiter, now + timeout_s, now):
                own = None  # no timerfd here, or another wait holds it
        handle = loop.call_later(timeout_s, self._wake) if own is None else None
        try:
            await waiter
        finally:
            if own is not None:
                own.unwake(waiter)
            elif handle is not None:
                handle.cancel()
            self._waiter = None
