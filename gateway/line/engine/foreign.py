"""Other masters' requests on the line: in the bus task's queue, within a share of bus time.

An RS485 line has one master. Another master (a SCADA, the vendor's service software)
reaches the sensors through the gateway instead (``shared_bus:``): its requests wait here
and are sent by the bus task like the gateway's own, under the same rules (inter-frame
gap, the device's minimum response time, post-write waits, the late-answer window, an
offline device's backoff). They take turns with due values (one after each device's
poll) and go before diagnostics, and only while their share of bus time is not spent (a
token bucket of bus seconds): the share keeps polling on its deadlines. Within the share,
the next request is the one of the client that had the least bus time
(:mod:`~gateway.line.engine.fair_share`): one that pipelines long reads, or opens many
connections, leaves the others their part. A request that waits too long, or finds the
queue full (and cannot take the place of a client holding more), is refused with
:class:`BusBusyError` (Modbus exception 06 to the client); nothing collides.
"""

from __future__ import annotations

import asyncio
import time
from collections import Counter
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Final

from gateway.errors import (
    BusBusyError,
    BusClosedError,
    BusTimeoutError,
    DeviceExceptionError,
    FrameError,
    GatewayError,
)
from gateway.line.engine.fair_share import FairShare, Origin
from gateway.profiles.effects import touched_by_write

if TYPE_CHECKING:
    from collections.abc import Mapping

    from gateway.line.engine.devices import DeviceState
    from gateway.line.engine.schedule import Schedule
    from gateway.line.engine.transactions import Transactions
    from gateway.wire import frames

BURST_S: Final = 2.0  # the share is kept over this window: a burst may use it at once
CREDIT_SLACK_S: Final = 1e-9  # rounding: a credit refilled to what a request needs covers it


@dataclass(frozen=True, slots=True, kw_only=True)
class SharePolicy:
    """How much of a line other masters may have.

    Example::

        SharePolicy(share=0.25, max_wait_s=2.0, max_pending=16)
    """

    share: float = 0.25  # of bus time, over a window of ``BURST_S``
    max_wait_s: float = 2.0  # a request not sent by then is refused (busy)
    max_pending: int = 16  # requests waiting on the line; more are refused at once


@dataclass(slots=True)
class ForeignStats:
    """What other masters did on one line (read by the metrics)."""

    busy_s: float = 0.0  # line time their transactions took (part of the line's busy time)
    refused: Counter[str] = field(default_factory=Counter)  # by reason: queue_full, no_share


@dataclass(slots=True)
class ForeignJob:
    """One request of another master, framed for the line, waiting for its turn."""

    device: str
    request: frames.Request
    queued_at: float
    done: asyncio.Future[frames.Response]
    origin: Origin = field(default_factory=Origin)  # whose turn it goes in
    sent_at: float | None = None  # when it got the line


class BusTimeBucket:
    """Bus seconds other masters may still spend: refilled at ``share`` per second."""

    def __init__(self, share: float, *, now: float) -> None:
        """Start full: a client's first requests need not wait."""
        self.share = share
        self.capacity_s = share * BURST_S
        self._credit_s = self.capacity_s
        self._at = now

    def credit(self, now: float) -> float:
        """Seconds left now (negative after an overspend, until it is paid back)."""
        self._credit_s = min(self.capacity_s, self._credit_s + (now - self._at) * self.share)
        self._at = now
        return self._credit_s

    def spend(self, seconds: float, now: float) -> None:
        """Take the bus time a transaction used."""
        self._credit_s = self.credit(now) - seconds

    def allows(self, seconds: float, now: float) -> bool:
        """Whether a transaction expected to take ``seconds`` may start now.

        The credit must cover it (one longer than the window, a full window): a long read
        that overdrew the share would make whoever asks next wait to pay it back.
        """
        credit = self.credit(now)
        return credit > 0 and credit >= self._need(seconds) - CREDIT_SLACK_S

    def available_at(self, now: float, seconds: float = 0.0) -> float:
        """When a transaction expected to take ``seconds`` may start (0: the credit is positive)."""
        if self.allows(seconds, now):
            return now
        if self.share <= 0:
            return float("inf")
        return now + (self._need(seconds) - self._credit_s) / self.share

    def _need(self, seconds: float) -> float:
        return max(0.0, min(seconds, self.capacity_s))


class ForeignQueue:
    """The requests of other masters on one line, served by its bus task."""

    def __init__(
        self,
        *,
        bus: str,
        devices: Mapping[str, DeviceState],
        transactions: Transactions,
        schedule: Schedule,
        wake: asyncio.Event,
    ) -> None:
        """No other master until :meth:`open` gives the line's share."""
        self.bus = bus
        self.devices = devices
        self.transactions = transactions
        self.schedule = schedule
        self.policy = SharePolicy(share=0.0)
        self.stats = ForeignStats()
        self._bucket = BusTimeBucket(0.0, now=time.monotonic())
        self._fair = FairShare()
        self._jobs: list[ForeignJob] = []
        self._wake = wake
        self.accepting = False  # False: refused as busy (not shared, or the bus stops)

    def open(self, policy: SharePolicy) -> None:
        """Let other masters in, within ``policy``."""
        self.policy = policy
        self._bucket = BusTimeBucket(policy.share, now=time.monotonic())
        self._fair = FairShare()
        self.accepting = True

    def submit(
        self, device: str, request: frames.Request, origin: Origin | None = None
    ) -> ForeignJob:
        """Queue a request for the device; :class:`BusBusyError` at once if it cannot wait.

        It goes in the turn of ``origin`` (its client's address and connection). The job's
        ``done`` holds the device's answer, or the error of the transaction
        (:class:`DeviceExceptionError`, :class:`BusTimeoutError`, a :class:`FrameError`,
        :class:`BusBusyError` when its wait ran out or a client holding fewer took its
        place, :class:`BusClosedError`).
        """
        if device not in self.devices:
            raise GatewayError(f"bus {self.bus} has no device {device!r}")
        if not self.transactions.line.is_open:
            raise BusClosedError(f"bus {self.bus}: {self.transactions.line.port} is not open")
        if not self.accepting:
            self.stats.refused["closed"] += 1
            raise BusBusyError(f"bus {self.bus} takes no requests of other masters now")
        origin = origin or Origin()
        if len(self._jobs) >= self.policy.max_pending:
            self._make_room(origin)
        done: asyncio.Future[frames.Response] = asyncio.get_running_loop().create_future()
        job = ForeignJob(
            device=device, request=request, queued_at=time.monotonic(), done=done, origin=origin
        )
        self._jobs.append(job)
        self._wake.set()
        return job

    def _make_room(self, origin: Origin) -> None:
        """Refuse the newest request of a client that holds more of the queue, or this one."""
        self.stats.refused["queue_full"] += 1
        waiting = len(self._jobs)
        displaced = self._fair.displaced(self._jobs, origin)
        if displaced is None:
            raise BusBusyError(f"bus {self.bus}: {waiting} requests already wait")
        self._jobs.remove(displaced)
        address = displaced.origin.address
        reason = (
            f"bus {self.bus}: {waiting} requests wait, most of them from {address}: "
            "this one gave its place to another client's"
        )
        _settle(displaced, BusBusyError(reason))

    def wake_at(self, wake_at: float, now: float) -> float:
        """``wake_at``, or earlier if a request may go (or time out) before.

        The request whose turn it is goes when the share covers it, and no client that had
        less is about to ask again; a device that becomes free first may bring another's
        turn.
        """
        if not self._jobs:
            return wake_at
        times = [wake_at, min(job.queued_at for job in self._jobs) + self.policy.max_wait_s]
        if (job := self._turn(now)) is not None:
            held = self._fair.held_until(job, now)
            times.append(max(held, self._bucket.available_at(now, self._expected_s(job))))
        freed = [self.devices[j.device].holds.not_before for j in self._jobs]
        times.extend(t for t in freed if t > now)
        return min(times)

    def fail_all(self, exc: Exception) -> None:
        """Fail every waiting request (the port is gone, or the bus stops)."""
        for job in self._jobs:
            _settle(job, exc)
        self._jobs.clear()

    def fail_device(self, device: str, exc: Exception) -> None:
        """Fail the waiting requests for one device (a reload removed it)."""
        for job in [job for job in self._jobs if job.device == device]:
            _settle(job, exc)
            self._jobs.remove(job)

    def waiting(self) -> bool:
        """Whether another master's request is queued (asked before :meth:`run_next`)."""
        return bool(self._jobs)

    async def run_next(self, now: float) -> bool:
        """Send one request if its device is free and the share allows; whether one went."""
        if not self._jobs:
            return False
        self._jobs[:] = [job for job in self._jobs if not job.done.cancelled()]  # clients gone
        self._expire(now)
        self._refuse_offline()
        job = self._turn(now)
        if job is None or self._fair.held_until(job, now) > now:
            return False
        if not self._bucket.allows(self._expected_s(job), now):
            # The others wait too: they would spend the credit its turn waits for.
            return False
        self._jobs.remove(job)
        await self._send(self.devices[job.device], job)
        return True

    def _turn(self, now: float) -> ForeignJob | None:
        """The request whose turn it is, of those whose device is free now."""
        devices = self.devices
        return self._fair.pick([j for j in self._jobs if devices[j.device].holds.not_before <= now])

    def _expected_s(self, job: ForeignJob) -> float:
        """The bus time the request will take at least: both frames and the gap before it."""
        nbytes = len(job.request.frame) + _answer_bytes(job.request)
        state = self.devices[job.device]
        transactions = self.transactions
        return transactions.line.format.wire_s(nbytes) + transactions.requests.gap_s(state)

    def _expire(self, now: float) -> None:
        """Refuse the requests that waited longer than the policy allows."""
        limit = now - self.policy.max_wait_s
        for job in [j for j in self._jobs if j.queued_at <= limit]:
            self._jobs.remove(job)
            self.stats.refused["no_share"] += 1
            wait = self.policy.max_wait_s
            _settle(job, BusBusyError(f"bus {self.bus}: no bus time within {wait:g} s"))

    def _refuse_offline(self) -> None:
        """Answer the requests for offline devices at once, without the wire.

        The device's backoff holds for every master: the gateway's probes find it again,
        and another master's requests would only wait out its timeout.
        """
        for job in [j for j in self._jobs if self.devices[j.device].presence.online is False]:
            self._jobs.remove(job)
            _settle(job, BusTimeoutError(f"device {job.device} is offline"))

    async def _send(self, state: DeviceState, job: ForeignJob) -> None:
        request = job.request
        line = self.transactions.line
        job.sent_at = time.monotonic()
        busy_before = line.stats.busy_s
        if request.is_write:
            self.transactions.cache.forget(state.target.name, request.address, request.count)
        try:
            response = await self.transactions.transact(state, request, _answer_bytes(request))
        except DeviceExceptionError as exc:
            await self.transactions.availability.answered(state, "answered")
            _settle(job, exc)
        except (BusTimeoutError, FrameError) as exc:
            await self.transactions.availability.failed(state, str(exc))
            _settle(job, exc)
        except BusClosedError as exc:
            _settle(job, exc)
            raise
        else:
            await self.transactions.availability.answered(state, "answered")
            if not request.is_write:
                self.transactions.cache.store(
                    state.target.name, request.address, response.registers, time.monotonic()
                )
            _settle(job, response)
        finally:
            now = time.monotonic()
            if request.is_write:
                # The device's post-write wait holds whoever wrote (H10/H20 6.1.5); what
                # was written is read again, in case values depend on it (units, format).
                wait = state.profile.post_write_wait(request.address, request.count)
                state.holds.hold_until(now + wait)
                self.schedule.reread(state, request.address, request.count, now)
                for address, count in touched_by_write(
                    state.profile, request.address, request.count
                ):
                    self.schedule.reread(state, address, count, now)
            # The line's busy time (request to answer or timeout; counted in the line's
            # busy time too), and for the share the silent gap before it as well.
            busy = line.stats.busy_s - busy_before
            spent = busy + self.transactions.requests.gap_s(state)
            self._bucket.spend(spent, now)
            self._fair.charge(job.origin, spent, now)
            self.stats.busy_s += busy


def _settle(job: ForeignJob, outcome: frames.Response | Exception) -> None:
    """Hand the outcome to the waiting client, unless it stopped waiting (it disconnected)."""
    if job.done.done():
        return
    if isinstance(outcome, Exception):
        job.done.set_exception(outcome)
    else:
        job.done.set_result(outcome)


def _answer_bytes(request: frames.Request) -> int:
    """The length of the device's answer, for its timeout."""
    return 8 if request.is_write else 5 + 2 * request.count
