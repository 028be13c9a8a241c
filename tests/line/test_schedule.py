"""The pure schedule: its heap picks what a scan over every device would, step by step."""

from __future__ import annotations

import math
import random

import pytest

from gateway.line.engine.devices import DeviceState, DeviceTarget
from gateway.line.engine.schedule import Schedule
from gateway.profiles import PollGroup, get_profile

FAMILIES = ("jumo-digiline-odo-s10", "jumo-tecline-cl2", "reiss-m0c")


def seeded(seed: int) -> random.Random:
    return random.Random(seed)  # noqa: S311 - a repeatable test, nothing secret


def states(count: int, rng: random.Random, *, phases: bool = False) -> dict[str, DeviceState]:
    """Devices of every family; ``phases``: some with a phase (some with none), as spread."""
    result = {}
    for n in range(count):
        profile = get_profile(FAMILIES[n % len(FAMILIES)])
        process = [p for p in profile.points_in(PollGroup.PROCESS, PollGroup.STATUS) if not p.view]
        slow = [p for p in profile.points_in(PollGroup.DIAGNOSTICS) if not p.view][:3]
        intervals: dict[str, float | None] = {p.name: rng.choice((0.5, 1.0, 2.0)) for p in process}
        intervals.update({p.name: 10.0 for p in slow})
        phase = rng.choice((None, 0.0, rng.random())) if phases else None
        target = DeviceTarget(
            name=f"d{n}",
            address=rng.randint(1, 247),
            profile=profile,
            intervals=intervals,
            phase=phase,
        )
        result[target.name] = DeviceState(target=target)
    return result


def scan(schedule: Schedule, now: float, *, slow: bool) -> DeviceState | None:
    """The reference: every device looked at, the earliest deadline, ties to the lower address."""
    due = [
        (deadline, s.target.address, n, s)
        for n, s in enumerate(schedule.devices.values())
        if s.holds.not_before <= now and (deadline := schedule.next_deadline(s, slow=slow)) <= now
    ]
    return min(due, key=lambda item: item[:3])[3] if due else None


def identity_read(state: DeviceState) -> None:
    state.deadlines.identity_pending.clear()
    state.deadlines.cache.clear()


@pytest.mark.parametrize("phases", [False, True], ids=["from-start", "phased"])
@pytest.mark.parametrize("seed", range(10))
def test_the_heap_picks_what_a_scan_picks(seed: int, *, phases: bool) -> None:
    rng = seeded(seed)
    devices = states(rng.randint(1, 40), rng, phases=phases)
    schedule = Schedule(devices)
    now = 1000.0
    schedule.restart(now)
    for _ in range(600):
        now += rng.choice((0.0, 0.001, 0.05, 0.3))
        slow = rng.random() < 0.3
        chosen = schedule.pick(now, slow=slow)
        expected = scan(schedule, now, slow=slow)
        assert chosen is expected
        if chosen is None:
            continue
        action = rng.random()
        if action < 0.6:
            identity_read(chosen)
            names = schedule.due_points(chosen, now, slow=slow)
            schedule.advance(chosen, rng.sample(names, k=(len(names) + 1) // 2), now)
        elif action < 0.75:
            chosen.holds.not_before = now + rng.choice((0.01, 0.25, 1.0))  # a wait: set aside
        elif action < 0.85:
            chosen.presence.online = False  # as Availability does, then tells the schedule
            chosen.presence.probe_at = now + rng.choice((0.0, 0.5))
            schedule.touch(chosen)
        elif action < 0.92:
            chosen.presence.online = None
            schedule.restart_device(chosen, now)
        else:
            names = sorted(chosen.deadlines.next_due)
            chosen.holds.unreadable.add(rng.choice(names))  # as the transactions do
            chosen.deadlines.changed()


def test_a_device_inside_a_wait_is_passed_over_then_picked_when_it_ends() -> None:
    devices = states(2, seeded(1))
    first, second = sorted(devices.values(), key=lambda s: s.target.address)
    schedule = Schedule(devices)
    schedule.restart(0.0)
    identity_read(first)
    identity_read(second)
    first.holds.not_before = 5.0
    assert schedule.pick(1.0, slow=False) is second
    assert schedule.pick(5.0, slow=False) is first  # ties go to the lower address


def test_nothing_due_is_nothing_picked() -> None:
    devices = states(3, seeded(2))
    schedule = Schedule(devices)
    assert schedule.pick(0.0, slow=False) is None  # never started: no deadlines
    schedule.restart(10.0)
    for state in devices.values():
        identity_read(state)
        schedule.advance(state, list(state.deadlines.next_due), 10.0)
    assert schedule.pick(10.0, slow=False) is None
    assert schedule.wake_at(10.0) > 10.0
    assert not math.isinf(schedule.wake_at(10.0))


def test_what_another_master_wrote_is_read_again_the_format_before_the_values() -> None:
    profile = get_profile("jumo-digiline-odo-h10")
    intervals: dict[str, float | None] = {
        "oxygen": 1.0,
        "compensation_temperature": 60.0,
        "float_format": 300.0,
        "serial_number": None,
    }
    state = DeviceState(
        target=DeviceTarget(name="h10", address=2, profile=profile, intervals=intervals)
    )
    schedule = Schedule({"h10": state})
    schedule.restart(0.0)
    state.deadlines.identity_pending.clear()  # read: everything is polled on its interval now
    state.deadlines.next_due.update(
        {"oxygen": 1.0, "compensation_temperature": 60.0, "float_format": 300}
    )
    state.deadlines.cache.clear()

    schedule.reread(state, 0x2013, 2, now=5.0)  # compensation_temperature, by another master
    assert state.deadlines.next_due["compensation_temperature"] == 5.0
    assert state.deadlines.next_due["float_format"] == 300
    assert state.deadlines.identity_pending == set()

    schedule.reread(state, 0x0300, 0x10, now=6.0)  # a block holding the float format (0x0307)
    # Read before any value, as at a start: values decoded after it follow the new format.
    assert "float_format" in state.deadlines.identity_pending
    assert schedule.next_deadline(state, slow=False) == 0.0
    assert state.deadlines.next_due["oxygen"] == 1.0  # unwritten points keep their deadlines
