"""Polling one line: what is due when, in which order, and what happens when it fails.

Every point has a monotonic deadline (``next += interval``); missed deadlines are counted
and skipped, never piled up. At each step the worker serves pending writes first, then
the device with the earliest due deadline (fair between devices), as long as the device
is not inside a post-write wait or a late-answer quarantine. A failed request is retried
later rather than at once, so one bad device never holds up the others; a device that
keeps failing goes offline and is probed on a capped, jittered backoff.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import random
import time
from collections import Counter
from dataclasses import dataclass, field
from datetime import UTC, datetime
from typing import TYPE_CHECKING, Final, TypeAlias

from gateway.errors import (
    BusClosedError,
    BusTimeoutError,
    CrcError,
    DecodeError,
    DeviceExceptionError,
    EncodeError,
    FrameError,
    GatewayError,
    MalformedFrameError,
    UnexpectedDeviceError,
)
from gateway.line.health import DeviceHealth
from gateway.line.plan import CostModel, Planner, ReadBlock
from gateway.line.samples import DeviceEvent, Quality, Sample, hex_registers
from gateway.profiles import PollGroup
from gateway.wire import codec, frames

if TYPE_CHECKING:
    from collections.abc import Mapping, Sequence

    from gateway.line.port import Line
    from gateway.line.samples import Sink
    from gateway.profiles import Point, Profile

_LOGGER = logging.getLogger(__name__)

RESPONSE_MARGIN_S: Final = 0.05  # USB adapters and the event loop add a few ms either way
LATE_ANSWER_WINDOW_S: Final = 1.0  # after no answer of its own, a device's late one may come
BROADCAST_TURNAROUND_S: Final = 0.1  # Modbus over serial line 2.4.1: 100-200 ms after broadcasts
PROBE_MAX_S: Final = 5.0  # largest wait between probes of an offline device
PORT_BACKOFF_FIRST_S: Final = 0.5
SLOW_GROUP_DELAY_S: Final = 2.0


_SLOW_GROUPS: Final = frozenset({PollGroup.DIAGNOSTICS, PollGroup.CONFIGURATION})
_FAILURE_NAMES: Final[dict[type[Exception], str]] = {
    BusTimeoutError: "timeout",
    CrcError: "crc_error",
    UnexpectedDeviceError: "wrong_address",
    MalformedFrameError: "malformed_answer",
}


@dataclass(frozen=True, slots=True, kw_only=True)
class DeviceTarget:
    """One device to poll, with everything resolved from the config and its profile."""

    name: str
    address: int
    profile: Profile
    intervals: Mapping[str, float | None]  # point -> seconds; None: identity, read once
    float_order: codec.WordOrder | None = None  # explicit override of the profile/register
    timeout_s: float | None = None  # None: computed from the profile's timing
    min_response_time_s: float = 0.0
    extra_gap_s: float = 0.0
    retries: int = 2
    offline_after: int = 3
    probe_max_s: float = PROBE_MAX_S

    # Points of the diagnostics and configuration groups, polled in free line time; resolved
    # once here, not looked up on every scheduling step.
    slow_points: frozenset[str] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        """Resolve the slow points from the profile."""
        slow = frozenset(n for n in self.intervals if self.profile.point(n).group in _SLOW_GROUPS)
        object.__setattr__(self, "slow_points", slow)

    @property
    def poll_interval_s(self) -> float:
        """The shortest interval of its points: the pace of its probes when offline."""
        return min((i for i in self.intervals.values() if i), default=1.0)


@dataclass(slots=True)
class DeviceState:
    """What the worker knows about a device while running."""

    target: DeviceTarget
    next_due: dict[str, float] = field(default_factory=dict)
    identity_pending: set[str] = field(default_factory=set)
    # The earliest deadline of each class (slow: diagnostics), cleared whenever a deadline,
    # the pending identity or the unreadable points change: asked for on every scheduling
    # step of every device, it must not walk all points each time.
    deadline_cache: dict[bool, float] = field(default_factory=dict)
    values: dict[str, codec.Decoded] = field(default_factory=dict)
    attempts: Counter[str] = field(default_factory=Counter)
    online: bool | None = None  # None until the first answer or the first offline verdict
    failures: int = 0
    probe_at: float = 0.0
    backoff_s: float = 0.0
    not_before: float = 0.0
    split_before: set[int] = field(default_factory=set)
    unreadable: set[str] = field(default_factory=set)
    undecodable: set[str] = field(default_factory=set)  # points whose registers did not decode
    missed_deadlines: int = 0
    fresh: set[str] = field(default_factory=set)  # not polled since (re)start: no lag yet
    lag_s: float = 0.0
    lag_reported: bool = False

    @property
    def profile(self) -> Profile:
        """The device's register map."""
        return self.target.profile

    @property
    def float_order(self) -> codec.WordOrder:
        """Configured order, else the one the device's format register reports, else CDAB."""
        if self.target.float_order is not None:
            return self.target.float_order
        selector = self.profile.float_order_register
        if selector is not None:
            value = self.values.get(selector.point)
            if isinstance(value, codec.EnumValue) and value.code in selector.orders:
                return selector.orders[value.code]
        return self.profile.float_order

    def unit_of(self, point: Point) -> str | None:
        """The point's unit, looked up in the unit register it names if need be."""
        if point.unit_from is None:
            return point.unit
        selected = self.values.get(point.unit_from)
        if isinstance(selected, codec.EnumValue):
            return self.profile.point(point.unit_from).enum_units.get(selected.code)
        return None


@dataclass(slots=True)
class WriteJob:
    """A write waiting for its turn on the line: a value to encode, or registers encoded."""

    device: str
    point: str
    value: object
    done: asyncio.Future[frames.Response | None]
    registers: tuple[int, ...] | None = None


@dataclass(slots=True)
class ReadJob:
    """An on-demand read (a command's check or read-back) waiting for its turn."""

    device: str
    points: tuple[str, ...]
    done: asyncio.Future[list[Sample]]


LineJob: TypeAlias = WriteJob | ReadJob


def default_timeout_s(target: DeviceTarget, response_bytes: int, wire_s: float) -> float:
    """Response timeout: the answer's wire time plus t1 (digiLine: 25 ms + min. response time)."""
    if target.timeout_s is not None:
        return target.timeout_s
    t1 = target.profile.timing.processing_time_s + target.min_response_time_s
    return wire_s * response_bytes + t1 + RESPONSE_MARGIN_S


class BusWorker:
    """Polls the devices of one line for as long as it runs; owns the line exclusively."""

    def __init__(
        self,
        *,
        name: str,
        line: Line,
        devices: Sequence[DeviceTarget],
        sinks: Sequence[Sink] = (),
        late_answer_window_s: float = LATE_ANSWER_WINDOW_S,
        reconnect_max_s: float = 30.0,
        rng: random.Random | None = None,
    ) -> None:
        """Prepare the schedule; :meth:`run` does the work."""
        self.name = name
        self.line = line
        self.sinks = list(sinks)
        self.devices = {d.name: DeviceState(target=d) for d in devices}
        self.late_answer_window_s = late_answer_window_s
        self.reconnect_max_s = reconnect_max_s
        self._jobs: list[LineJob] = []  # writes and on-demand reads, in submission order
        self._running = False
        self._broadcasts: list[tuple[frames.Request, asyncio.Future[None]]] = []
        self._wake = asyncio.Event()
        self._rng = rng or random.Random()  # noqa: S311 - jitter, nothing secret
        self._planners = {
            d.name: Planner(
                d.profile, CostModel.for_device(d.profile, line.format, extra_gap_s=d.extra_gap_s)
            )
            for d in devices
        }
        self._port_failures_in_a_row = 0
        self._stopping = False
        self._stop_requested = asyncio.Event()

    # --- public -----------------------------------------------------------------------

    async def run(self) -> None:
        """Open the port, poll, and on port failure reopen with capped jittered backoff."""
        delay = PORT_BACKOFF_FIRST_S
        self._running = True
        try:
            await self._run(delay)
        finally:
            self._running = False
            self._fail_jobs(BusClosedError(f"bus {self.name} stopped"))

    async def _run(self, delay: float) -> None:
        while not self._stopping:
            try:
                if not self.line.is_open:
                    await self.line.open()
                    if self._port_failures_in_a_row:
                        _LOGGER.info("%s: port %s is back", self.name, self.line.port)
                    self._port_failures_in_a_row = 0
                    delay = PORT_BACKOFF_FIRST_S
                    self._restart_schedule(time.monotonic())
                await self._poll_forever()
            except BusClosedError as exc:
                await self.line.close()
                self._port_failures_in_a_row += 1
                self.line.stats.port_failures += 1
                self._fail_jobs(exc)  # a command waits for no reconnection: it says why now
                log = _LOGGER.warning if self._port_failures_in_a_row == 1 else _LOGGER.debug
                log("%s: %s; retrying in %.1f s", self.name, exc, delay)
                await self._all_offline(str(exc))
                await self._backoff(delay * self._rng.uniform(0.8, 1.2))
                delay = min(delay * 2, self.reconnect_max_s)

    async def _backoff(self, delay_s: float) -> None:
        """Wait before reopening the port, or until a stop is asked for.

        SIGTERM with the line gone must not wait out a backoff of up to ``reconnect_max_s``.
        """
        with contextlib.suppress(TimeoutError):
            async with asyncio.timeout(delay_s):
                await self._stop_requested.wait()

    @property
    def running(self) -> bool:
        """Whether :meth:`run` owns the line now (jobs queue) or not (they run inline)."""
        return self._running

    def device_profile(self, device: str) -> Profile:
        """The register map of a device of this line."""
        return self._state(device).profile

    def device_address(self, device: str) -> int:
        """The Modbus address of a device of this line."""
        return self._state(device).target.address

    def float_order(self, device: str) -> codec.WordOrder:
        """The float word order a device uses now (config, its format register, or CDAB)."""
        return self._state(device).float_order

    def needs_float_order(self, device: str) -> bool:
        """Whether the device's format register must be read before floats are encoded."""
        state = self._state(device)
        selector = state.profile.float_order_register
        return (
            selector is not None
            and state.target.float_order is None
            and selector.point not in state.values
        )

    def last_value(self, device: str, point: str) -> codec.Decoded:
        """The value last decoded for a point (a :class:`codec.Fault` included), or ``None``."""
        return self._state(device).values.get(point)

    def _state(self, device: str) -> DeviceState:
        if device not in self.devices:
            raise GatewayError(f"bus {self.name} has no device {device!r}")
        return self.devices[device]

    def submit_write(
        self, device: str, point: str, value: object
    ) -> asyncio.Future[frames.Response | None]:
        """Queue a write; it runs before pending reads but after any wait the rules require."""
        self._state(device).profile.point(point)
        done: asyncio.Future[frames.Response | None] = asyncio.get_running_loop().create_future()
        self._enqueue(WriteJob(device=device, point=point, value=value, done=done))
        return done

    async def write_registers(
        self, device: str, point: str, registers: tuple[int, ...]
    ) -> frames.Response | None:
        """Write registers already encoded and validated to a point, then keep its wait.

        While :meth:`run` polls, the write queues ahead of due reads; otherwise (the command
        line) it runs at once, after any wait still pending. Failures raise as the bus
        reports them (:class:`DeviceExceptionError`, :class:`BusTimeoutError`, ...).
        """
        self._state(device).profile.point(point)
        done: asyncio.Future[frames.Response | None] = asyncio.get_running_loop().create_future()
        job = WriteJob(device=device, point=point, value=None, done=done, registers=registers)
        if self._running:
            self._enqueue(job)
        else:
            await self._wait_for_turn(self.devices[device])
            with contextlib.suppress(BusClosedError):  # set on the future, raised below
                await self._write(self.devices[device], job)
        return await done

    async def read_points(self, device: str, points: Sequence[str]) -> list[Sample]:
        """Read points of a device now (a command's check or read-back), with retries.

        Queued ahead of due reads while :meth:`run` polls, else run at once. A point that
        could not be read comes back with quality ``comms_error``; the samples are not
        published.
        """
        state = self._state(device)
        names = tuple(state.profile.point(p).name for p in points)
        if not self._running:
            return await self._read_now(state, names)
        done: asyncio.Future[list[Sample]] = asyncio.get_running_loop().create_future()
        self._enqueue(ReadJob(device=device, points=names, done=done))
        return await done

    def _enqueue(self, job: LineJob) -> None:
        if self._stopping:
            job.done.set_exception(BusClosedError(f"bus {self.name} is stopping"))
            return
        self._jobs.append(job)
        self._wake.set()

    def _fail_jobs(self, exc: Exception) -> None:
        for job in self._jobs:
            if not job.done.done():
                job.done.set_exception(exc)
        self._jobs.clear()

    @staticmethod
    async def _wait_for_turn(state: DeviceState) -> None:
        delay = state.not_before - time.monotonic()
        if delay > 0:
            await asyncio.sleep(delay)

    def submit_broadcast(self, address: int, registers: Sequence[int]) -> asyncio.Future[None]:
        """Queue a write to every device (Modbus address 0); no device answers it.

        After it, every device waits the turnaround delay, or its profile's post-write
        wait for that register if longer, before the next request.
        """
        request = frames.write_request(frames.BROADCAST, address, registers)
        done: asyncio.Future[None] = asyncio.get_running_loop().create_future()
        self._broadcasts.append((request, done))
        self._wake.set()
        return done

    async def _run_a_broadcast(self, now: float) -> bool:
        if not self._broadcasts or any(s.not_before > now for s in self.devices.values()):
            return False
        request, done = self._broadcasts.pop(0)
        gap = max(
            (self._gap_s(s) for s in self.devices.values()), default=self.line.format.frame_gap_s()
        )
        try:
            await self.line.transact(request, timeout_s=0.0, gap_s=gap)
        except BusClosedError as exc:
            done.set_exception(exc)
            raise
        sent = time.monotonic()
        for state in self.devices.values():
            wait = max(
                BROADCAST_TURNAROUND_S,
                state.profile.post_write_wait(request.address, request.count),
            )
            state.not_before = max(state.not_before, sent + wait)
        done.set_result(None)
        return True

    def request_stop(self) -> None:
        """Finish the transaction in flight, then leave :meth:`run` (SIGTERM, SIGINT)."""
        self._stopping = True
        self._stop_requested.set()
        self._wake.set()

    def health(self) -> list[DeviceHealth]:
        """Each device's availability, lag and missed deadlines (read by the metrics)."""
        return [
            DeviceHealth(
                bus=self.name,
                device=name,
                address=state.target.address,
                online=state.online,
                failures_in_a_row=state.failures,
                lag_s=state.lag_s,
                missed_deadlines=state.missed_deadlines,
                unreadable_points=len(state.unreadable),
            )
            for name, state in self.devices.items()
        ]

    # --- scheduling -------------------------------------------------------------------

    def _restart_schedule(self, now: float) -> None:
        for state in self.devices.values():
            self._schedule_device(state, now)

    def _schedule_device(self, state: DeviceState, now: float) -> None:
        """Everything due now, identity again (start or reconnection)."""
        state.next_due.clear()
        state.identity_pending.clear()
        state.deadline_cache.clear()
        state.fresh = set(state.target.intervals)
        profile = state.profile
        for name, interval in state.target.intervals.items():
            if interval is None:
                state.identity_pending.add(name)
            elif profile.point(name).group in _SLOW_GROUPS:
                # Process values first: slow groups follow once the first values are out.
                state.next_due[name] = now + min(interval, SLOW_GROUP_DELAY_S)
            else:
                state.next_due[name] = now
        # Registers other values depend on: units and the float format.
        for name in state.target.intervals:
            unit_from = profile.point(name).unit_from
            if unit_from is not None:
                state.identity_pending.add(unit_from)
        if profile.float_order_register is not None and state.target.float_order is None:
            state.identity_pending.add(profile.float_order_register.point)
        state.attempts.clear()

    @staticmethod
    def _is_slow(state: DeviceState, name: str) -> bool:
        return name in state.target.slow_points and name not in state.identity_pending

    def _due_points(self, state: DeviceState, now: float, *, slow: bool) -> list[str]:
        due = [name for name, deadline in state.next_due.items() if deadline <= now]
        due.extend(state.identity_pending - set(due))
        return [n for n in due if n not in state.unreadable and self._is_slow(state, n) == slow]

    def _next_deadline(self, state: DeviceState, *, slow: bool) -> float:
        """When the device next has work of the class: values (fast) or diagnostics (slow)."""
        if state.online is False:
            return state.probe_at if not slow else math.inf
        if not slow and any(n not in state.unreadable for n in state.identity_pending):
            return 0.0
        cached = state.deadline_cache.get(slow)
        if cached is None:
            cached = min(
                (
                    t
                    for n, t in state.next_due.items()
                    if n not in state.unreadable and self._is_slow(state, n) == slow
                ),
                default=math.inf,
            )
            state.deadline_cache[slow] = cached
        return cached

    def _pick(self, now: float, *, slow: bool) -> DeviceState | None:
        """The device with the earliest due work of the class (ties: lower address)."""
        due = [
            (deadline, s.target.address, s)
            for s in self.devices.values()
            if s.not_before <= now and (deadline := self._next_deadline(s, slow=slow)) <= now
        ]
        return min(due, key=lambda item: (item[0], item[1]))[2] if due else None

    async def _poll_forever(self) -> None:
        """Writes first, then due values (earliest deadline first), then diagnostics.

        Diagnostics and configuration only fill the time values leave free, one read at a
        time, so a long logbook read never delays a measured value.
        """
        while not self._stopping:
            now = time.monotonic()
            if await self._run_a_job(now) or await self._run_a_broadcast(now):
                continue
            if (state := self._pick(now, slow=False)) is not None:
                if state.online is False:
                    await self._probe(state, now)
                else:
                    await self._poll(state, now, slow=False)
                continue
            if (state := self._pick(now, slow=True)) is not None:
                await self._poll(state, now, slow=True)
                continue
            await self._sleep_until_next(now)

    async def _sleep_until_next(self, now: float) -> None:
        wake_at = min(
            (
                max(
                    min(self._next_deadline(s, slow=False), self._next_deadline(s, slow=True)),
                    s.not_before,
                )
                for s in self.devices.values()
            ),
            default=now + 1.0,
        )
        if self._jobs:
            wake_at = min(wake_at, *(self.devices[j.device].not_before for j in self._jobs))
        if self._broadcasts:
            wake_at = min(wake_at, max((s.not_before for s in self.devices.values()), default=now))
        self._wake.clear()
        timeout = max(0.0, wake_at - now)
        if math.isinf(timeout):
            timeout = 1.0
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(self._wake.wait(), timeout=timeout)
        if not self.line.is_open:
            raise BusClosedError(f"{self.line.port} went away")

    # --- reads ------------------------------------------------------------------------

    def _timeout_for(self, state: DeviceState, response_bytes: int) -> float:
        return default_timeout_s(state.target, response_bytes, self.line.format.character_s)

    def _gap_s(self, state: DeviceState) -> float:
        return self.line.format.frame_gap_s(
            max(state.profile.timing.min_gap_s, state.target.extra_gap_s)
        )

    async def _transact(
        self, state: DeviceState, request: frames.Request, response_bytes: int
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
                request,
                timeout_s=self._timeout_for(state, response_bytes),
                gap_s=self._gap_s(state),
                not_before=state.not_before,
                exceptions=state.profile.exceptions,
                byte_count_16bit=state.profile.quirks.string_byte_count_16bit,
            )
        except (BusTimeoutError, MalformedFrameError, UnexpectedDeviceError):
            window_end = time.monotonic() + self.late_answer_window_s
            state.not_before = max(state.not_before, window_end)
            raise
        assert exchange is not None  # noqa: S101 - unicast requests always have an answer
        return exchange.response

    def _plan(self, state: DeviceState, names: Sequence[str]) -> tuple[ReadBlock, ...]:
        points = [state.profile.point(name) for name in names]
        planner = self._planners[state.target.name]
        return planner.plan(points, split_before=frozenset(state.split_before))

    def _plan_slow(self, state: DeviceState, names: Sequence[str]) -> tuple[ReadBlock, ...]:
        """The reads of due diagnostics: the blocks of their whole interval classes.

        Diagnostics are read a block at a time and cut short whenever values fall due, so
        the set still due is a different one after every interruption. Planning each such
        set anew missed the plan cache nearly every time (an H10 has some 260 slow points)
        and took a third of the gateway's CPU at 480 devices. The plan of every slow point
        sharing an interval with a due one has a stable key; its blocks that hold a due
        point are the ones to read, and points that come along were read in the same phase.
        """
        intervals = state.target.intervals
        wanted = {intervals.get(name) for name in names}
        members = [  # in any order: the planner keys its cache by the set
            name
            for name in state.target.slow_points
            if intervals.get(name) in wanted
            and name not in state.unreadable
            and name not in state.identity_pending
        ]
        due = set(names)
        return tuple(
            block
            for block in self._plan(state, members)
            if any(point.name in due for point in block.points)
        )

    async def _poll(self, state: DeviceState, now: float, *, slow: bool) -> None:
        names = self._due_points(state, now, slow=slow)
        samples: list[Sample] = []
        plan = self._plan_slow(state, names) if slow else self._plan(state, names)
        # Oldest deadlines first, so a read cut short by due values resumes where it left.
        blocks = sorted(plan, key=lambda b: self._block_deadline(state, b))
        for block in blocks:
            if state.not_before > time.monotonic() or state.online is False:
                break  # a failure set a quarantine or took the device offline: others first
            if samples and slow and self._pick(time.monotonic(), slow=False) is not None:
                break  # values are due somewhere: the rest of the diagnostics waits
            samples.extend(await self._read_block(state, block) or ())
        self._advance(state, [s.point for s in samples], now)
        if samples:
            await self._publish(samples)

    @staticmethod
    def _block_deadline(state: DeviceState, block: ReadBlock) -> float:
        """The earliest deadline of a block's points (identity reads come first)."""
        return min(state.next_due.get(p.name, 0.0) for p in block.points)

    async def _read_block(self, state: DeviceState, block: ReadBlock) -> list[Sample] | None:
        """Read one block; ``None`` when it will be retried later.

        Every failed transaction counts towards taking the device offline; any answer,
        an exception included, shows it is there.
        """
        request = frames.read_request(state.target.address, block.address, block.count)
        try:
            response = await self._transact(state, request, 5 + 2 * block.count)
        except DeviceExceptionError as exc:
            await self._mark_online(state, "answered")
            if exc.code == frames.ILLEGAL_ADDRESS and len(block.points) > 1:
                state.split_before.update(p.address for p in block.points[1:])
                _LOGGER.info(
                    "%s/%s: exception 02 for %d registers at %#06x; reading its points apart",
                    self.name,
                    state.target.name,
                    block.count,
                    block.address,
                )
                return None
            if exc.code == frames.ILLEGAL_ADDRESS:
                point = block.points[0]
                state.unreadable.add(point.name)
                state.deadline_cache.clear()
                _LOGGER.warning(
                    "%s/%s: the device does not answer %s (%#06x): exception 02; no longer polled",
                    self.name,
                    state.target.name,
                    point.name,
                    point.address,
                )
            return self._failed(state, block, f"exception_{exc.code:02d}")
        except (BusTimeoutError, FrameError) as exc:
            await self._count_failure(state, str(exc))
            if state.online is not False and self._retry(state, block):
                return None
            _LOGGER.debug("%s/%s: %s", self.name, state.target.name, exc)
            return self._failed(state, block, _FAILURE_NAMES.get(type(exc), "comms_error"))
        await self._mark_online(state, "answered")
        for point in block.points:
            state.attempts.pop(point.name, None)
        return self._decode(state, block, response.registers)

    def _retry(self, state: DeviceState, block: ReadBlock) -> bool:
        names = [p.name for p in block.points]
        attempts = max(state.attempts[n] for n in names) + 1
        if attempts > state.target.retries:
            for name in names:
                state.attempts.pop(name, None)
            return False
        for name in names:
            state.attempts[name] = attempts
        self.line.stats.retries[state.target.address] += 1
        return True

    def _decode(
        self, state: DeviceState, block: ReadBlock, registers: tuple[int, ...]
    ) -> list[Sample]:
        at = (time.monotonic(), datetime.now(tz=UTC))
        order = state.float_order
        samples = []
        for point in block.points:
            offset = point.address - block.address
            chunk = registers[offset : offset + point.count]
            try:
                value: codec.Decoded = codec.decode(point.format, chunk, float_order=order)
            except DecodeError as exc:
                # The line and the device worked; the registers are not a value of the
                # point's type (an S10 clock dated month 13). A fault of the value, with
                # what was sent, and never a comms error that would blame the line.
                value = codec.Fault.undecodable(chunk, exc)
            self._note_undecodable(state, point, value)
            state.values[point.name] = value
            if point.name in state.identity_pending:
                state.identity_pending.discard(point.name)
                state.deadline_cache.clear()
            if isinstance(value, codec.Fault):
                fault = self._sample(state, point, fault=value.name, raw=value.registers, at=at)
                samples.append(fault)
            else:
                samples.append(self._sample(state, point, value=value, at=at))
        return samples

    def _note_undecodable(self, state: DeviceState, point: Point, value: codec.Decoded) -> None:
        """Log why a point's registers do not decode: the first time loudly, then quietly."""
        if not (isinstance(value, codec.Fault) and value.name == codec.UNDECODABLE):
            if point.name in state.undecodable:
                state.undecodable.discard(point.name)
                _LOGGER.info("%s/%s: %s decodes again", self.name, state.target.name, point.name)
            return
        log = _LOGGER.debug if point.name in state.undecodable else _LOGGER.warning
        state.undecodable.add(point.name)
        log(
            "%s/%s: %s cannot be decoded (%s): %s",
            self.name,
            state.target.name,
            point.name,
            " ".join(hex_registers(value.registers)),
            value.reason,
        )

    def _failed(self, state: DeviceState, block: ReadBlock, reason: str) -> list[Sample]:
        at = (time.monotonic(), datetime.now(tz=UTC))
        for point in block.points:
            state.identity_pending.discard(point.name)
        state.deadline_cache.clear()
        return [self._sample(state, p, fault=reason, comms_error=True, at=at) for p in block.points]

    def _sample(
        self,
        state: DeviceState,
        point: Point,
        *,
        value: codec.Value = None,
        fault: str | None = None,
        raw: tuple[int, ...] = (),
        comms_error: bool = False,
        at: tuple[float, datetime],
    ) -> Sample:
        """A good value, a sensor fault, or (``comms_error``) no value at all.

        ``raw`` carries the registers of a value that could not be decoded.
        """
        if comms_error:
            quality = Quality.COMMS_ERROR
        elif fault is not None:
            quality = Quality.FAULT
        else:
            quality = Quality.GOOD
        return Sample(
            bus=self.name,
            device=state.target.name,
            profile=state.profile.id,
            point=point.name,
            value=value,
            fault=fault,
            unit=state.unit_of(point),
            quality=quality,
            monotonic=at[0],
            time=at[1],
            group=point.group.value,
            raw=raw,
        )

    def _advance(self, state: DeviceState, names: Sequence[str], now: float) -> None:
        """Move the deadlines of the points just handled; count and skip missed ones."""
        state.deadline_cache.clear()
        for name in set(names):
            interval = state.target.intervals.get(name)
            if interval is None or name not in state.next_due:
                continue
            deadline = state.next_due[name]
            if name in state.fresh:  # the first cycle after a (re)start reads everything
                state.fresh.discard(name)
                deadline = now
            if deadline > now:  # read early, along with due diagnostics: take their phase
                state.next_due[name] = now + interval
                continue
            lag = now - deadline
            nxt = deadline + interval
            if nxt <= now:
                skipped = math.floor((now - nxt) / interval) + 1
                nxt += skipped * interval
                state.missed_deadlines += skipped
            state.next_due[name] = nxt
            state.lag_s = max(0.0, lag)
            starting = any(s.identity_pending for s in self.devices.values())
            if lag > interval and not state.lag_reported and not starting:
                state.lag_reported = True
                _LOGGER.warning(
                    "%s/%s: the line cannot keep up: %s is %.2f s late (interval %.2f s); "
                    "see the poll lag metric",
                    self.name,
                    state.target.name,
                    name,
                    lag,
                    interval,
                )

    # --- availability -----------------------------------------------------------------

    async def _mark_online(self, state: DeviceState, reason: str) -> None:
        state.failures = 0
        state.backoff_s = 0.0
        if state.online is not True:
            was_offline = state.online is False
            state.online = True
            if was_offline:
                _LOGGER.info("%s/%s is back online", self.name, state.target.name)
                self._schedule_device(state, time.monotonic())
            await self._event(state, online=True, reason=reason)

    async def _count_failure(self, state: DeviceState, reason: str) -> None:
        """One more failed transaction in a row; enough of them take the device offline."""
        state.failures += 1
        if state.failures >= state.target.offline_after and state.online is not False:
            state.online = False
            state.backoff_s = state.target.poll_interval_s
            state.probe_at = time.monotonic() + state.backoff_s
            _LOGGER.warning(
                "%s/%s (address %d) is offline after %d failed requests: %s",
                self.name,
                state.target.name,
                state.target.address,
                state.failures,
                reason,
            )
            await self._event(state, online=False, reason=reason)

    async def _probe(self, state: DeviceState, now: float) -> None:
        """One small read of an offline device; on success it is polled in full again."""
        names = list(state.target.intervals) or [state.profile.points[0].name]
        block = self._plan(state, names[:1])[0]
        request = frames.read_request(state.target.address, block.address, block.count)
        try:
            await self._transact(state, request, 5 + 2 * block.count)
        except DeviceExceptionError:
            pass  # an exception is an answer: the device is there
        except (BusTimeoutError, FrameError):
            cap = max(state.target.probe_max_s, state.target.poll_interval_s)
            state.backoff_s = min(max(state.backoff_s, state.target.poll_interval_s) * 2, cap)
            state.probe_at = now + state.backoff_s * self._rng.uniform(0.8, 1.2)
            return
        state.online = None
        await self._mark_online(state, "answered a probe")
        self._schedule_device(state, time.monotonic())

    async def _all_offline(self, reason: str) -> None:
        for state in self.devices.values():
            if state.online is not False:
                state.online = False
                state.probe_at = 0.0
                await self._event(state, online=False, reason=reason)

    # --- writes -----------------------------------------------------------------------

    async def _run_a_job(self, now: float) -> bool:
        """Run the oldest job whose device is free; a device's jobs keep their order."""
        for job in self._jobs:
            state = self.devices[job.device]
            if state.not_before <= now:
                self._jobs.remove(job)
                if job.done.cancelled():
                    return True  # the caller gave up waiting: nothing to do
                if isinstance(job, ReadJob):
                    try:
                        job.done.set_result(await self._read_now(state, job.points))
                    except BusClosedError as exc:
                        job.done.set_exception(exc)
                        raise
                else:
                    await self._write(state, job)
                return True
        return False

    async def _write(self, state: DeviceState, job: WriteJob) -> None:
        point = state.profile.point(job.point)
        try:
            registers = job.registers
            if registers is None:
                registers = codec.encode(point.format, job.value, float_order=state.float_order)
            request = frames.write_request(state.target.address, point.address, registers)
        except EncodeError as exc:
            job.done.set_exception(exc)
            return
        try:
            response = await self._transact(state, request, 8)
        except (DeviceExceptionError, BusTimeoutError, FrameError) as exc:
            job.done.set_exception(exc)
            return
        except BusClosedError as exc:
            job.done.set_exception(exc)
            raise
        finally:
            # H10/H20 6.1.5: the wait follows every write, answered or not.
            wait = state.profile.post_write_wait(point.address, point.count)
            state.not_before = max(state.not_before, time.monotonic() + wait)
        job.done.set_result(response)

    # --- one-shot reads ---------------------------------------------------------------

    async def read_once(self, device: str) -> list[Sample]:
        """Read every point of a device once, with all timing rules and retries inline.

        The unit and float-format registers other points depend on are read first.
        """
        state = self.devices[device]
        names = list(state.target.intervals)
        profile = state.profile
        needed = {u for n in names if (u := profile.point(n).unit_from) is not None}
        if profile.float_order_register is not None and state.target.float_order is None:
            needed.add(profile.float_order_register.point)
        if needed:
            await self._read_now(state, sorted(needed))
        return await self._read_now(state, names)

    async def _read_now(self, state: DeviceState, names: Sequence[str]) -> list[Sample]:
        samples: dict[str, Sample] = {}
        todo = list(names)
        while todo:
            blocks = self._plan(state, todo)
            todo = []
            for block in blocks:
                delay = state.not_before - time.monotonic()
                if delay > 0:
                    await asyncio.sleep(delay)
                outcome = await self._read_block(state, block)
                if outcome is None:
                    todo.extend(p.name for p in block.points)
                else:
                    samples.update((s.point, s) for s in outcome)
        return [samples[name] for name in names if name in samples]

    # --- sinks ------------------------------------------------------------------------

    async def _publish(self, samples: list[Sample]) -> None:
        for sink in self.sinks:
            await sink.publish(samples)

    async def _event(self, state: DeviceState, *, online: bool, reason: str) -> None:
        event = DeviceEvent(
            bus=self.name,
            device=state.target.name,
            profile=state.profile.id,
            online=online,
            reason=reason,
            time=datetime.now(tz=UTC),
        )
        for sink in self.sinks:
            await sink.device_event(event)
