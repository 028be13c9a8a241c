"""Each device's requests on one line and the options they go out with, built once.

A read of the same block is the same frame every time, and its timeout, the device's gap
and its quirks change only with the device's target or the line: they are made at the
first request and kept (building a request through pymodbus costs more than the rest of
a read). The one thing that changes between two requests is the device's wait
(``Holds.not_before``) and what it reported of its minimum response time.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Final

from gateway.line.boundary import RequestOptions
from gateway.wire import encoding, frames

if TYPE_CHECKING:
    from gateway.line.engine.devices import DeviceState, DeviceTarget
    from gateway.line.engine.plan import ReadBlock
    from gateway.profiles import Point
    from gateway.wire.timing import LineFormat

RESPONSE_MARGIN_S: Final = 0.05  # USB adapters and the event loop add a few ms either way
# digiLine 0x0305: the minimum response time is 0-500 ms (S10 and H10 manuals, interface
# settings). Until a sensor has said its own, the gateway waits as if it were the longest.
MIN_RESPONSE_TIME_MAX_S: Final = 0.5


def default_timeout_s(
    target: DeviceTarget, response_bytes: int, wire_s: float, *, min_response_s: float | None = None
) -> float:
    """Response timeout: the answer's wire time plus t1 (digiLine: 25 ms + min. response time).

    ``min_response_s`` is the device's minimum response time as it reported it (its
    register), where it did; the configured one otherwise. A configured timeout wins.
    """
    if target.timeout_s is not None:
        return target.timeout_s
    if min_response_s is None:
        min_response_s = target.min_response_time_s
    t1 = target.profile.timing.processing_time_s + max(target.min_response_time_s, min_response_s)
    return wire_s * response_bytes + t1 + RESPONSE_MARGIN_S


def reported_min_response_s(state: DeviceState) -> float | None:
    """The minimum response time the device reports in its register, once read.

    ``None``: the profile has no such register, the device refuses it, or it has not
    been read yet (the read of it waits the manual's longest, see :meth:`Transactions.read_block`).
    """
    point = state.target.min_response_point
    if point is None:
        return None
    value = state.values.get(point.name)
    if isinstance(value, int) and not isinstance(value, bool):
        return min(max(value, 0) / 1000, MIN_RESPONSE_TIME_MAX_S)
    return None


class DeviceRequests:
    """The requests of each device of one line, and the options of each transaction."""

    def __init__(self, line_format: LineFormat) -> None:
        """Requests for a line of ``line_format``."""
        self.line_format = line_format
        # Read requests by (device, address, count): the same few blocks are asked again
        # and again, and building one through pymodbus costs more than the rest of a read.
        self._reads: dict[tuple[int, int, int], frames.Request] = {}
        self._gaps: dict[str, float] = {}
        self._timeouts: dict[tuple[str, int, float | None], float] = {}
        # The options of each device's kind of request (its name, the answer's length, the
        # stand-in and the reported minimum response time): the same few, over and over.
        self._options: dict[tuple[str, int, float | None, float | None], RequestOptions] = {}

    def use_format(self, line_format: LineFormat) -> None:
        """Another line, maybe of another format (a reload): every wait anew."""
        self.line_format = line_format
        self._reads.clear()
        self._gaps.clear()
        self._timeouts.clear()
        self._options.clear()

    def remove(self, state: DeviceState) -> None:
        """Forget a device a reload removed or re-plans: its waits and timeouts."""
        name = state.target.name
        self._gaps.pop(name, None)
        self._timeouts = {key: t for key, t in self._timeouts.items() if key[0] != name}
        self._options = {key: o for key, o in self._options.items() if key[0] != name}

    def options(
        self, state: DeviceState, response_bytes: int, min_response_s: float | None = None
    ) -> RequestOptions:
        """How a request to the device goes out now: its timeout, gap, wait and quirks.

        ``min_response_s`` stands in for the device's minimum response time until it has
        reported its own (``None``: the configured one).
        """
        # The least time the device takes to answer is what it reported, once it has: not
        # the configured value, not the manual's longest. An answer refused as too early
        # must never be the device's own.
        reported = reported_min_response_s(state)
        key = (state.target.name, response_bytes, min_response_s, reported)
        options = self._options.get(key)
        if options is None:  # cleared when the target or the line changes
            profile = state.target.profile
            options = self._options[key] = RequestOptions(
                timeout_s=self.timeout_for(
                    state, response_bytes, min_response_s if reported is None else reported
                ),
                gap_s=self.gap_s(state),
                exceptions=profile.exceptions,
                byte_count_16bit=profile.quirks.string_byte_count_16bit,
                turnaround_s=0.0 if reported is None else reported,
            )
        # The one field that moves (a post-write wait, a late answer's window): set for
        # this request. A line carries one transaction at a time, and none keeps its
        # options past it.
        options.not_before = state.holds.not_before
        return options

    def timeout_for(
        self, state: DeviceState, response_bytes: int, min_response_s: float | None
    ) -> float:
        """How long to wait for an answer of ``response_bytes`` from the device.

        ``min_response_s``: its minimum response time as reported, or what stands in for
        it until then (``None``: the configured one).
        """
        key = (state.target.name, response_bytes, min_response_s)
        timeout = self._timeouts.get(key)
        if timeout is None:  # cleared when the target or the line changes
            timeout = default_timeout_s(
                state.target,
                response_bytes,
                self.line_format.character_s,
                min_response_s=min_response_s,
            )
            self._timeouts[key] = timeout
        return timeout

    def gap_s(self, state: DeviceState) -> float:
        """The silence the device needs before a request."""
        gap = self._gaps.get(state.target.name)
        if gap is None:
            gap = self.line_format.frame_gap_s(
                max(state.profile.timing.min_gap_s, state.target.extra_gap_s)
            )
            self._gaps[state.target.name] = gap
        return gap

    def read(self, state: DeviceState, block: ReadBlock) -> frames.Request:
        """The request that reads ``block`` (built once, then reused: requests are values)."""
        key = (state.target.address, block.address, block.count)
        request = self._reads.get(key)
        if request is None:
            request = frames.read_request(*key)
            self._reads[key] = request
        return request

    @staticmethod
    def write(
        state: DeviceState, point: Point, *, value: object, registers: tuple[int, ...] | None
    ) -> frames.Request:
        """The request that writes ``registers``, or ``value`` encoded (an :class:`EncodeError`)."""
        if registers is None:
            registers = encoding.encode(point.format, value, float_order=state.float_order)
        return frames.write_request(state.target.address, point.address, registers)
