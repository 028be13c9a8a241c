"""One line's transactions: each request and its answer under every timing rule of the manuals.

The response timeout is the answer's wire time plus the device's processing time (t1); the
inter-frame gap is 3.5 characters or the device's larger minimum; after a write the device's
post-write wait holds, answered or not. After no answer of its own a device gets nothing for
a late-answer window, so a late answer is flushed as stale rather than taken for the next
request's. A failed read is retried later, not at once, so one bad device never holds up the
others; a block the device refuses with exception 02 is read point by point, and a point it
refuses alone is no longer polled.
"""

from __future__ import annotations

import asyncio
import logging
import math
import time
from typing import TYPE_CHECKING, Final

from gateway.errors import (
    BusTimeoutError,
    ConverterNoAnswerError,
    ConverterPathError,
    CrcError,
    DeviceExceptionError,
    EchoMismatchError,
    FrameError,
    LineNoiseError,
    MalformedFrameError,
    UnexpectedDeviceError,
)
from gateway.line.boundary import RequestOptions
from gateway.line.engine.read_plans import ReadPlans
from gateway.line.engine.register_cache import RegisterCache
from gateway.line.engine.requests import MIN_RESPONSE_TIME_MAX_S, DeviceRequests
from gateway.wire import frames

if TYPE_CHECKING:
    from collections.abc import Callable, Mapping, Sequence

    from gateway.line.boundary import Line
    from gateway.line.engine.decode import Decoder
    from gateway.line.engine.devices import DeviceState
    from gateway.line.engine.health import Availability
    from gateway.line.engine.plan import ReadBlock
    from gateway.line.samples import Sample
    from gateway.profiles import Point

_LOGGER = logging.getLogger(__name__)

LATE_ANSWER_WINDOW_S: Final = 1.0  # after no answer of its own, a device's late one may come
BROADCAST_TURNAROUND_S: Final = 0.1  # Modbus over serial line 2.4.1: 100-200 ms after broadcasts

_FAILURE_NAMES: Final[dict[type[Exception], str]] = {
    BusTimeoutError: "timeout",
    CrcError: "crc_error",
    UnexpectedDeviceError: "wrong_address",
    MalformedFrameError: "malformed_answer",
    EchoMismatchError: "echo_mismatch",
    LineNoiseError: "no_silence",
    ConverterPathError: ConverterPathError.kind,  # Modbus TCP converters' 0A and 0B
    ConverterNoAnswerError: ConverterNoAnswerError.kind,
}


def learning_wait(state: DeviceState, block: ReadBlock) -> float | None:
    """The wait for a read of the device's minimum response time register itself.

    Until the device has said its own, the read of it waits the manual's longest (500
    ms): a sensor set slower than the config says would otherwise time out on every
    read, that one included, and never be heard. Every other read waits as configured.
    """
    learn = state.target.min_response_point
    if learn is None or learn.name in state.values or learn not in block.points:
        return None
    return MIN_RESPONSE_TIME_MAX_S


class Transactions:
    """Reads, writes, probes and broadcasts on one line, one transaction at a time."""

    def __init__(
        self,
        *,
        bus: str,
        line: Line,
        devices: Mapping[str, DeviceState],
        availability: Availability,
        decoder: Decoder,
        late_answer_window_s: float = LATE_ANSWER_WINDOW_S,
    ) -> None:
        """Transact on ``line`` with ``devices``; answers and failures go to ``availability``."""
        self.bus = bus
        self.line = line
        self.devices = devices
        self.availability = availability
        self.decoder = decoder
        self.late_answer_window_s = late_answer_window_s
        self.plans = ReadPlans(line.format)  # which reads cover which points, per device
        self.requests = DeviceRequests(line.format)  # each device's requests and their options
        self._by_address: dict[int, DeviceState] = {}
        for state in devices.values():
            self.add(state)
        # What each device last answered, for other masters' reads (off unless asked for).
        self.cache = RegisterCache()

    def add(self, state: DeviceState) -> None:
        """Plan the reads of a device (at the start, or one a reload added or re-planned)."""
        self.plans.add(state)
        self._by_address[state.target.address] = state

    def remove(self, state: DeviceState) -> None:
        """Forget a device a reload removed or re-plans: its plans, waits and registers."""
        name = state.target.name
        self.plans.remove(state)
        self.requests.remove(state)
        if self._by_address.get(state.target.address) is state:
            del self._by_address[state.target.address]
        self.cache.drop(name)

    def use_line(self, line: Line) -> None:
        """Another line, maybe of another format (a reload): every plan and wait anew."""
        self.line = line
        self.plans.use_format(line.format)
        self.requests.use_format(line.format)
        for state in self.devices.values():
            self.add(state)

    async def transact(
        self,
        state: DeviceState,
        request: frames.Request,
        response_bytes: int,
        *,
        min_response_s: float | None = None,
    ) -> frames.Response:
        """One transaction with the device; after no answer of its own, its late-answer window.

        A timeout, only noise, or only another device's frame: the device's own answer has
        not come and may still come late. Nothing more goes to the device for the window, so
        that answer is flushed as stale instead of taken for the next request's (the soak
        found noise, then the answer 0.3 s late, taken as the immediate retry's answer, and
        the next request sent over the retry's real answer). A corrupted answer of its own
        (CRC) is the device's answer: nothing more is to come.
        """
        try:
            exchange = await self.line.transact(
                request, self.requests.options(state, response_bytes, min_response_s)
            )
        except LineNoiseError:
            raise  # nothing was sent: no answer can come late
        except (
            BusTimeoutError,
            MalformedFrameError,
            UnexpectedDeviceError,
            EchoMismatchError,
        ):
            window_end = time.monotonic() + self.late_answer_window_s
            state.holds.hold_until(window_end)
            raise
        finally:
            if self.line.late_answer is not None:
                self._late_answer_hint()
        assert exchange is not None  # noqa: S101 - unicast requests always have an answer
        return exchange.response

    def _late_answer_hint(self) -> None:
        """A device answered after its timeout: say once how late, and what to change."""
        late, self.line.late_answer = self.line.late_answer, None
        state = self._by_address.get(late.device) if late is not None else None
        if late is None or state is None or state.holds.late_hint_given:
            return
        state.holds.late_hint_given = True
        name = state.target.name
        after_ms = late.after_s * 1000
        suggestion = math.ceil(late.after_s * 1.5 * 10) / 10  # half as much again, in 0.1 s
        point = state.target.min_response_point
        reported = state.values.get(point.name) if point is not None else None
        told = (
            f" It reports a minimum response time of {reported} ms (register "
            f"{point.address:#06x}); set `min_response_time_ms: {reported}` for the device, or"
            if point is not None and isinstance(reported, int)
            else " Set"
        )
        _LOGGER.warning(
            "%s/%s: an answer came %.0f ms after its request, %.0f ms after the gateway "
            "had given up waiting (timeout %.0f ms), and was discarded as stale: the "
            "timeout is too short for this device.%s `timeout: %.1f` for device %s in the "
            "config",
            self.bus,
            name,
            after_ms,
            after_ms - late.waited_s * 1000,
            late.timeout_s * 1000,
            told,
            suggestion,
            name,
        )

    async def read_plan(
        self,
        state: DeviceState,
        blocks: Sequence[ReadBlock],
        *,
        yield_to_values: Callable[[], bool] | None = None,
    ) -> list[Sample]:
        """Read a poll's ``blocks`` in order; the samples of those read.

        Stops where a failure set the device a wait or took it offline (other devices go
        first), and, after the first block, wherever ``yield_to_values`` says values are due
        elsewhere (diagnostics fill only the time values leave free).
        """
        samples: list[Sample] = []
        for block in blocks:
            if state.holds.not_before > time.monotonic() or state.presence.online is False:
                break
            if samples and yield_to_values is not None and yield_to_values():
                break
            samples.extend(await self.read_block(state, block) or ())
        return samples

    async def read_block(self, state: DeviceState, block: ReadBlock) -> list[Sample] | None:
        """Read one block; ``None`` when it will be retried later.

        Every failed transaction counts towards taking the device offline; any answer,
        an exception included, shows it is there.
        """
        request = self.requests.read(state, block)
        try:
            response = await self.transact(
                state, request, 5 + 2 * block.count, min_response_s=learning_wait(state, block)
            )
        except DeviceExceptionError as exc:
            await self.availability.answered(state, "answered")
            if exc.code == frames.ILLEGAL_ADDRESS and len(block.points) > 1:
                state.holds.split_before.update(p.address for p in block.points[1:])
                _LOGGER.info(
                    "%s/%s: exception 02 for %d registers at %#06x; reading its points apart",
                    self.bus,
                    state.target.name,
                    block.count,
                    block.address,
                )
                return None
            if exc.code == frames.ILLEGAL_ADDRESS:
                point = block.points[0]
                state.holds.unreadable.add(point.name)
                state.deadlines.changed()  # the schedule skips it from now on
                _LOGGER.warning(
                    "%s/%s: the device does not answer %s (%#06x): exception 02; no longer polled",
                    self.bus,
                    state.target.name,
                    point.name,
                    point.address,
                )
            return self.decoder.failed(state, block, f"exception_{exc.code:02d}")
        except (BusTimeoutError, FrameError) as exc:
            await self.availability.failed(state, str(exc))
            if state.presence.online is not False and self._retry(state, block):
                return None
            _LOGGER.debug("%s/%s: %s", self.bus, state.target.name, exc)
            return self.decoder.failed(state, block, _FAILURE_NAMES.get(type(exc), "comms_error"))
        if not self.availability.answered_online(state):
            await self.availability.answered(state, "answered")
        if state.holds.attempts:  # only after a failure: nearly every read has nothing to forget
            for point in block.points:
                state.holds.attempts.pop(point.name, None)
        if self.cache.enabled:
            self.cache.store(state.target.name, block.address, response.registers, time.monotonic())
        return self.decoder.decode(state, block, response.registers)

    def _retry(self, state: DeviceState, block: ReadBlock) -> bool:
        names = [p.name for p in block.points]
        attempts = max(state.holds.attempts[n] for n in names) + 1
        if attempts > state.target.retries:
            for name in names:
                state.holds.attempts.pop(name, None)
            return False
        for name in names:
            state.holds.attempts[name] = attempts
        self.line.stats.retries[state.target.address] += 1
        return True

    async def read_now(self, state: DeviceState, points: Sequence[Point]) -> list[Sample]:
        """Read points (resolved where their names came in), waiting and retrying inline."""
        samples: dict[str, Sample] = {}
        todo = list(points)
        learn = state.target.min_response_point
        if (
            learn is not None
            and learn.name not in state.values
            and learn.name not in state.holds.unreadable
            and learn not in todo
        ):
            # The device's own minimum response time first (once, see ``plan_points``),
            # so the reads that follow wait as long as it takes to answer.
            todo.append(learn)
        while todo:
            blocks = self.plans.plan_points(state, todo)
            todo = []
            for block in blocks:
                delay = state.holds.not_before - time.monotonic()
                if delay > 0:
                    await asyncio.sleep(delay)
                outcome = await self.read_block(state, block)
                if outcome is None:
                    todo.extend(block.points)
                else:
                    samples.update((s.point, s) for s in outcome)
        return [samples[p.name] for p in points if p.name in samples]

    async def read_all(self, state: DeviceState) -> list[Sample]:
        """Read every point of the device, the unit and float-format registers first."""
        profile = state.profile
        points = [profile.point(name) for name in state.target.intervals]
        needed = {u for p in points if (u := p.unit_from) is not None}
        if profile.float_order_register is not None and state.target.float_order is None:
            needed.add(profile.float_order_register.point)
        if state.target.min_response_point is not None:
            needed.add(state.target.min_response_point.name)
        if needed:
            await self.read_now(state, [profile.point(name) for name in sorted(needed)])
        return await self.read_now(state, points)

    async def probe(self, state: DeviceState, now: float) -> None:
        """One small read of an offline device; on success it is polled in full again."""
        names = list(state.target.intervals) or [state.profile.points[0].name]
        block = self.plans.plan(state, names[:1])[0]
        request = self.requests.read(state, block)
        try:
            await self.transact(state, request, 5 + 2 * block.count)
        except DeviceExceptionError:
            pass  # an exception is an answer: the device is there
        except (BusTimeoutError, FrameError):
            self.availability.probe_unanswered(state, now)
            return
        await self.availability.probe_answered(state)

    async def write(
        self, state: DeviceState, point: Point, request: frames.Request
    ) -> frames.Response:
        """Send a write; the device's post-write wait follows, answered or not."""
        self.cache.forget(state.target.name, request.address, request.count)
        try:
            return await self.transact(state, request, 8)
        finally:
            # H10/H20 6.1.5: the wait follows every write, answered or not.
            wait = state.profile.post_write_wait(point.address, point.count)
            state.holds.hold_until(time.monotonic() + wait)

    async def broadcast(self, request: frames.Request) -> None:
        """Send a broadcast; then every device waits the turnaround or its post-write wait."""
        gap = max(
            (self.requests.gap_s(s) for s in self.devices.values()),
            default=self.line.format.frame_gap_s(),
        )
        await self.line.transact(request, RequestOptions(timeout_s=0.0, gap_s=gap))
        sent = time.monotonic()
        for state in self.devices.values():
            wait = max(
                BROADCAST_TURNAROUND_S,
                state.profile.post_write_wait(request.address, request.count),
            )
            state.holds.hold_until(sent + wait)
