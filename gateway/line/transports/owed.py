"""The answer still due to a request whose transaction was cancelled once it went out.

The gateway stops waiting when a bus worker is stopped, or paused for a command; the
device does not, and its answer (with the adapter's echo ahead of it) comes all the same.
The next request on the line, sent at once, went out into that answer: the device heard a
collision, and the answer was taken for noise, or, come before the next request, counted
a stale frame of the device. So the line remembers what it owes, and its next transaction
first waits for that answer (or for the cancelled request's timeout) and keeps the gap
after it. The answer, its echo and its failure are dropped uncounted: the gateway left it,
not the device, so it is neither a stale frame nor a timeout of the device's.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

from gateway.line.transports.answer import AnswerScan

if TYPE_CHECKING:
    from gateway.line.boundary import RequestOptions
    from gateway.line.transports.inbox import Inbox
    from gateway.wire import frames


@dataclass(frozen=True, slots=True, kw_only=True)
class OwedAnswer:
    """A request sent whose answer nobody waits for any more, until the line has carried it."""

    request: frames.Request
    options: RequestOptions
    deadline: float  # the request's end on the wire plus its timeout
    inbox: Inbox  # the stream it comes on: a line closed and opened again owes nothing

    def scan(self) -> AnswerScan:
        """A look for the answer from the bytes at hand, its echo passed over if one comes."""
        return AnswerScan(
            self.request,
            exceptions=self.options.exceptions,
            byte_count_16bit=self.options.byte_count_16bit,
            echo=self.request.frame,  # not read back if the cancel came during the echo's wait
        )
