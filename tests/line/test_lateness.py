"""What made a poll late: the line busy, or the gateway's process, and then who or why.

The log line is what an operator reads first; it must blame the right thing. The first
tests give :class:`Lateness` a real line's counters and a real event loop that is made
busy (``time.sleep`` on the loop, as any work that never yields does); the next run a bus
worker on the simulator with a sink that holds the loop, computing or blocked (as a
process that is not scheduled is), and one holds the process while a request of its is
answered by a simulator in a process of its own, as a starved gateway on a plant is.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import re
import time
from typing import TYPE_CHECKING

import pytest

from gateway.line.engine.lateness import RAN_SHARE, Lateness, LoopWatch
from gateway.line.engine.schedule import Late
from gateway.line.engine.worker import BusWorker
from gateway.line.stats import ErrorKind
from gateway.line.transports.serial_line import SerialLine
from gateway.wire.timing import LineFormat
from tests.rigs import ListSink, rig, simulate_process, target

# The held loops and the late polls are measured in CPU time and on the clock: alone.
pytestmark = pytest.mark.timing

if TYPE_CHECKING:
    from collections.abc import Callable, Sequence
    from pathlib import Path

    from gateway.line.samples import DeviceEvent, Sample

SHARED_BUS = "answering other masters on the shared bus"


def _line() -> SerialLine:
    return SerialLine(port="/dev/null", line=LineFormat(baudrate=9600, parity="E", stopbits=1))


async def _explain_since(lateness: Lateness, started: float) -> str:
    """Why oxygen (every 0.1 s) is late since ``started``; the watch and the line closed."""
    now = time.monotonic()
    text = lateness.explain(Late(point="oxygen", lag_s=now - started, interval_s=0.1), now)
    assert lateness.watch is not None
    lateness.watch.detach()
    await lateness.line.close()
    return text


async def test_a_line_busy_all_along_cannot_keep_up() -> None:
    line = _line()
    watch = LoopWatch(asyncio.get_running_loop())
    lateness = Lateness(line, watch)
    now = time.monotonic()
    lateness.mark(now - 1.0)
    line.stats.busy_s += 0.8  # transactions took 0.8 s of the second since
    text = lateness.explain(Late(point="oxygen", lag_s=1.0, interval_s=0.5), now)
    await line.close()
    assert text == (
        "the line cannot keep up: oxygen is 1.00 s late (interval 0.50 s); "
        "it carried transactions 0.80 s of those 1.00 s; see the poll lag metric"
    )


async def test_an_idle_line_and_a_busy_loop_blame_the_process_and_name_who_held_it() -> None:
    line = _line()
    watch = LoopWatch(asyncio.get_running_loop())
    watch.attach()
    lateness = Lateness(line, watch)
    await asyncio.sleep(0.1)
    started = time.monotonic()
    lateness.mark(started)
    time.sleep(0.4)  # noqa: ASYNC251 - the point: the loop held, as a flood that never yields
    watch.charge(SHARED_BUS, 0.4, time.monotonic())
    await asyncio.sleep(0.1)  # the watch's timer runs, late
    text = await _explain_since(lateness, started)
    match = re.fullmatch(
        r"oxygen is 0\.5\d s late \(interval 0\.10 s\) while the line was idle "
        r"\(0\.00 s busy of 0\.5\d s\): the gateway's process was busy, its event loop "
        r"(0\.\d\d) s late, 0\.40 s of it answering other masters on the shared bus",
        text,
    )
    assert match is not None, text
    # The timer was due somewhere in the held 0.4 s: late by that, less up to a tick.
    assert 0.4 - 0.05 - 0.02 <= float(match[1]) <= 0.5


async def test_a_held_loop_with_no_cpu_sample_before_it_is_held_without_a_verdict() -> None:
    """The watch began at the hold: the CPU used over it is not known, so no cause is
    named (not "busy", not "waited for a CPU")."""
    line = _line()
    watch = LoopWatch(asyncio.get_running_loop())
    lateness = Lateness(line, watch)
    started = time.monotonic()
    lateness.mark(started)
    watch.attach()  # its timer's first sample comes after the hold
    time.sleep(0.3)  # noqa: ASYNC251 - the point: the loop held
    await asyncio.sleep(0.1)
    text = await _explain_since(lateness, started)
    assert re.fullmatch(
        r"oxygen is 0\.\d\d s late \(interval 0\.10 s\) while the line was idle \(0\.00 s busy "
        r"of 0\.\d\d s\): the gateway's process was held, its event loop 0\.[23]\d s late",
        text,
    ), text


async def test_an_idle_line_and_a_loop_on_time_say_the_bus_task_waited() -> None:
    line = _line()
    watch = LoopWatch(asyncio.get_running_loop())
    watch.attach()
    lateness = Lateness(line, watch)
    started = time.monotonic()
    lateness.mark(started)
    await asyncio.sleep(0.3)  # the loop free, the bus task waiting on something
    text = await _explain_since(lateness, started)
    assert re.fullmatch(
        r"oxygen is 0\.3\d s late \(interval 0\.10 s\) while the line was idle \(0\.00 s busy "
        r"of 0\.3\d s\) and the event loop on time \(0\.0\d s late\): the bus task waited on "
        r"something else \(its sinks, a pause\)",
        text,
    ), text


def _only_warning(pattern: str, warnings: list[str]) -> re.Match[str]:
    """The one warning of a late poll, matched whole by ``pattern``."""
    assert len(warnings) == 1, warnings
    match = re.fullmatch(pattern, warnings[0])
    assert match is not None, warnings[0]
    return match


def _compute(seconds: float) -> None:
    """Hold the loop as code that computes does: until it has used ``seconds`` of CPU."""
    end = time.process_time() + seconds
    while time.process_time() < end:
        pass


def _block(seconds: float) -> None:
    """Hold the loop as a process that is not scheduled does, or a call that blocks."""
    time.sleep(seconds)  # the point: the loop held, no CPU used


class _HoldingSink:
    """A sink that, once, holds the event loop (``hold``) for ``hold_s``."""

    def __init__(self, after: int, hold_s: float, hold: Callable[[float], None]) -> None:
        self.calls = 0
        self.after = after
        self.hold_s = hold_s
        self.hold = hold
        self.held_s = 0.0  # how long the loop was held, by the monotonic clock
        self.done = asyncio.Event()

    async def publish(self, samples: Sequence[Sample]) -> None:  # noqa: ARG002
        self.calls += 1
        if self.calls == self.after:
            start = time.monotonic()
            self.hold(self.hold_s)
            self.held_s = time.monotonic() - start
            self.done.set()

    async def device_event(self, event: DeviceEvent) -> None:
        pass


async def _late_warnings(
    tmp_path: Path, caplog: pytest.LogCaptureFixture, hold: Callable[[float], None]
) -> tuple[list[str], float]:
    """The warnings of late polls around one hold of the loop, and how long it was held."""
    caplog.set_level(logging.WARNING, logger="gateway.line.engine.poll")
    devices = [{"profile": "jumo-tecline-cl2", "address": 20, "animate": False}]
    targets = [target("cl2", "jumo-tecline-cl2", 20, interval=0.2)]
    sink = _HoldingSink(after=8, hold_s=1.0, hold=hold)
    async with rig(tmp_path, devices, targets) as bench:
        bench.worker.sinks.append(sink)
        polling = asyncio.create_task(bench.worker.run())
        async with asyncio.timeout(30):  # however long a busy machine makes the hold
            await sink.done.wait()
        await asyncio.sleep(1.0)  # the late poll, and polls on time after it
        polling.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await polling
    return [r.getMessage() for r in caplog.records if "late" in r.getMessage()], sink.held_s


IDLE_AND_HELD = (
    r"line1/cl2: \w+ is (?P<lag>\d\.\d\d) s late \(interval 0\.20 s\) while the line was "
    r"idle \((?P<busy>\d\.\d\d) s busy of (?P=lag) s\): "
)


@pytest.mark.line
async def test_a_poll_made_late_by_a_loop_held_computing_blames_the_process_busy(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """A second of CPU on the loop: busy. On a machine short of CPU the same second takes
    longer by the clock, and the process also waited for a CPU; from some 1.3 s for the
    second (RAN_SHARE), that is what the log says, and it is checked as such."""
    warnings, held_s = await _late_warnings(tmp_path, caplog, _compute)
    match = _only_warning(
        IDLE_AND_HELD + r"the gateway's process was (?P<verdict>busy|held), its event loop "
        r"(?P<loop>\d\.\d\d) s late(?:, using| while it used) (?P<cpu>\d\.\d\d) s of CPU.*",
        warnings,
    )
    lag, busy, loop, cpu = (float(match[name]) for name in ("lag", "busy", "loop", "cpu"))
    # Late by the part of the hold after its deadline; the loop late as much.
    assert held_s - 0.2 - 0.2 <= lag <= held_s + 0.1
    assert busy < 0.2 * lag
    assert loop >= lag - 0.1
    assert cpu >= 1.0  # the held second of CPU, and the polls around it
    if held_s <= 1.1:  # the second of CPU took a second: nothing else ran
        assert match["verdict"] == "busy", warnings[0]
    else:
        assert match["verdict"] == ("busy" if cpu >= RAN_SHARE * loop else "held"), warnings[0]


@pytest.mark.line
async def test_a_poll_made_late_by_a_loop_held_not_running_says_it_waited_for_a_cpu(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    warnings, held_s = await _late_warnings(tmp_path, caplog, _block)
    match = _only_warning(
        IDLE_AND_HELD + r"the gateway's process was held, its event loop (?P<loop>\d\.\d\d) s "
        r"late while it used (?P<cpu>\d\.\d\d) s of CPU: it waited for a CPU \(a busy "
        r"machine, or a CPU quota too small: systemd's CPUQuota=, a container's --cpus\) or "
        r"in a call that blocked \(a slow disk\)",
        warnings,
    )
    lag, loop, cpu = (float(match[name]) for name in ("lag", "loop", "cpu"))
    assert held_s - 0.2 - 0.2 <= lag <= held_s + 0.1
    assert loop >= lag - 0.1
    assert cpu < 0.5 * loop  # a few polls' worth, not the held second


@pytest.mark.line
async def test_a_process_held_while_its_request_is_answered_is_not_a_line_that_cannot_keep_up(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """The starved process of a plant: its request is on the wire, the sensor (a process
    of its own) answers, and the gateway reads the answer only when it runs again. The
    transaction lasted the whole hold, so the line looks busy all along; the log must
    still blame the process and say it did not run, not "the line cannot keep up"."""
    caplog.set_level(logging.WARNING, logger="gateway.line.engine.poll")
    simulated = (
        "line: {baudrate: 38400, parity: E, stopbits: 1}\n"
        "devices:\n  - {profile: jumo-tecline-cl2, address: 20, animate: false}\n"
    )
    with simulate_process(tmp_path, simulated) as (port, _):
        line = SerialLine(port=str(port), line=LineFormat(baudrate=38400, parity="E", stopbits=1))
        targets = [target("cl2", "jumo-tecline-cl2", 20, interval=0.2)]
        worker = BusWorker(name="line1", line=line, devices=targets, sinks=[ListSink()])
        held: list[int] = []

        async def hold_in_the_tenth_transaction() -> None:
            # Polled: the hold must come between the request's write and its answer's read.
            while sum(line.stats.requests.values()) < 10:  # noqa: ASYNC110
                await asyncio.sleep(0.0005)
            held.append(sum(line.stats.requests.values()))
            _block(1.0)  # the request is out; its answer comes while the process is held

        holder = asyncio.create_task(hold_in_the_tenth_transaction())
        polling = asyncio.create_task(worker.run())
        await asyncio.sleep(3.0)
        polling.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await polling
        await holder
        await line.close()
    assert held == [10]
    timeouts = sum(n for (_, kind), n in line.stats.errors.items() if kind == ErrorKind.TIMEOUT)
    assert timeouts == 0  # the answer was read after the hold, as a starved process reads it
    warnings = [r.getMessage() for r in caplog.records if "late" in r.getMessage()]
    match = _only_warning(
        r"line1/cl2: \w+ is (?P<lag>\d\.\d\d) s late \(interval 0\.20 s\), "
        r"(?P<busy>\d\.\d\d) s of it in transactions: the gateway's process was held, its "
        r"event loop (?P<loop>\d\.\d\d) s late while it used (?P<cpu>\d\.\d\d) s of CPU: "
        r"it waited for a CPU .*",
        warnings,
    )
    lag, busy, loop, cpu = (float(match[name]) for name in ("lag", "busy", "loop", "cpu"))
    assert 0.8 - 0.2 <= lag <= 1.0 + 0.1
    assert busy >= 0.5 * lag  # what read as "the line cannot keep up" before
    assert loop >= 0.5 * lag
    assert cpu < 0.5 * loop


@pytest.mark.line
async def test_a_poll_made_late_by_the_window_after_a_timeout_says_the_device_was_held(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """After a request it did not answer, nothing goes to the device for its late answer's
    window (1 s): its next poll is late by about that, with the line idle and the loop on
    time. The log says the device was held, not that the bus task waited on something."""
    caplog.set_level(logging.WARNING, logger="gateway.line.engine.poll")
    silent = {"animate": False, "faults": {"silences": [(1.0, 0.1)]}}
    devices = [{"profile": "jumo-tecline-cl2", "address": 20, **silent}]
    targets = [target("cl2", "jumo-tecline-cl2", 20, interval=0.2)]
    async with rig(tmp_path, devices, targets) as bench:
        await bench.run_for(3.0)
        timeouts = sum(
            n for (_, kind), n in bench.line.stats.errors.items() if kind == ErrorKind.TIMEOUT
        )
    assert timeouts >= 1
    warnings = [r.getMessage() for r in caplog.records if " s late (interval" in r.getMessage()]
    match = _only_warning(
        r"line1/cl2: \w+ is (?P<lag>\d\.\d\d) s late \(interval 0\.20 s\) while the line was "
        r"idle \((?P<busy>0\.\d\d) s busy of (?P=lag) s\) and the event loop on time "
        r"\(0\.0\d s late\): nothing was to be sent to the device for (?P<held>\d\.\d\d) s "
        r"of it \(the window for a late answer after a transaction that failed, see the warning before; or the "
        r"wait after a write\)",
        warnings,
    )
    lag, busy, held = (float(match[name]) for name in ("lag", "busy", "held"))
    # The window after the failed transaction (and its retry), less the interval it overlaps.
    assert 1.0 - 0.2 - 0.1 <= lag <= 1.0 + busy + 0.1
    assert lag - busy - 0.1 <= held <= lag - busy + 0.01  # the idle time, nearly all held


async def test_while_every_worker_sleeps_the_watch_rests_and_the_sleeper_measures_the_loop() -> (
    None
):
    """The watch's timer does not wake an idle loop: the sleeping worker's own wake tells
    how late the loop ran it, once (the resting timer adds nothing on top)."""
    watch = LoopWatch(asyncio.get_running_loop())
    watch.attach()
    start = time.monotonic()
    watch.asleep()
    due = start + 0.05
    time.sleep(0.3)  # noqa: ASYNC251 - the point: the loop held past the sleeper's due time
    await asyncio.sleep(0.1)  # a timer of the watch would run now, late
    woke = time.monotonic()
    watch.awake(due, woke)
    stalled = watch.since(start).stalled_s
    watch.detach()
    # Late by the time from its due to its wake: the hold past it, and the loop's free 0.1 s.
    assert woke - due - 0.001 <= stalled <= woke - due + 0.001
    assert 0.3 <= stalled < 0.5  # a timer of its own would have added some 0.3 s again


async def test_while_one_worker_is_awake_the_watch_keeps_time_and_a_sleeper_adds_nothing() -> None:
    loop = asyncio.get_running_loop()
    watch = LoopWatch(loop)
    watch.attach()
    watch.attach()  # a second worker, awake
    await asyncio.sleep(0.06)
    start = time.monotonic()
    watch.asleep()
    time.sleep(0.3)  # noqa: ASYNC251 - the loop held
    await asyncio.sleep(0.06)  # the watch's timer runs, late
    watch.awake(start, time.monotonic())  # late too, by more: not counted again
    stalled = watch.since(start).stalled_s
    watch.detach()
    watch.detach()
    assert 0.3 - 0.05 - 0.02 <= stalled <= 0.3 + 0.02  # the watch's timer alone
