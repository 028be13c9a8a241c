"""The boundary of a line: what the rest of the bus may ask of any kind of line.

The bus worker, the transactions, the scan, the shared bus and lateness see a line only
through :class:`Line`, and a transaction's result as an :class:`Exchange`.

Three kinds stand behind it, each owning only what is its own
(:func:`gateway.line.transports.factory.build_line` picks one from the port):

- :class:`gateway.line.transports.serial_line.SerialLine`: Modbus RTU on a local serial device (the
  echo of a two-wire adapter, the wire-time floor, exclusive opening);
- :class:`gateway.line.transports.rtu_over_tcp.RtuOverTcpLine`: the same RTU frames through a serial
  device server's transparent TCP port (``socket://``), its session watched;
- :class:`gateway.line.transports.modbus_tcp.ModbusTcpLine`: Modbus TCP to a converter (``tcp://``),
  MBAP framing and transaction ids, no gap on the socket.

The first two share the RTU engine, :class:`gateway.line.transports.rtu.RtuLine`; the third shares
nothing but this protocol, the counters (:mod:`gateway.line.stats`) and the timer.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Protocol

from gateway.wire import frames

if TYPE_CHECKING:
    from collections.abc import Mapping

    from gateway.line.stats import LineStats
    from gateway.wire.timing import LineFormat


class WaitWatch(Protocol):
    """Told of the line's timed waits: the event loop's watch (``line/engine/lateness``)."""

    @property
    def look_s(self) -> float:
        """How far ahead a line's timer is set while it looks for the watch."""

    def asleep(self) -> None:
        """A timed wait begins."""

    def awake(self, due: float, now: float) -> None:
        """The timed wait due at ``due`` ended at ``now``."""

    def late(self, due: float, now: float) -> None:
        """A line's timer looking for the watch, due at ``due``, fired at ``now``."""


@dataclass(frozen=True, slots=True, kw_only=True)
class LateAnswer:
    """A device's own answer that came after its request had timed out."""

    device: int
    after_s: float  # from sending the request to the answer's last byte
    timeout_s: float  # the response timeout
    waited_s: float  # from sending to giving up: the request's wire time and the timeout


@dataclass(slots=True, kw_only=True)
class RequestOptions:
    """How one request goes out and its answer is read, on any kind of line.

    ``gap_s`` is the silence the line keeps before the request (where the line has one to
    keep), ``not_before`` the earliest time it may go out (a post-write wait, a late
    answer's window), ``timeout_s`` how long the answer may take once the request is on the
    wire, ``turnaround_s`` the least time the device takes to answer (a converter times its
    serial side itself and ignores it); ``exceptions`` names the device's exception codes
    and ``byte_count_16bit`` is a profile's quirk for string reads. Not frozen: a device's
    options are kept per kind of request and ``not_before`` set for each one (a line carries
    one transaction at a time and none keeps its options past it).
    """

    timeout_s: float
    gap_s: float
    not_before: float = 0.0
    exceptions: Mapping[int, str] = field(default_factory=lambda: frames.STANDARD_EXCEPTIONS)
    byte_count_16bit: bool = False
    turnaround_s: float = 0.0


@dataclass(frozen=True, slots=True, kw_only=True)
class Exchange:
    """A completed transaction: the response and when it happened on the wire."""

    response: frames.Response
    sent_at: float
    received_at: float


class Line(Protocol):
    """One bus's line, whatever carries it: one strict transaction at a time.

    ``port`` is the configured port (a device path or a URL), ``format`` the RS485 line's
    (behind a converter, its serial side), ``stats`` the line's counters. ``late_answer``
    is set when a device's answer came after its request timed out (the transactions take
    it and say how late); ``wait_watch`` is told of the line's timed waits while a worker
    runs, and :meth:`rest` ends them.
    """

    port: str
    format: LineFormat
    stats: LineStats
    late_answer: LateAnswer | None
    wait_watch: WaitWatch | None

    @property
    def is_open(self) -> bool:
        """Whether the line is open and has not been lost."""

    async def open(self) -> None:
        """Open the line; one that cannot be opened raises a ``BusClosedError``."""

    def rest(self) -> None:
        """The worker sleeps on a timer of its own, or stops: the line stops looking for it.

        A line whose timer is the loop watch's look (``wait_watch``) disarms it; the next
        wait of a transaction looks again.
        """

    async def close(self) -> None:
        """Close the line (idempotent); back once its resources are released."""

    async def transact(self, request: frames.Request, options: RequestOptions) -> Exchange | None:
        """Send ``request`` when the line allows and return its answer (``None``: broadcast).

        Failures raise the :mod:`gateway.errors` of a transaction, each counted by kind in
        :attr:`stats`.
        """
