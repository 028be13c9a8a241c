"""The bus owner: one task per line that polls its devices and runs the writes queued for them.

At each step the worker serves pending writes and on-demand reads first, then broadcasts,
then the device with the earliest due values, then diagnostics in the time left, as long as
the device is not inside a post-write wait or a late-answer quarantine. What is due is the
:class:`~gateway.line.engine.schedule.Schedule`'s to say; one device's poll (plan, run,
report) is the :class:`~gateway.line.engine.poll.Poller`'s; each request and its answer are
the :class:`~gateway.line.engine.transactions.Transactions`'; who is online is
:class:`~gateway.line.engine.health.Availability`'s verdict; a reload's devices change
through :class:`~gateway.line.engine.changes.DeviceChanges`. A port that fails is reopened
on a capped, jittered backoff.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import random
import time
from datetime import UTC, datetime
from typing import TYPE_CHECKING, Final

from gateway.errors import BusClosedError, BusError, PortUnavailableError
from gateway.line.engine.changes import DeviceChanges
from gateway.line.engine.decode import Decoder
from gateway.line.engine.devices import DeviceState
from gateway.line.engine.foreign import ForeignQueue
from gateway.line.engine.health import Availability
from gateway.line.engine.identity_guard import IdentityGuard
from gateway.line.engine.jobs import JobQueue
from gateway.line.engine.lateness import loop_watch
from gateway.line.engine.poll import Poller
from gateway.line.engine.schedule import Schedule
from gateway.line.engine.transactions import LATE_ANSWER_WINDOW_S, Transactions
from gateway.line.samples import DeviceEvent
from gateway.line.transports.port_diagnosis import PortReason
from gateway.profiles.effects import touched_by_write

if TYPE_CHECKING:
    from collections.abc import AsyncIterator, Sequence

    from gateway.line.boundary import Line
    from gateway.line.engine.devices import DeviceTarget
    from gateway.line.engine.health import DeviceHealth
    from gateway.line.samples import Sample, Sink
    from gateway.profiles import Profile
    from gateway.profiles.model import Point
    from gateway.wire import codec, frames

_LOGGER = logging.getLogger(__name__)

PORT_BACKOFF_FIRST_S: Final = 0.5


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
        self.reconnect_max_s = reconnect_max_s
        self._wake = asyncio.Event()
        self._rng = rng or random.Random()  # noqa: S311 - jitter, nothing secret
        self.schedule = Schedule(self.devices)
        self.availability = Availability(
            bus=name,
            devices=self.devices,
            schedule=self.schedule,
            announce=self._event,
            rng=self._rng,
        )
        self.transactions = Transactions(
            bus=name,
            line=line,
            devices=self.devices,
            availability=self.availability,
            decoder=Decoder(name),
            late_answer_window_s=late_answer_window_s,
        )
        self.jobs = JobQueue(
            bus=name, devices=self.devices, transactions=self.transactions, wake=self._wake
        )
        self.jobs.on_written = self._written
        # Pinned serial numbers: nothing published for, or written to, another sensor.
        self.identity = IdentityGuard(
            bus=name,
            devices=self.devices,
            transactions=self.transactions,
            availability=self.availability,
            schedule=self.schedule,
            announce=self._send_event,
        )
        # Other masters' requests (shared_bus:), refused until the gateway opens it.
        self.foreign = ForeignQueue(
            bus=name,
            devices=self.devices,
            transactions=self.transactions,
            schedule=self.schedule,
            wake=self._wake,
        )
        self.poller = Poller(
            bus=name,
            line=line,
            schedule=self.schedule,
            transactions=self.transactions,
            identity=self.identity,
            sinks=self.sinks,
        )
        self._port_failures_in_a_row = 0
        self._ever_opened = False
        # Whether a port another master holds at the start ends the run (the gateway's own
        # start), or is retried like any failure (a bus a reload added: the rest runs on).
        self.in_use_is_fatal = True
        self._last_reason: str | None = None
        self._stopping = False
        self._stop_requested = asyncio.Event()  # also set to end a backoff for a pause
        self._resume: asyncio.Event | None = None  # set while :meth:`paused` holds the line
        self._released = asyncio.Event()
        self.paused_for: str | None = None  # why polling is paused, while it is
        # A reload's new set of devices, applied between transactions (:meth:`change_devices`).
        self._changes = DeviceChanges(
            bus=name,
            devices=self.devices,
            schedule=self.schedule,
            transactions=self.transactions,
            identity=self.identity,
            jobs=self.jobs,
            foreign=self.foreign,
        )
        # Whether run() waits where nothing of it walks the devices (asleep, backing off,
        # paused): a change of devices is applied at once then, not at the next step.
        self._parked = False

    # --- running ----------------------------------------------------------------------

    async def run(self) -> None:
        """Open the port, poll, and on port failure reopen with capped jittered backoff."""
        delay = PORT_BACKOFF_FIRST_S
        self.jobs.running = True
        watch = loop_watch()
        self.poller.watch_loop(watch)
        watch.attach()
        self.line.wait_watch = watch  # the line's timer looks for the watch while it polls
        try:
            await self._run(delay)
        finally:
            self.line.rest()
            self.line.wait_watch = None
            watch.detach()
            self.jobs.running = False
            self.foreign.accepting = False
            self._released.set()  # a pause waiting for the line has it now
            stopped = BusClosedError(f"bus {self.name} stopped")
            self.jobs.fail_all(stopped)
            self.foreign.fail_all(stopped)

    async def _run(self, delay: float) -> None:
        while not self._stopping:
            self._changes.apply()
            if self._resume is not None:
                await self._hold(self._resume)
                continue
            try:
                if not self.line.is_open:
                    await self._open()
                    if self._port_failures_in_a_row:
                        _LOGGER.info("%s: port %s is back", self.name, self.line.port)
                    self._port_failures_in_a_row = 0
                    delay = PORT_BACKOFF_FIRST_S
                    self.schedule.restart(time.monotonic())
                await self._poll_forever()
            except BusClosedError as exc:
                await self.line.close()
                if self._fatal(exc):
                    raise
                self._port_failures_in_a_row += 1
                self.line.stats.port_failures += 1
                self.jobs.fail_all(exc)  # a command waits for no reconnection: it says why now
                self.foreign.fail_all(exc)
                # The first failure of a streak, and a new reason within it (unplugged,
                # then back without permission), loudly; the repeats quietly.
                reason = getattr(exc, "reason", None)
                first = self._port_failures_in_a_row == 1 or reason != self._last_reason
                self._last_reason = reason
                log = _LOGGER.warning if first else _LOGGER.debug
                log("%s: %s; retrying in %.1f s", self.name, exc, delay)
                await self.availability.all_offline(str(exc))
                await self._backoff(delay * self._rng.uniform(0.8, 1.2))
                delay = min(delay * 2, self.reconnect_max_s)

    async def _open(self) -> None:
        await self.line.open()
        self._ever_opened = True

    async def claim_port(self) -> None:
        """Open the port before :meth:`run`, so that another master on it stops a start.

        Raises :class:`PortUnavailableError` if the port is in use; any other failure is
        left to :meth:`run`, which reports it and retries on its backoff.
        """
        try:
            await self._open()
        except BusClosedError as exc:
            await self.line.close()
            if self._fatal(exc):
                raise
            return
        self.schedule.restart(time.monotonic())  # as run() does after it opens the port

    def _fatal(self, exc: BusClosedError) -> bool:
        """Whether a port failure ends the run: another master holds the port at start.

        Retrying would only repeat the message every backoff (a second ``gateway run``
        by mistake, or the service while a command holds the port), and the message
        names what to stop. Once this worker has had the port, an in-use reopen
        (``gateway read`` during an unplug) is retried like any other failure.
        """
        return (
            self.in_use_is_fatal
            and isinstance(exc, PortUnavailableError)
            and exc.reason == PortReason.IN_USE
            and not self._ever_opened
        )

    async def _backoff(self, delay_s: float) -> None:
        """Wait before reopening the port, or until a stop is asked for.

        SIGTERM with the line gone must not wait out a backoff of up to ``reconnect_max_s``.
        """
        if self._resume is not None:
            return
        self._parked = True
        try:
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(delay_s):
                    await self._stop_requested.wait()
        finally:
            self._parked = False
        if not self._stopping:
            self._stop_requested.clear()  # it ended the backoff for a pause

    def request_stop(self) -> None:
        """Finish the transaction in flight, then leave :meth:`run` (SIGTERM, SIGINT)."""
        self._stopping = True
        self.jobs.stopping = True
        self.foreign.accepting = False
        self._stop_requested.set()
        self._wake.set()
        if self._resume is not None:
            self._resume.set()

    # --- handing the line over --------------------------------------------------------

    @contextlib.asynccontextmanager
    async def paused(self, reason: str) -> AsyncIterator[None]:
        """Stop polling and close the port while the block runs (a scan of the line).

        Entered, the transaction in flight ends, the port is closed and nothing of this
        worker touches the line; queued writes and reads wait. Left, the port is reopened
        and polling goes on where its schedule says. Without :meth:`run` (the command
        line) the worker holds no port, and the block runs at once. One pause at a time:
        a second raises :class:`BusError`.
        """
        if self._resume is not None:
            raise BusError(f"bus {self.name} is already paused: {self.paused_for}")
        resume = self._resume = asyncio.Event()
        self.paused_for = reason
        self._released.clear()
        self._wake.set()
        self._stop_requested.set()  # ends a backoff
        _LOGGER.warning("%s: polling paused: %s", self.name, reason)
        try:
            if self.running:
                await self._released.wait()
            yield
        finally:
            self._resume = None
            self.paused_for = None
            resume.set()
            _LOGGER.info("%s: polling resumed", self.name)

    async def _hold(self, resume: asyncio.Event) -> None:
        """Let go of the line until :meth:`paused` ends (or the worker stops)."""
        await self.line.close()
        self._released.set()
        self._parked = True
        try:
            await resume.wait()
        finally:
            self._parked = False
        self._released.clear()
        if not self._stopping:
            self._stop_requested.clear()  # it was set to end a backoff for the pause

    @property
    def running(self) -> bool:
        """Whether :meth:`run` owns the line now (jobs queue) or not (they run inline)."""
        return self.jobs.running

    def health(self) -> list[DeviceHealth]:
        """Each device's availability, lag, missed deadlines and identity (for the metrics)."""
        return self.identity.annotate(self.availability.health())

    # --- the devices ------------------------------------------------------------------

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
        return self.jobs.state(device)

    def _written(self, state: DeviceState, request: frames.Request) -> None:
        """After a write: what it changes besides itself is read again at once (a calibration)."""
        now = time.monotonic()
        for address, count in touched_by_write(state.profile, request.address, request.count):
            self.schedule.reread(state, address, count, now)

    # --- a reload's changes ------------------------------------------------------------

    def change_devices(self, targets: Sequence[DeviceTarget]) -> asyncio.Future[None]:
        """The devices of this line are ``targets`` from now on; done once applied.

        A device whose target is the one it has keeps everything: its schedule, its state,
        its queued work (a calibration under way goes on). One with the same address and
        profile but other settings is re-planned: its deadlines start again, while what
        it answered, its waits (a post-write wait holds), its verdicts and its counters
        stay, and so does its queued work. One at another address or of another profile
        is another sensor: its queued work fails, and it starts afresh, as does a new one.
        A device not in ``targets`` goes; its queued work fails with the reason.

        Applied between transactions, never inside one: at once while :meth:`run` sleeps,
        backs off or is paused (or does not run), else before its next step.
        """
        done = self._changes.request(targets)
        if self._parked or not self.running:
            self._changes.apply()
        self._wake.set()
        return done

    async def use_line(self, line: Line) -> bool:
        """Go on with ``line`` in place of the line (a reload changed the bus's settings).

        Polling pauses: the transaction in flight ends and the old port closes; the new
        one opens as after a reconnection. False, and nothing changed, if the line is
        paused already (a scan of it): the caller builds a new worker instead.
        """
        if self._resume is not None:
            return False
        if not self.running:
            await self.line.close()
            self._swap_line(line)
            return True
        async with self.paused("its settings changed"):
            self._swap_line(line)
        return True

    def _swap_line(self, line: Line) -> None:
        self.line.rest()
        line.wait_watch, self.line.wait_watch = self.line.wait_watch, None
        self.line = line
        self.poller.use_line(line)
        self.transactions.use_line(line)

    # --- queued work ------------------------------------------------------------------

    def submit_write(
        self, device: str, point: str, value: object
    ) -> asyncio.Future[frames.Response | None]:
        """Queue a write; it runs before pending reads but after any wait the rules require."""
        self.identity.require_expected(device)
        return self.jobs.submit_write(device, point, value)

    async def write_registers(
        self, device: str, point: Point, registers: tuple[int, ...]
    ) -> frames.Response | None:
        """Write registers already encoded and validated to a point, then keep its wait.

        While :meth:`run` polls, the write queues ahead of due reads; otherwise (the command
        line) it runs at once, after any wait still pending. Failures raise as the bus
        reports them (:class:`DeviceExceptionError`, :class:`BusTimeoutError`, ...); a
        device whose pinned serial number is not confirmed refuses it
        (:class:`CommandRejectedError`).
        """
        self.identity.require_expected(device)
        return await self.jobs.write_registers(device, point, registers)

    async def read_points(self, device: str, points: Sequence[Point]) -> list[Sample]:
        """Read points of a device's profile now (a command's check or read-back), with retries.

        Queued ahead of due reads while :meth:`run` polls, else run at once. A point that
        could not be read comes back with quality ``comms_error``; the samples are not
        published. A device whose pinned serial number is not confirmed refuses it.
        """
        self.identity.require_expected(device)
        return await self.jobs.read_points(device, points)

    async def read_once(self, device: str) -> list[Sample]:
        """Read every point of a device once, with all timing rules and retries inline.

        The unit and float-format registers other points depend on are read first.
        """
        return await self.transactions.read_all(self.devices[device])

    def submit_broadcast(self, address: int, registers: Sequence[int]) -> asyncio.Future[None]:
        """Queue a write to every device (Modbus address 0); no device answers it.

        After it, every device waits the turnaround delay, or its profile's post-write
        wait for that register if longer, before the next request.
        """
        return self.jobs.submit_broadcast(address, registers)

    # --- polling ----------------------------------------------------------------------

    async def _poll_forever(self) -> None:
        """Writes, due values (earliest deadline first), other masters, then diagnostics.

        Other masters' requests take turns with due values, one after each device's poll,
        within their share of bus time: so a burst of due values (a start, a reconnection)
        does not keep them waiting past their clients' timeouts, and their share, not
        their number, bounds what they take from polling.

        Diagnostics and configuration only fill the time values leave free, one read at a
        time, so a long logbook read never delays a measured value.
        """
        foreign_turn = False
        while not self._stopping and self._resume is None:
            if self._changes:
                self._changes.apply()
            now = time.monotonic()
            # Each queue asked first whether it holds anything: a coroutine made for an
            # empty queue, on every poll, is CPU on every transaction's path.
            if self.jobs.waiting() and await self.jobs.run_next(now):
                continue
            foreign = self.foreign.waiting()
            if foreign and foreign_turn and await self.foreign.run_next(now):
                foreign_turn = False
                continue
            if (state := self.schedule.pick(now, slow=False)) is not None:
                if self.identity.holds(state):
                    await self.identity.recheck(state, now)
                elif state.presence.online is False:
                    await self.transactions.probe(state, now)
                else:
                    await self.poller.poll(state, now, slow=False)
                foreign_turn = True
                continue
            if foreign and await self.foreign.run_next(now):
                continue
            if (state := self.schedule.pick(now, slow=True)) is not None:
                await self.poller.poll(state, now, slow=True)
                continue
            await self._sleep_until_next(now)

    async def _sleep_until_next(self, now: float) -> None:
        wake_at = self.foreign.wake_at(self.jobs.wake_at(self.schedule.wake_at(now), now), now)
        self._wake.clear()
        timeout = max(0.0, wake_at - now)
        if math.isinf(timeout):
            timeout = 1.0
        watch = self.line.wait_watch
        if watch is not None:
            self.line.rest()  # its timer looks no more: this sleep is the worker's own
            watch.asleep()
        self._parked = True
        try:
            # asyncio.timeout, not wait_for: wait_for wraps the wait in a task of its own,
            # at every sleep (with devices' phases spread, a bus sleeps between most polls).
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(timeout):
                    await self._wake.wait()
        finally:
            self._parked = False
            if watch is not None:
                watch.awake(now + timeout, time.monotonic())
        if self._resume is not None:
            return  # a pause: the port is closed on purpose
        if not self.line.is_open:
            raise BusClosedError(f"{self.line.port} went away")

    async def _event(self, state: DeviceState, *, online: bool, reason: str) -> None:
        if self.identity.announces(state, online=online, reason=reason):
            await self._send_event(state, online=online, reason=reason)

    async def _send_event(self, state: DeviceState, *, online: bool, reason: str) -> None:
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
