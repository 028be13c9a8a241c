"""Why a poll was late: the line busy with transactions, or the gateway's process held.

A poll is late when its deadline passed before the bus task got to it. Either the line
carried transactions all along (it cannot keep up: too many points for its speed, a
device that times out), or the event loop that runs every bus, sink and server did not
run on time, or the device was held back (the window for a late answer after a failed
transaction, the wait after a write), or the bus task waited on something else. The
remedies differ (fewer points or a faster line; a limit on who loads the process; more
CPU for the service; the device's timeout), so the log says which, from three measures
over the time the poll was late: the line's busy time (``LineStats.busy_s``), how late
the event loop ran a timer (:class:`LoopWatch`), and the CPU the process used meanwhile
(and the device's own waits, from the worker). Work that knows it holds the loop (the
shared bus answering requests itself) charges its time to the watch, so the report
names it.

A late loop comes first: a transaction lasts until its answer is read, so while the
process does not run (a machine short of CPU, a CPU quota spent: the process is not
scheduled at all) the line's busy time grows with the stall, and a line that had time to
spare would read as one that cannot keep up. The CPU used tells the two kinds of stall
apart: a process that held its loop computing used about as much CPU as the stall lasted;
one that was not scheduled, or sat in a call that blocked, used less.
"""

from __future__ import annotations

import asyncio
import time
import weakref
from array import array
from collections import defaultdict, deque
from dataclasses import dataclass, field
from itertools import chain
from typing import TYPE_CHECKING, Final

if TYPE_CHECKING:
    from gateway.line.boundary import Line
    from gateway.line.engine.schedule import Late

TICK_S: Final = 0.05  # the watch's timer; 20 wakes a second cost ~1 ms of CPU
STALL_MIN_S: Final = 0.002  # a timer this much late: the loop was busy, not just scheduling
SLOT_S: Final = 0.1  # charges are summed per source in slots this long
HISTORY: Final = 4096  # stalls, charge slots and busy marks kept (minutes of history)
LINE_BUSY_SHARE: Final = 0.5  # the line carried transactions this much of the lateness: its fault
LOOP_BUSY_SHARE: Final = 0.5  # the loop was late this much of the line's idle time: the process's
LOOP_HELD_SHARE: Final = 0.5  # the loop was late this much of the lateness: not the line's fault
NAMED_SHARE: Final = 0.5  # a source charged this much of the loop's lateness is named
# CPU used under this much of the loop's lateness: the process did not run for much of it.
# A process held by a CPU quota of 40 % uses some 0.67 s of CPU per second its loop is
# late; one that computes while another process takes a fifth of its core, some 0.8.
RAN_SHARE: Final = 0.75
DEVICE_HELD_SHARE: Final = 0.5  # the device was held back this much of the idle time: its wait
HELD_DEVICE: Final = (
    "nothing was to be sent to the device for {held:.2f} s of it (the window for a late "
    "answer after a transaction that failed, see the warning before; or the wait after a write)"
)
CPU_QUOTA_HINT: Final = (
    "it waited for a CPU (a busy machine, or a CPU quota too small: systemd's CPUQuota=, "
    "a container's --cpus) or in a call that blocked (a slow disk)"
)


@dataclass(frozen=True, slots=True)
class LoopLoad:
    """How late the event loop ran, over a stretch of time, and who said it held it.

    ``cpu_s`` is the CPU the process used over about that stretch, from the watch's last
    sample before it (None when the watch has none that old).
    """

    stalled_s: float
    charged_s: dict[str, float] = field(default_factory=dict)
    cpu_s: float | None = None


@dataclass(slots=True, kw_only=True)
class _Charge:
    """Time one source held the loop within one slot (summed: a flood is many small ones)."""

    slot: int
    source: str
    seconds: float


class LoopWatch:
    """How late one event loop runs a timer; time that work charges to it, by source.

    One per event loop (:func:`loop_watch`); its timer runs while a bus worker runs,
    except while every worker sleeps on a timer of its own (:meth:`asleep`): then each
    measures how late the loop woke it (:meth:`awake`), which is all of the loop's
    lateness that can make a poll late, and the watch's timer does not wake the loop
    20 times a second for nothing (at one poll a second, that was 2.5 wakes per
    transaction; at 9600 baud some 50 µs of CPU per transaction).

    A serial line's timer counts as such a sleep all the while its worker polls: it is
    set no more than :attr:`look_s` ahead while the worker is awake, and says how late
    each of its firings ran (:meth:`late`; ``line/transports/timer``). So the watch's
    own timer is not set and cancelled in every transaction.
    """

    look_s: Final = TICK_S  # how far ahead a line's timer looking for the watch is set

    def __init__(self, loop: asyncio.AbstractEventLoop) -> None:
        """Idle until :meth:`attach`."""
        self._loop = loop
        self._users = 0
        self._sleepers = 0  # workers in a timed wait of their own
        self._handle: asyncio.TimerHandle | None = None
        self._due = 0.0
        self._stalls: deque[tuple[float, float]] = deque(maxlen=HISTORY)  # (end, seconds)
        self._charges: deque[_Charge] = deque(maxlen=HISTORY)
        # The process's CPU time (when, cpu_s) at the watch's ticks and as the loop goes
        # idle, at most once a tick: a base for the CPU used over a late poll.
        self._cpu: deque[tuple[float, float]] = deque(maxlen=HISTORY)

    def attach(self) -> None:
        """A worker runs: watch (the first starts the timer)."""
        self._users += 1
        if self._users == 1:
            self._arm(time.monotonic())

    def detach(self) -> None:
        """A worker stopped: the last one stops the timer."""
        self._users = max(0, self._users - 1)
        if self._users == 0 and self._handle is not None:
            self._handle.cancel()
            self._handle = None

    def asleep(self) -> None:
        """A worker waits on a timer of its own; the last to do so lets the watch's rest."""
        self._sleepers += 1
        if self._sleepers >= self._users and self._handle is not None:
            self._handle.cancel()
            self._handle = None
            self._sample_cpu(time.monotonic())

    def awake(self, due: float, now: float) -> None:
        """A worker's timed wait due at ``due`` ended at ``now`` (early, when woken by work).

        While the watch's timer rested, how late the loop woke the worker is the loop's
        lateness; the timer runs again while the worker is awake.
        """
        self._sleepers = max(0, self._sleepers - 1)
        if self._handle is None and self._users:
            self._stalled(due, now)
            if self._sleepers < self._users:  # a line's timer may look for the others
                self._arm(now)

    def late(self, due: float, now: float) -> None:
        """A line's timer looking for the watch, due at ``due``, fired at ``now``.

        Counted as the loop's lateness while the watch's own timer rests, as a sleeper's
        wake is (:meth:`awake`); the CPU is sampled at most once a tick, as the loop goes
        idle.
        """
        if self._handle is None:
            self._stalled(due, now)
        self._sample_cpu(now)

    def _stalled(self, due: float, now: float) -> None:
        """A timer due at ``due`` ran at ``now``: a stall of the loop, if late enough."""
        late = now - due
        if late > STALL_MIN_S:
            self._stalls.append((now, late))

    def _arm(self, now: float) -> None:
        self._due = now + TICK_S
        self._handle = self._loop.call_later(TICK_S, self._tick)

    def _tick(self) -> None:
        now = time.monotonic()
        self._stalled(self._due, now)
        self._sample_cpu(now)
        self._arm(now)

    def _sample_cpu(self, now: float) -> None:
        """A base for the CPU used over a late poll, at most one a tick.

        ``process_time`` is a system call (no vDSO serves a process's CPU clock): once per
        sleep was one per transaction, 1-2 % of its CPU on a virtual machine.
        """
        cpu = self._cpu
        if not cpu or now - cpu[-1][0] >= TICK_S:
            cpu.append((now, time.process_time()))

    def charge(self, source: str, seconds: float, now: float) -> None:
        """``source`` held the loop for ``seconds`` just now."""
        slot = int(now / SLOT_S)
        last = self._charges[-1] if self._charges else None
        if last is not None and last.slot == slot and last.source == source:
            last.seconds += seconds
        else:
            self._charges.append(_Charge(slot=slot, source=source, seconds=seconds))

    def since(self, start: float) -> LoopLoad:
        """How late the loop ran from ``start`` until now, and who charged time meanwhile.

        With the CPU the process used since the watch's last sample before ``start``.
        """
        stalled = sum(min(late, end - start) for end, late in self._stalls if end > start)
        charged: defaultdict[str, float] = defaultdict(float)
        for charge in self._charges:
            if (charge.slot + 1) * SLOT_S > start:
                charged[charge.source] += charge.seconds
        base: float | None = None
        for when, cpu in self._cpu:
            if when > start:
                break
            base = cpu
        cpu_s = None if base is None else time.process_time() - base
        return LoopLoad(stalled_s=stalled, charged_s=dict(charged), cpu_s=cpu_s)


_WATCHES: weakref.WeakKeyDictionary[asyncio.AbstractEventLoop, LoopWatch] = (
    weakref.WeakKeyDictionary()
)


def loop_watch() -> LoopWatch:
    """The watch of the running event loop (made at the first call)."""
    loop = asyncio.get_running_loop()
    watch = _WATCHES.get(loop)
    if watch is None:
        watch = _WATCHES[loop] = LoopWatch(loop)
    return watch


class Lateness:
    """One line's busy time as it went, to tell what made a poll late (:meth:`explain`)."""

    def __init__(self, line: Line, watch: LoopWatch | None = None) -> None:
        """Marks of ``line``'s busy time; the loop's ``watch`` is found when first needed."""
        self.line = line
        self.watch = watch
        # The marks (when, busy_s) as two rings of plain doubles, HISTORY long, not a deque
        # of tuples: a line marks every poll, some 40 times a second, and 4096 tuples of two
        # floats held about half a MiB per line (8 MiB at 16 buses) once full, a few
        # minutes after the start; 64 KiB as doubles.
        self._when = array("d")
        self._busy = array("d")
        self._oldest = 0  # once full: the index of the oldest mark, the next overwritten

    def mark(self, now: float) -> None:
        """The line's busy time now (the worker marks every poll)."""
        busy = self.line.stats.busy_s
        if len(self._when) < HISTORY:
            self._when.append(now)
            self._busy.append(busy)
            return
        oldest = self._oldest
        self._when[oldest] = now
        self._busy[oldest] = busy
        self._oldest = (oldest + 1) % HISTORY

    def busy_since(self, start: float) -> float:
        """Seconds the line carried transactions from about ``start`` until now."""
        n = self._oldest
        whens, busies = self._when, self._busy
        before = busies[n] if whens else self.line.stats.busy_s
        # Oldest first: from the oldest mark to the end, then from the start of the ring.
        marks = chain(
            zip(whens[n:], busies[n:], strict=True), zip(whens[:n], busies[:n], strict=True)
        )
        for when, busy in marks:
            if when > start:
                break
            before = busy
        return self.line.stats.busy_s - before

    def explain(self, late: Late, now: float, *, held_until: float = 0.0) -> str:
        """What made ``late`` late, in words for the log.

        ``held_until``: the end of the device's last wait (after a write, or the window for
        a late answer after a failed transaction), when nothing was to be sent to it.
        """
        lag = late.lag_s
        head = f"{late.point} is {lag:.2f} s late (interval {late.interval_s:.2f} s)"
        # The mark before the lateness began may fall inside a transaction: at most the lag.
        busy = min(lag, self.busy_since(now - lag))
        watch = self.watch or loop_watch()
        load = watch.since(now - lag)
        if busy >= LINE_BUSY_SHARE * lag:
            if load.stalled_s < LOOP_HELD_SHARE * lag:
                return (
                    f"the line cannot keep up: {head}; it carried transactions {busy:.2f} s "
                    f"of those {lag:.2f} s; see the poll lag metric"
                )
            # The transactions lasted as long as the process took to read their answers.
            return self._held(f"{head}, {busy:.2f} s of it in transactions", load)
        idle = f"{head} while the line was idle ({busy:.2f} s busy of {lag:.2f} s)"
        if load.stalled_s < LOOP_BUSY_SHARE * (lag - busy):
            on_time = f"{idle} and the event loop on time ({load.stalled_s:.2f} s late)"
            # Of the time the line was idle: the failed transactions came before the window.
            held = min(lag - busy, max(0.0, held_until - (now - lag)))
            if held >= DEVICE_HELD_SHARE * (lag - busy):
                return f"{on_time}: {HELD_DEVICE.format(held=held)}"
            return f"{on_time}: the bus task waited on something else (its sinks, a pause)"
        return self._held(idle, load)

    @staticmethod
    def _held(context: str, load: LoopLoad) -> str:
        """Why the loop ran late: work that named itself, the process's own, or neither.

        Neither: the process did not run (not scheduled, or in a call that blocked).
        """
        stalled = f"its event loop {load.stalled_s:.2f} s late"
        if load.charged_s:
            source, seconds = max(load.charged_s.items(), key=lambda item: item[1])
            if seconds >= NAMED_SHARE * load.stalled_s:
                named = f"{seconds:.2f} s of it {source}"
                return f"{context}: the gateway's process was busy, {stalled}, {named}"
        if load.cpu_s is None:
            return f"{context}: the gateway's process was held, {stalled}"
        # Had it computed all the while its loop was late, it would have used that much CPU
        # at least (more with its other work); much less, and it did not run for part of it.
        if load.cpu_s < RAN_SHARE * load.stalled_s:
            return (
                f"{context}: the gateway's process was held, {stalled} while it used "
                f"{load.cpu_s:.2f} s of CPU: {CPU_QUOTA_HINT}"
            )
        return (
            f"{context}: the gateway's process was busy, {stalled}, using {load.cpu_s:.2f} s of CPU"
        )
