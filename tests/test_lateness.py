"""What made a poll late: the line busy, or the gateway's process, and then who.

The log line is what an operator reads first; it must blame the right thing. The first
tests give :class:`Lateness` a real line's counters and a real event loop that is made
busy (``time.sleep`` on the loop, as any work that never yields does); the last runs a
bus worker on the simulator with a sink that holds the loop.
"""

from __future__ import annotations

import asyncio
import logging
import re
import time
from typing import TYPE_CHECKING

from gateway.line.lateness import Lateness, LoopWatch
from gateway.line.schedule import Late
from gateway.line.serial_line import SerialLine
from gateway.wire.timing import LineFormat
from tests.rigs import rig, target

if TYPE_CHECKING:
    from collections.abc import Sequence
    from pathlib import Path

    import pytest

    from gateway.line.samples import DeviceEvent, Sample

SHARED_BUS = "answering other masters on the shared bus"


def _line() -> SerialLine:
    return SerialLine(port="/dev/null", line=LineFormat(baudrate=9600, parity="E", stopbits=1))


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
    now = time.monotonic()
    text = lateness.explain(Late(point="oxygen", lag_s=now - started, interval_s=0.1), now)
    watch.detach()
    await line.close()
    match = re.fullmatch(
        r"oxygen is 0\.5\d s late \(interval 0\.10 s\) while the line was idle "
        r"\(0\.00 s busy of 0\.5\d s\): the gateway's process was busy, its event loop "
        r"(0\.\d\d) s late, 0\.40 s of it answering other masters on the shared bus",
        text,
    )
    assert match is not None, text
    # The timer was due somewhere in the held 0.4 s: late by that, less up to a tick.
    assert 0.4 - 0.05 - 0.02 <= float(match[1]) <= 0.5


async def test_an_idle_line_and_a_loop_on_time_say_the_bus_task_waited() -> None:
    line = _line()
    watch = LoopWatch(asyncio.get_running_loop())
    watch.attach()
    lateness = Lateness(line, watch)
    started = time.monotonic()
    lateness.mark(started)
    await asyncio.sleep(0.3)  # the loop free, the bus task waiting on something
    now = time.monotonic()
    text = lateness.explain(Late(point="oxygen", lag_s=now - started, interval_s=0.1), now)
    watch.detach()
    await line.close()
    assert re.fullmatch(
        r"oxygen is 0\.3\d s late \(interval 0\.10 s\) while the line was idle \(0\.00 s busy "
        r"of 0\.3\d s\) and the event loop on time \(0\.0\d s late\): the bus task waited on "
        r"something else \(its sinks, a pause\)",
        text,
    ), text


class _HoldingSink:
    """A sink that, once, holds the event loop as a slow piece of code would."""

    def __init__(self, after: int, hold_s: float) -> None:
        self.calls = 0
        self.after = after
        self.hold_s = hold_s

    async def publish(self, samples: Sequence[Sample]) -> None:  # noqa: ARG002
        self.calls += 1
        if self.calls == self.after:
            time.sleep(self.hold_s)  # noqa: ASYNC251 - the point: the loop held

    async def device_event(self, event: DeviceEvent) -> None:
        pass


async def test_a_poll_made_late_by_a_held_loop_blames_the_process_not_the_line(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.WARNING, logger="gateway.line.worker")
    devices = [{"profile": "jumo-tecline-cl2", "address": 20, "animate": False}]
    targets = [target("cl2", "jumo-tecline-cl2", 20, interval=0.2)]
    sink = _HoldingSink(after=8, hold_s=1.0)
    async with rig(tmp_path, devices, targets) as bench:
        bench.worker.sinks.append(sink)
        await bench.run_for(3.0)
    warnings = [r.getMessage() for r in caplog.records if "late" in r.getMessage()]
    assert len(warnings) == 1, warnings
    match = re.fullmatch(
        r"line1/cl2: \w+ is (?P<lag>\d\.\d\d) s late \(interval 0\.20 s\) while the line was "
        r"idle \((?P<busy>\d\.\d\d) s busy of (?P=lag) s\): the gateway's process was busy, "
        r"its event loop (?P<loop>\d\.\d\d) s late",
        warnings[0],
    )
    assert match is not None, warnings[0]
    lag, busy, loop = (float(match[name]) for name in ("lag", "busy", "loop"))
    # Late by the part of the held second after its deadline; the loop late as much.
    assert 0.8 - 0.2 <= lag <= 1.0 + 0.1
    assert busy < 0.2 * lag
    assert loop >= lag - 0.1


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
