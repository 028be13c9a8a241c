"""The bus engine against the simulator on a real pseudo-terminal, timed on the wire.

The simulator's referee timestamps every frame: these tests hold the engine to the
manuals' gaps and post-write waits, to its coalescing and to how it survives faults.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
from collections import Counter
from typing import TYPE_CHECKING, Any

import pytest

from gateway.control.link import DeviceLink
from gateway.line.engine.devices import DeviceTarget
from gateway.line.samples import Quality
from gateway.profiles import PollGroup, get_profile
from gateway.wire import codec
from gateway.wire.timing import LineFormat
from tests.rigs import PLANT, ListSink, plant_targets, rig, target

if TYPE_CHECKING:
    from collections.abc import Mapping
    from pathlib import Path

pytestmark = [pytest.mark.line, pytest.mark.timing]


def gaps_on_the_wire(records: list[Any]) -> list[tuple[float, Any]]:
    """Silence before each request: from the previous frame's end (its answer or itself)."""
    gaps = []
    previous_end = None
    for record in records:
        if previous_end is not None:
            gaps.append((record.start - previous_end, record))
        previous_end = record.answer_at if record.answer_at is not None else record.start
    return gaps


# --- timing on the wire ------------------------------------------------------------------


@pytest.mark.parametrize(
    "line",
    [
        {"baudrate": 9600, "parity": "E", "stopbits": 1},
        {"baudrate": 19200, "parity": "N", "stopbits": 1},
    ],
    ids=["9600-8E1", "19200-8N1"],
)
async def test_mixed_poll_of_every_family_keeps_every_timing_rule(
    tmp_path: Path, line: dict[str, Any]
) -> None:
    async with rig(tmp_path, PLANT, plant_targets(0.5), line=line) as r:

        async def writer() -> None:
            for n in range(12):
                await asyncio.sleep(0.4)
                await r.worker.submit_write("h10", "compensation_temperature", 20.0 + n / 10)
                await r.worker.submit_write("s10", "compensation_temperature", 21.0 + n / 10)

        poller = asyncio.create_task(r.worker.run())
        await asyncio.wait_for(writer(), timeout=30)
        await asyncio.sleep(1.0)
        poller.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await poller
        stats = r.server.bus.stats()
        records = r.frames()
    assert stats["timing_violations"] == 0, stats["violations"][:3]
    assert stats["counters"]["writes"] == 24
    assert stats["counters"]["responses"] > 100
    fmt = LineFormat(**line)
    for gap, record in gaps_on_the_wire(records):
        required = fmt.frame_gap_s(0.002 if record.device in {1, 2, 3} else 0.0)
        assert gap >= required, (gap, required, record)
    for device in ("s10", "h10", "h20", "cl2", "m0c"):
        good = [s for s in r.sink.samples if s.device == device and s.good]
        assert len(good) > 10, device
    assert all(s.quality is Quality.GOOD for s in r.sink.samples)
    # The writes reached the sensors, in order, last value last.
    writes_log = stats["devices"]["2"]["writes"]
    assert [w["points"] for w in writes_log] == [["compensation_temperature"]] * 12


@pytest.mark.parametrize(
    ("point", "value", "wait_s"),
    [
        ("calibration_mode", "wet", 0.25),
        ("sensor_constant_f1", 1.5, 0.65),
        ("sensor_replacement_counter", 4, 0.65),
    ],
)
async def test_post_write_waits_measured_on_the_wire(
    tmp_path: Path, point: str, value: object, wait_s: float
) -> None:
    devices = [
        {"profile": "jumo-digiline-odo-h10", "address": 2},
        {"profile": "jumo-tecline-cl2", "address": 20},
    ]
    targets = [
        target("h10", "jumo-digiline-odo-h10", 2, interval=0.1),
        target("cl2", "jumo-tecline-cl2", 20, interval=0.1),
    ]
    async with rig(tmp_path, devices, targets) as r:

        async def write() -> None:
            await asyncio.sleep(1.0)
            await r.worker.submit_write("h10", point, value)

        task = asyncio.create_task(write())
        await r.run_for(2.5)
        await asyncio.wait_for(task, timeout=1)
        records = r.frames()
        stats = r.server.bus.stats()
    assert stats["timing_violations"] == 0
    index = next(i for i, rec in enumerate(records) if rec.function in {6, 16})
    written = records[index]
    assert written.answer_at is not None
    following = [rec for rec in records[index + 1 :] if rec.device == 2]
    assert following, "polling of the device resumed"
    assert following[0].start - written.answer_at >= wait_s
    assert following[0].start - written.answer_at < wait_s + 0.1
    # The other device was polled during the wait: the wait is per device.
    assert any(rec.device == 20 and rec.start < following[0].start for rec in records[index + 1 :])


# --- coalescing ----------------------------------------------------------------------------


async def test_exception_02_splits_a_merged_read_and_remembers(tmp_path: Path) -> None:
    devices = [{"profile": "jumo-digiline-odo-h10", "address": 2, "unmapped": [0x2009, 0x200A]}]
    profile = get_profile("jumo-digiline-odo-h10")
    detailed = {p.name: 0.3 for p in profile.points if 0x2001 <= p.address <= 0x200D}  # 6.2.1
    h10 = DeviceTarget(name="h10", address=2, profile=profile, intervals=detailed)
    async with rig(tmp_path, devices, [h10]) as r:
        await r.run_for(2.5)
        records = [rec for rec in r.frames() if 0x2001 <= rec.address <= 0x200D]
    exceptions = [rec for rec in records if rec.outcome == "exception_02"]
    assert len(exceptions) == 2  # the merged block once, then the unreadable point once
    assert exceptions[1].address == 0x2009
    late = [rec for rec in records if rec.start > exceptions[1].start]
    assert late, "polling went on"
    assert all(rec.outcome == "answered" for rec in late)
    assert not any(rec.address == 0x2009 for rec in late)
    raw = [s for s in r.sink.samples if s.point == "raw_reference_amplitude"]
    assert [s.fault for s in raw] == ["exception_02"]
    assert len(r.sink.good("h10", "raw_oxygen_amplitude")) >= 3


async def test_fewer_frames_than_one_request_per_point(tmp_path: Path) -> None:
    devices = [{"profile": "jumo-digiline-odo-h10", "address": 2}]
    profile = get_profile("jumo-digiline-odo-h10")
    slow = {PollGroup.DIAGNOSTICS, PollGroup.CONFIGURATION}
    intervals: dict[str, float | None] = {
        p.name: None if p.group is PollGroup.IDENTITY else 3.0 if p.group in slow else 0.5
        for p in profile.points
        if not p.view
    }
    h10 = DeviceTarget(name="h10", address=2, profile=profile, intervals=intervals)
    async with rig(tmp_path, devices, [h10]) as r:
        await r.run_for(6.0)
    polled = {s.point for s in r.sink.samples if s.good}
    reads = [rec for rec in r.frames() if rec.function == 3]
    assert len(polled) == len(intervals) == 289  # the logbook included
    per_point = sum(1 for s in r.sink.samples if s.good)
    assert len(reads) < per_point / 4  # one request per point: a frame per value


async def test_diagnostics_cut_short_resume_with_the_same_reads(tmp_path: Path) -> None:
    """Values due every 0.25 s cut an H10's 260 diagnostics into pieces (19200 baud).

    What remains due after each cut is read with the blocks of one plan of the whole
    class, not re-planned: the diagnostics' reads never overlap one another (a re-planned
    remainder starts its blocks elsewhere), and every diagnostic still comes round at
    its interval.
    """
    devices = [{"profile": "jumo-digiline-odo-h10", "address": 2}]
    profile = get_profile("jumo-digiline-odo-h10")
    slow_groups = {PollGroup.DIAGNOSTICS, PollGroup.CONFIGURATION}
    slow = {p.name for p in profile.points if not p.view and p.group in slow_groups}
    fast = [p.name for p in profile.points_in(PollGroup.PROCESS, PollGroup.STATUS) if not p.view]
    intervals: dict[str, float | None] = {n: 2.0 if n in slow else 0.25 for n in [*fast, *slow]}
    h10 = DeviceTarget(name="h10", address=2, profile=profile, intervals=intervals)
    line = {"baudrate": 19200, "parity": "N", "stopbits": 1}
    async with rig(tmp_path, devices, [h10], line=line) as r:
        await r.run_for(9.0)
    slow_starts = {profile.point(n).address for n in slow}
    fast_starts = {profile.point(n).address for n in fast}
    reads = {
        (rec.address, rec.quantity)
        for rec in r.frames()
        if rec.function == 3 and rec.address in slow_starts - fast_starts and rec.start > 1.0
    }  # after the start, which reads the unit and float format registers on their own
    spans = sorted((a, a + q - 1) for a, q in reads)
    assert len(spans) > 3  # cut into several reads
    for (_, last), (first, _) in itertools.pairwise(spans):
        assert first > last, spans
    polled = Counter(s.point for s in r.sink.samples if s.good and s.point in slow)
    assert set(polled) == slow
    assert min(polled.values()) >= 3  # at 2 s in 9 s, the first read at the start
    assert r.server.bus.stats()["timing_violations"] == 0


# --- faults ------------------------------------------------------------------------------

STATIC = [
    {
        "profile": "jumo-digiline-odo-s10",
        "address": 1,
        "animate": False,
        "values": {"oxygen": 8.5, "temperature": 20.25},
    },
    {
        "profile": "jumo-tecline-cl2",
        "address": 20,
        "animate": False,
        "values": {"concentration": 0.168, "temperature": 24.5, "cell_current": 3.5},
    },
]
EXPECTED = {
    ("s10", "oxygen"): 8.5,
    ("s10", "temperature"): 20.25,
    ("cl2", "concentration"): 0.168,
    ("cl2", "temperature"): 24.5,
    ("cl2", "cell_current"): 3.5,
}


def static_targets() -> list[DeviceTarget]:
    return [
        target("s10", "jumo-digiline-odo-s10", 1, interval=0.3),
        target("cl2", "jumo-tecline-cl2", 20, interval=0.3),
    ]


def errors_by_kind(errors: Mapping[tuple[int, str], int]) -> Counter[str]:
    """Errors summed over the devices they were counted for.

    A late answer is counted for whichever device's transaction flushed it, so one kind
    may appear under several devices (a dict comprehension kept only the last of them).
    """
    by_kind: Counter[str] = Counter()
    for (_, kind), count in errors.items():
        by_kind[kind] += count
    return by_kind


def assert_no_wrong_value(sink: ListSink) -> None:
    for sample in sink.samples:
        expected = EXPECTED.get((sample.device, sample.point))
        if expected is not None and sample.good:
            assert sample.value == expected, sample


def last_bad(sink: ListSink) -> float:
    return max((s.monotonic for s in sink.samples if not s.good), default=0.0)


@pytest.mark.parametrize(
    ("fault", "kind"),
    [
        ({"crc": 0.3}, "crc"),
        ({"drop": 0.3}, "timeout"),
        ({"late": 0.3, "late_s": 0.5}, "stale_frame"),
        ({"noise": 0.5}, "noise"),
        ({"wrong_address": 0.3}, "wrong_address"),
    ],
)
async def test_injected_faults_are_counted_and_never_give_a_wrong_value(
    tmp_path: Path, fault: dict[str, float], kind: str
) -> None:
    devices = [{**STATIC[0], "faults": fault}, STATIC[1]]
    async with rig(tmp_path, devices, static_targets()) as r:
        task = asyncio.create_task(r.worker.run())
        await asyncio.sleep(4.0)
        r.server.bus.faults[1] = type(r.server.bus.faults[1])()  # the fault clears
        cleared = asyncio.get_running_loop().time()
        await asyncio.sleep(2.5)
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task
        injected = dict(r.server.bus.injected)
        errors = errors_by_kind(r.line.stats.errors)
    assert sum(injected.values()) > 0
    assert errors[kind] > 0, (errors, injected)
    assert_no_wrong_value(r.sink)
    # Full polling within one poll interval after the fault clears (plus a late-answer window).
    recovered = [
        s for s in r.sink.samples if s.device == "s10" and s.good and s.monotonic > cleared + 1.3
    ]
    assert {s.point for s in recovered} >= {"oxygen", "temperature", "status"}
    assert all(s.good for s in r.sink.samples if s.monotonic > cleared + 1.3)


async def test_after_noise_and_no_answer_the_late_answer_is_not_taken_for_the_next(
    tmp_path: Path,
) -> None:
    """Noise, then the device's answer 0.3 s late: the request failed as noise only.

    The answer is still to come, so the device waits out its late-answer window; retried
    at once, the late answer would pass for the retry's, and the next request would go out
    while the retry's own answer was on the line (the soak found it).
    """
    devices = [{**STATIC[0], "faults": {"noise": 1.0, "late": 1.0, "late_s": 0.3}}, STATIC[1]]
    async with rig(tmp_path, devices, static_targets()) as r:
        await r.run_for(4.0)
    # The first read is of the sensor's minimum response time, which waits the manual's
    # longest (500 ms): the 0.3 s answer is in time for it. Every read after it waits what
    # the sensor said (0 ms), so its late answers are late.
    to_s10 = [rec.start for rec in r.frames() if rec.device == 1][1:]
    assert len(to_s10) >= 3
    assert all(later - earlier >= 1.0 for earlier, later in itertools.pairwise(to_s10))
    errors = errors_by_kind(r.line.stats.errors)
    assert errors["malformed"] + errors["crc"] == len(to_s10)
    assert errors["stale_frame"] >= len(to_s10) - 1  # each late answer flushed, unread
    assert r.server.bus.violations == []
    late = [s for s in r.sink.samples if s.device == "s10" and s.good]
    assert [s.point for s in late] == ["min_response_time"]  # the first read's, in time


async def test_silent_sensor_goes_offline_and_comes_back(tmp_path: Path) -> None:
    devices = [{**STATIC[0], "faults": {"silences": [[1.5, 3.0]]}}, STATIC[1]]
    targets = [
        target("s10", "jumo-digiline-odo-s10", 1, interval=0.3, probe_max_s=0.6),
        static_targets()[1],
    ]
    async with rig(tmp_path, devices, targets) as r:
        await r.run_for(7.0)
    states = [(e.device, e.online) for e in r.sink.events]
    assert states.count(("s10", False)) == 1
    assert states[-1] == ("s10", True) or ("s10", True) in states[states.index(("s10", False)) :]
    assert_no_wrong_value(r.sink)
    # The other device was polled all along.
    cl2 = sorted(s.monotonic for s in r.sink.good("cl2", "concentration"))
    assert max(b - a for a, b in itertools.pairwise(cl2)) < 1.0
    back = [e for e in r.sink.events if e.device == "s10" and e.online][-1]
    assert back.time > next(e for e in r.sink.events if not e.online).time
    assert r.line.stats.errors[1, "timeout"] >= 3


async def test_unplugged_port_is_reopened_without_a_restart(tmp_path: Path) -> None:
    async with rig(tmp_path, STATIC, static_targets()) as r:
        task = asyncio.create_task(r.worker.run())
        await asyncio.sleep(1.5)
        r.server.unplug_pty()
        unplugged = asyncio.get_running_loop().time()
        await asyncio.sleep(2.0)
        r.server.replug_pty()
        back = asyncio.get_running_loop().time()
        await asyncio.sleep(3.0)
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task
    assert r.line.stats.port_failures >= 1
    before = r.sink.good("s10", "oxygen")
    assert any(s.monotonic < unplugged for s in before)
    assert any(s.monotonic > back for s in before), "polling resumed after the port came back"
    assert any(not e.online for e in r.sink.events)
    assert_no_wrong_value(r.sink)


async def test_a_stop_does_not_wait_out_the_port_backoff(tmp_path: Path) -> None:
    # SIGTERM with the line gone took the whole backoff (seconds, up to reconnect_max_s).
    async with rig(tmp_path, STATIC, static_targets()) as r:
        task = asyncio.create_task(r.worker.run())
        await asyncio.sleep(0.5)
        r.server.unplug_pty()
        while r.line.stats.port_failures < 4:  # noqa: ASYNC110 - backoffs 0.5, 1, 2, then ~4 s
            await asyncio.sleep(0.05)
        await asyncio.sleep(0.2)
        asked = asyncio.get_running_loop().time()
        r.worker.request_stop()
        await asyncio.wait_for(task, timeout=10)
        stopped = asyncio.get_running_loop().time()
        r.server.replug_pty()
    assert stopped - asked < 0.5, f"the stop waited {stopped - asked:.1f} s for the backoff"


async def test_broadcast_write_has_no_answer_then_the_turnaround(tmp_path: Path) -> None:
    devices = [
        {"profile": "jumo-digiline-odo-h10", "address": 2},
        {"profile": "jumo-digiline-odo-s10", "address": 1},
    ]
    targets = [
        target("h10", "jumo-digiline-odo-h10", 2, interval=0.05),
        target("s10", "jumo-digiline-odo-s10", 1, interval=0.05),
    ]
    async with rig(tmp_path, devices, targets) as r:
        poller = asyncio.create_task(r.worker.run())
        await asyncio.sleep(1.0)
        await asyncio.wait_for(r.worker.submit_broadcast(0x0305, [0]), timeout=2)
        await asyncio.sleep(1.0)
        poller.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await poller
        records = r.frames()
        stats = r.server.bus.stats()
    assert stats["timing_violations"] == 0
    index = next(i for i, rec in enumerate(records) if rec.device == 0)
    broadcast = records[index]
    assert broadcast.outcome == "broadcast"
    assert broadcast.answer_at is None
    after = records[index + 1 :]
    first_h10 = next(rec for rec in after if rec.device == 2)
    first_s10 = next(rec for rec in after if rec.device == 1)
    assert first_h10.start - broadcast.start >= 0.25  # H10/H20 6.1.5 after every write
    assert first_s10.start - broadcast.start >= 0.1  # the broadcast turnaround delay


# An S10 clock block (6.9: year, month ... second, time-zone offset) dated month 13.
MONTH_13 = (2025, 13, 1, 12, 0, 0, 0)


async def test_an_undecodable_value_is_a_fault_of_the_value_not_of_the_line(
    tmp_path: Path,
) -> None:
    """The S10 answers every read, but its clock is not a date: the clock's samples are
    faults (``undecodable``) carrying the registers, the line and the device are fine, and
    a read through the device's link gets the fault as a value, as for 2.0e37."""
    clock = {0x2840 + offset: word for offset, word in enumerate(MONTH_13)}
    devices = [{**STATIC[0], "registers": clock}]
    profile = get_profile("jumo-digiline-odo-s10")
    s10 = DeviceTarget(
        name="s10", address=1, profile=profile, intervals={"temperature": 0.3, "clock": 0.3}
    )
    async with rig(tmp_path, devices, [s10]) as r:
        await r.run_for(1.5)
        value = await DeviceLink(r.worker, "s10").read_value("clock")  # inline, line still open
    clocks = [s for s in r.sink.samples if s.point == "clock"]
    assert len(clocks) >= 3
    assert {(s.quality, s.fault, s.value, s.raw) for s in clocks} == {
        (Quality.FAULT, "undecodable", None, MONTH_13)
    }
    assert isinstance(value, codec.Fault)
    assert (value.name, value.registers) == ("undecodable", MONTH_13)
    assert "month must be in 1..12" in value.reason
    assert [s.value for s in r.sink.good("s10", "temperature")][:1] == [20.25]
    assert [e.online for e in r.sink.events] == [True]
    assert not r.line.stats.errors
