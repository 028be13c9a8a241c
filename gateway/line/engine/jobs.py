"""Work for a line besides polling: writes, on-demand reads and broadcasts, in their turn.

While the worker runs, work waits here and is served ahead of due polls, the oldest job
whose device is free first, so a device's jobs keep their order; a broadcast waits until
every device is free. From the command line, with no worker running, work runs at once,
after any wait still pending.
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, TypeAlias

from gateway.errors import (
    BusClosedError,
    BusTimeoutError,
    DeviceExceptionError,
    EncodeError,
    FrameError,
    GatewayError,
)
from gateway.line.engine.plan import require_own
from gateway.wire import frames

if TYPE_CHECKING:
    from collections.abc import Callable, Mapping, Sequence

    from gateway.line.engine.devices import DeviceState
    from gateway.line.engine.transactions import Transactions
    from gateway.line.samples import Sample
    from gateway.profiles.model import Point


@dataclass(slots=True)
class WriteJob:
    """A write waiting for its turn on the line: a value to encode, or registers encoded."""

    device: str
    point: Point
    value: object
    done: asyncio.Future[frames.Response | None]
    registers: tuple[int, ...] | None = None


@dataclass(slots=True)
class ReadJob:
    """An on-demand read (a command's check or read-back) waiting for its turn."""

    device: str
    points: tuple[Point, ...]
    done: asyncio.Future[list[Sample]]


LineJob: TypeAlias = WriteJob | ReadJob


class JobQueue:
    """The writes, on-demand reads and broadcasts of one line."""

    def __init__(
        self,
        *,
        bus: str,
        devices: Mapping[str, DeviceState],
        transactions: Transactions,
        wake: asyncio.Event,
    ) -> None:
        """Queue work for ``devices``; ``wake`` is set whenever work arrives."""
        self.bus = bus
        self.devices = devices
        self.transactions = transactions
        self.running = False  # the worker polls: work queues (else it runs at once)
        self.stopping = False  # the worker stops: new work is refused
        self._jobs: list[LineJob] = []  # writes and on-demand reads, in submission order
        self._broadcasts: list[tuple[frames.Request, asyncio.Future[None]]] = []
        self._wake = wake
        # Called after each write that succeeded (the worker reads its effects again).
        self.on_written: Callable[[DeviceState, frames.Request], None] | None = None

    def state(self, device: str) -> DeviceState:
        """The device of that name on this line, or a :class:`GatewayError`."""
        if device not in self.devices:
            raise GatewayError(f"bus {self.bus} has no device {device!r}")
        return self.devices[device]

    def submit_write(
        self, device: str, point: str, value: object
    ) -> asyncio.Future[frames.Response | None]:
        """Queue a write of a value to encode; the point is looked up by name here, once."""
        target = self.state(device).profile.point(point)
        done: asyncio.Future[frames.Response | None] = asyncio.get_running_loop().create_future()
        self._enqueue(WriteJob(device=device, point=target, value=value, done=done))
        return done

    async def write_registers(
        self, device: str, point: Point, registers: tuple[int, ...]
    ) -> frames.Response | None:
        """Write registers already encoded to a point of the device's profile.

        Queued while the worker runs, else at once.
        """
        self.state(device)
        done: asyncio.Future[frames.Response | None] = asyncio.get_running_loop().create_future()
        job = WriteJob(device=device, point=point, value=None, done=done, registers=registers)
        if self.running:
            self._enqueue(job)
        else:
            await self._wait_for_turn(self.devices[device])
            with contextlib.suppress(BusClosedError):  # set on the future, raised below
                await self._write(self.devices[device], job)
        return await done

    async def read_points(self, device: str, points: Sequence[Point]) -> list[Sample]:
        """Read points of the device's profile; queued while the worker runs, else at once.

        The points come resolved (by the caller, where their names came in). One of another
        profile is refused here, at the caller, not in the bus task that would plan it.
        """
        state = self.state(device)
        chosen = tuple(points)
        for point in chosen:
            require_own(state.profile, point)
        if not self.running:
            return await self.transactions.read_now(state, chosen)
        done: asyncio.Future[list[Sample]] = asyncio.get_running_loop().create_future()
        self._enqueue(ReadJob(device=device, points=chosen, done=done))
        return await done

    def submit_broadcast(self, address: int, registers: Sequence[int]) -> asyncio.Future[None]:
        """Queue a write to every device (Modbus address 0)."""
        request = frames.write_request(frames.BROADCAST, address, registers)
        done: asyncio.Future[None] = asyncio.get_running_loop().create_future()
        self._broadcasts.append((request, done))
        self._wake.set()
        return done

    def fail_all(self, exc: Exception) -> None:
        """Fail every queued job with ``exc`` (the port is gone, or the worker stopped)."""
        for job in self._jobs:
            if not job.done.done():
                job.done.set_exception(exc)
        self._jobs.clear()

    def fail_device(self, device: str, exc: Exception) -> None:
        """Fail the queued jobs of one device (a reload removed it)."""
        for job in [job for job in self._jobs if job.device == device]:
            if not job.done.done():
                job.done.set_exception(exc)
            self._jobs.remove(job)

    def waiting(self) -> bool:
        """Whether a job or a broadcast is queued (asked before :meth:`run_next`'s coroutine)."""
        return bool(self._jobs or self._broadcasts)

    async def run_next(self, now: float) -> bool:
        """Run one job, else one broadcast, if one may run now; whether one did."""
        return await self._run_a_job(now) or await self._run_a_broadcast(now)

    def wake_at(self, wake_at: float, now: float) -> float:
        """``wake_at``, or earlier if queued work may run before."""
        if self._jobs:
            wake_at = min(wake_at, *(self.devices[j.device].holds.not_before for j in self._jobs))
        if self._broadcasts:
            holds = [s.holds.not_before for s in self.devices.values()]
            wake_at = min(wake_at, max(holds, default=now))
        return wake_at

    def _enqueue(self, job: LineJob) -> None:
        if self.stopping:
            job.done.set_exception(BusClosedError(f"bus {self.bus} is stopping"))
            return
        self._jobs.append(job)
        self._wake.set()

    @staticmethod
    async def _wait_for_turn(state: DeviceState) -> None:
        delay = state.holds.not_before - time.monotonic()
        if delay > 0:
            await asyncio.sleep(delay)

    async def _run_a_job(self, now: float) -> bool:
        """Run the oldest job whose device is free; a device's jobs keep their order."""
        for job in self._jobs:
            state = self.devices[job.device]
            if state.holds.not_before <= now:
                self._jobs.remove(job)
                if job.done.cancelled():
                    return True  # the caller gave up waiting: nothing to do
                if isinstance(job, ReadJob):
                    try:
                        job.done.set_result(await self.transactions.read_now(state, job.points))
                    except BusClosedError as exc:
                        job.done.set_exception(exc)
                        raise
                else:
                    await self._write(state, job)
                return True
        return False

    async def _write(self, state: DeviceState, job: WriteJob) -> None:
        point = job.point
        try:
            request = self.transactions.requests.write(
                state, point, value=job.value, registers=job.registers
            )
        except EncodeError as exc:
            job.done.set_exception(exc)
            return
        try:
            response = await self.transactions.write(state, point, request)
        except (DeviceExceptionError, BusTimeoutError, FrameError) as exc:
            job.done.set_exception(exc)
            return
        except BusClosedError as exc:
            job.done.set_exception(exc)
            raise
        if self.on_written is not None:
            self.on_written(state, request)
        job.done.set_result(response)

    async def _run_a_broadcast(self, now: float) -> bool:
        if not self._broadcasts or any(s.holds.not_before > now for s in self.devices.values()):
            return False
        request, done = self._broadcasts.pop(0)
        try:
            await self.transactions.broadcast(request)
        except BusClosedError as exc:
            done.set_exception(exc)
            raise
        done.set_result(None)
        return True
