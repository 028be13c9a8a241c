"""Poll phases: devices that share an interval fall due at their own instants, and keep them."""

from __future__ import annotations

import itertools
import math

import pytest

from gateway.app import build_workers
from gateway.config import parse_config
from gateway.line.engine.devices import DeviceState, DeviceTarget
from gateway.line.engine.schedule import SLOW_GROUP_DELAY_S, Schedule, next_slot, spread_phase
from gateway.profiles import PollGroup, get_profile

PROFILE = get_profile("reiss-m0c")
VALUES = tuple(p.name for p in PROFILE.points_in(PollGroup.PROCESS, PollGroup.STATUS) if not p.view)
DIAGNOSTICS = tuple(p.name for p in PROFILE.points_in(PollGroup.DIAGNOSTICS) if not p.view)[:2]
START = 1000.37  # a start that is no slot of anyone's


def target(
    name: str,
    address: int,
    *,
    phase: float | None,
    interval_s: float = 1.0,
    intervals: dict[str, float | None] | None = None,
) -> DeviceTarget:
    """A Reiss M0c: its values at ``interval_s``, two diagnostics at 60 s, no identity."""
    points: dict[str, float | None] = dict.fromkeys(VALUES, interval_s)
    points.update(dict.fromkeys(DIAGNOSTICS, 60.0))
    points.update(intervals or {})
    return DeviceTarget(name=name, address=address, profile=PROFILE, intervals=points, phase=phase)


def schedule_of(*targets: DeviceTarget) -> Schedule:
    return Schedule({t.name: DeviceState(target=t) for t in targets})


def read_due(schedule: Schedule, state: DeviceState, now: float) -> list[str]:
    """What the worker does for one device at ``now``: its due values read and advanced."""
    state.deadlines.identity_pending.clear()  # identity and unit registers read: not the point here
    state.deadlines.cache.clear()
    names = schedule.due_points(state, now, slow=False)
    schedule.advance(state, names, now)
    return names


def value_due(state: DeviceState) -> float:
    """When the device's values next fall due (all of them, together)."""
    (due,) = {state.deadlines.next_due[name] for name in VALUES}
    return due


# --- the default spread -------------------------------------------------------------------


def test_sixteen_buses_of_sixteen_devices_fall_due_at_256_evenly_spaced_instants() -> None:
    phases = sorted(
        spread_phase(device=j, devices=16, bus=b, buses=16) for b in range(16) for j in range(16)
    )
    assert phases == pytest.approx([n / 256 for n in range(256)])


def test_a_bus_shares_its_interval_and_the_buses_are_staggered_within_a_slot() -> None:
    # Device j of m on bus b of B: at (j + b/B) / m of the interval.
    assert [spread_phase(device=j, devices=4, bus=0, buses=2) for j in range(4)] == [
        0.0,
        0.25,
        0.5,
        0.75,
    ]
    assert [spread_phase(device=j, devices=4, bus=1, buses=2) for j in range(4)] == [
        0.125,
        0.375,
        0.625,
        0.875,
    ]
    assert [spread_phase(device=j, devices=3, bus=1, buses=2) for j in range(3)] == (
        pytest.approx([1 / 6, 1 / 2, 5 / 6])
    )
    assert spread_phase(device=0, devices=1, bus=0, buses=1) == 0.0


@pytest.mark.parametrize(
    ("after", "interval_s", "offset_s", "slot"),
    [
        (10.0, 1.0, 0.25, 10.25),
        (10.25, 1.0, 0.25, 11.25),  # a read at its slot: the next one
        (10.3, 1.0, 0.25, 11.25),
        (10.3, 2.0, 0.5, 10.5),
        (10.6, 2.0, 0.5, 12.5),
        (10.0, 1.0, 0.0, 11.0),
        (1e6 + 0.1, 0.5, 0.1, 1e6 + 0.6),  # days of uptime: still on the grid
    ],
)
def test_the_next_slot_is_the_first_of_the_grid_after_the_read(
    after: float, interval_s: float, offset_s: float, slot: float
) -> None:
    assert next_slot(after, interval_s=interval_s, offset_s=offset_s) == pytest.approx(slot)
    assert next_slot(after, interval_s=interval_s, offset_s=offset_s) > after


def test_256_cycles_do_not_fall_due_in_the_same_150_ms() -> None:
    buses, per_bus = 16, 16
    schedules = []
    for b in range(buses):
        targets = [
            target(
                f"dev{b}_{j}",
                j + 1,
                phase=spread_phase(device=j, devices=per_bus, bus=b, buses=buses),
            )
            for j in range(per_bus)
        ]
        schedules.append(schedule_of(*targets))
    due = []
    for schedule in schedules:
        schedule.restart(START)
        for state in schedule.devices.values():
            read_due(schedule, state, START + 0.01)  # the start's backlog: all at once
            due.append(value_due(state))
    # The next cycles all come in the interval after the next, each at its own instant.
    assert all(START + 1.01 < t <= START + 2.01 for t in due)
    assert len(set(due)) == 256
    ordered = sorted(due)
    busiest = max(sum(1 for t in ordered if s <= t < s + 0.150) for s in ordered)
    assert busiest <= math.ceil(0.150 * 256)  # 39: evenly spaced, 1/256 s apart
    gaps = [b - a for a, b in itertools.pairwise(ordered)]
    assert min(gaps) == pytest.approx(1 / 256)


# --- one device's phase ---------------------------------------------------------------------


def test_the_first_cycle_is_read_at_once_and_the_next_at_the_devices_slot() -> None:
    state = DeviceState(target=target("basin", 10, phase=0.25, interval_s=2.0))
    schedule = Schedule({"basin": state})
    schedule.restart(START)
    assert schedule.pick(START, slow=False) is state  # due at once: online promptly
    assert set(read_due(schedule, state, START + 0.02)) == set(VALUES)
    # A quarter of its 2 s interval: due at 2k + 0.5 s of the monotonic clock, the first
    # such slot a whole interval after the first cycle (1000.39 + 2).
    assert value_due(state) == pytest.approx(1002.5)
    assert schedule.pick(1002.49, slow=False) is None
    assert schedule.pick(1002.5, slow=False) is state
    read_due(schedule, state, 1002.53)
    assert value_due(state) == pytest.approx(1004.5)
    assert state.deadlines.missed_deadlines == 0


def test_a_long_first_cycle_leaves_the_next_slot_a_whole_interval_away() -> None:
    # At 9600 baud an H10's first cycle (its identity) took 0.6 s and a tecLine's another
    # 0.3 s; the H10's slot within the first interval (1000.75) would have been missed
    # before it was served.
    h10 = DeviceState(target=target("h10", 2, phase=0.5, interval_s=0.5))
    cl2 = DeviceState(target=target("cl2", 20, phase=0.0, interval_s=0.5))
    schedule = Schedule({"h10": h10, "cl2": cl2})
    schedule.restart(START)
    read_due(schedule, h10, START)  # began at the start, ended 0.6 s later
    read_due(schedule, cl2, START + 0.6)  # began then, ended 0.3 s later
    read_due(schedule, h10, START + 0.9)
    read_due(schedule, cl2, START + 1.13)
    assert (h10.deadlines.missed_deadlines, cl2.deadlines.missed_deadlines) == (0, 0)
    assert value_due(h10) % 0.5 == pytest.approx(0.25)  # back on its slots
    assert value_due(cl2) % 0.5 == pytest.approx(0.0, abs=1e-9)


def test_phase_zero_is_no_spread_devices_at_zero_fall_due_together() -> None:
    first = target("a", 1, phase=0.0)
    second = target("b", 2, phase=0.0)
    schedule = schedule_of(first, second)
    schedule.restart(START)
    for state in schedule.devices.values():
        read_due(schedule, state, START + 0.05 * state.target.address)
    assert [value_due(s) for s in schedule.devices.values()] == [1002.0, 1002.0]


def test_without_a_phase_deadlines_count_from_the_start_as_before() -> None:
    state = DeviceState(target=target("cli", 1, phase=None))
    schedule = Schedule({"cli": state})
    schedule.restart(START)
    read_due(schedule, state, START + 0.02)
    assert value_due(state) == pytest.approx(START + 0.02 + 1.0)


def test_points_at_a_multiple_of_the_interval_fall_due_with_the_others() -> None:
    # The phase is one offset in seconds for the device, so the 5 s point meets the 1 s
    # points every fifth cycle and is read in the same turn.
    state = DeviceState(target=target("basin", 10, phase=0.3, intervals={VALUES[0]: 5.0}))
    schedule = Schedule({"basin": state})
    schedule.restart(START)
    now = START
    turns = []
    for _ in range(17):
        names = read_due(schedule, state, now)
        turns.append((round(now, 6), VALUES[0] in names))
        now = min(state.deadlines.next_due[n] for n in VALUES)
    slow_point_turns = [t for t, read in turns if read]
    assert slow_point_turns == [START, 1010.3, 1015.3]  # its first slot 5 s after START
    assert all(round(t - 0.3, 6) % 1 == 0 for t, _ in turns[1:])  # every turn on its slot


def test_diagnostics_keep_their_own_rule() -> None:
    state = DeviceState(target=target("basin", 10, phase=0.5))
    schedule = Schedule({"basin": state})
    schedule.restart(START)
    assert {state.deadlines.next_due[n] for n in DIAGNOSTICS} == {START + SLOW_GROUP_DELAY_S}
    later = START + SLOW_GROUP_DELAY_S + 0.1
    state.deadlines.cache.clear()
    names = schedule.due_points(state, later, slow=True)
    schedule.advance(state, names, later)
    assert [state.deadlines.next_due[n] for n in DIAGNOSTICS] == pytest.approx([later + 60.0] * 2)


def test_missed_slots_are_counted_and_the_phase_kept() -> None:
    state = DeviceState(target=target("basin", 10, phase=0.5))
    schedule = Schedule({"basin": state})
    schedule.restart(START)
    read_due(schedule, state, START)
    assert value_due(state) == pytest.approx(1001.5)
    read_due(schedule, state, 1004.2)  # the line was busy: 1002.5 and 1003.5 missed
    assert state.deadlines.missed_deadlines == 2 * len(VALUES)
    assert value_due(state) == pytest.approx(1004.5)


# --- the phase holds ----------------------------------------------------------------------


@pytest.mark.parametrize("how", ["back-online", "port-reconnected"])
def test_a_restart_reads_at_once_then_returns_to_the_same_slots(how: str) -> None:
    spread = [target(f"d{j}", j + 1, phase=j / 4) for j in range(4)]
    schedule = schedule_of(*spread)
    schedule.restart(START)
    for state in schedule.devices.values():
        read_due(schedule, state, START)
    before = {name: value_due(s) % 1.0 for name, s in schedule.devices.items()}
    assert sorted(before.values()) == pytest.approx([0.0, 0.25, 0.5, 0.75])

    again = 1007.61  # off every slot
    if how == "back-online":
        restarted = [schedule.devices["d2"]]
        schedule.restart_device(restarted[0], again)
    else:
        restarted = list(schedule.devices.values())
        schedule.restart(again)
    for state in restarted:
        state.deadlines.identity_pending.clear()  # read first, as at any start
        assert set(schedule.due_points(state, again, slow=False)) == set(VALUES)  # at once
        read_due(schedule, state, again + 0.01)
    after = {name: value_due(s) % 1.0 for name, s in schedule.devices.items()}
    assert after == pytest.approx(before)
    assert all(again + 1.01 < value_due(s) <= again + 2.01 for s in restarted)


def test_values_read_again_for_another_master_return_to_their_slot() -> None:
    state = DeviceState(target=target("basin", 10, phase=0.25))
    schedule = Schedule({"basin": state})
    schedule.restart(START)
    read_due(schedule, state, START)
    read_due(schedule, state, 1001.25)
    assert value_due(state) == pytest.approx(1002.25)
    point = PROFILE.point(VALUES[0])
    schedule.reread(state, point.address, point.count, 1001.9)  # another master wrote
    assert schedule.due_points(state, 1001.9, slow=False) == [VALUES[0]]
    read_due(schedule, state, 1001.9)
    assert value_due(state) == pytest.approx(1002.25)  # with the others, not at 1002.9


# --- the gateway's devices ----------------------------------------------------------------


def test_the_gateway_spreads_its_devices_and_a_poll_phase_overrides_it() -> None:
    lines = ["buses:"]
    lines += [f"  - {{name: line{b}, port: /dev/ttyUSB{b}}}" for b in range(2)]
    lines.append("devices:")
    for b in range(2):
        for j in range(3):
            extra = ", poll_interval: 2, poll_phase: 0.5" if (b, j) == (1, 2) else ""
            lines.append(
                f"  - {{name: d{b}{j}, bus: line{b}, address: {j + 1}, profile: reiss-m0c{extra}}}"
            )
    config = parse_config("\n".join(lines) + "\n", environ={})
    workers = build_workers(config, sinks=[])
    phases = {
        name: (state.target.phase, state.target.phase_s)
        for worker in workers
        for name, state in worker.devices.items()
    }
    assert phases == {
        "d00": (0.0, 0.0),
        "d01": (pytest.approx(1 / 3), pytest.approx(1 / 3)),
        "d02": (pytest.approx(2 / 3), pytest.approx(2 / 3)),
        "d10": (pytest.approx(1 / 6), pytest.approx(1 / 6)),
        "d11": (pytest.approx(1 / 2), pytest.approx(1 / 2)),
        "d12": (0.5, 1.0),  # its own: half of its 2 s interval
    }
