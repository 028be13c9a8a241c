"""Read planner: the cheapest valid reads, checked against independent references."""

from __future__ import annotations

import functools
import itertools
import math
from collections.abc import Iterator, Sequence

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from gateway.errors import ConfigError
from gateway.line.engine.plan import TIE_S, CostModel, Planner, ReadBlock, plan_reads
from gateway.profiles import (
    Access,
    Limits,
    Point,
    PollGroup,
    Profile,
    Quirks,
    Timing,
    builtin_profiles,
    get_profile,
)
from gateway.wire.codec import DataType, Format, WordOrder
from gateway.wire.timing import LineFormat

LINE_9600_8E1 = LineFormat(baudrate=9600, parity="E", stopbits=1)
CHARACTER_S = 11 / 9600
S10 = get_profile("jumo-digiline-odo-s10")
H10 = get_profile("jumo-digiline-odo-h10")
TECLINE = get_profile("jumo-tecline-cl2")
PROFILES = list(builtin_profiles().values())

# (address, count) of each read, and its points' names.
Shape = tuple[tuple[int, int, tuple[str, ...]], ...]


def shape(blocks: Sequence[ReadBlock]) -> Shape:
    return tuple((b.address, b.count, tuple(p.name for p in b.points)) for b in blocks)


def cost_of(profile: Profile, line: LineFormat = LINE_9600_8E1) -> CostModel:
    return CostModel.for_device(profile, line)


def per_point_s(points: Sequence[Point], cost: CostModel) -> float:
    return sum(cost.read_s(p.count) for p in {p.name: p for p in points}.values())


# --- independent references ------------------------------------------------------------


def distinct_sorted(points: Sequence[Point]) -> list[Point]:
    return sorted({p.name: p for p in points}.values(), key=lambda p: (p.address, p.view, p.name))


def block_ok(
    group: Sequence[Point], profile: Profile, limit: int, split_before: frozenset[int]
) -> bool:
    """The rules for one read of exactly the registers ``group`` spans."""
    first, last = min(p.address for p in group), max(p.last for p in group)
    run = profile.readable_run(first)
    if run is None or last > run[1] or last - first + 1 > limit:
        return False
    # A split inside a requested point cannot be honoured and does not count.
    return all(
        not first < a <= last or any(p.address < a <= p.last for p in group) for a in split_before
    )


def span(group: Sequence[Point]) -> int:
    return max(p.last for p in group) - min(p.address for p in group) + 1


def brute_force(
    points: Sequence[Point],
    profile: Profile,
    cost: CostModel,
    *,
    limit: int,
    split_before: frozenset[int] = frozenset(),
) -> Shape:
    """The cheapest plan over every way to cut the sorted points, by enumeration."""
    ordered = distinct_sorted(points)
    if not ordered:
        return ()
    plans: list[tuple[float, Shape]] = []
    for cuts in itertools.product((False, True), repeat=len(ordered) - 1):
        groups: list[list[Point]] = [[ordered[0]]]
        for point, cut in zip(ordered[1:], cuts, strict=True):
            if cut:
                groups.append([])
            groups[-1].append(point)
        disjoint = all(
            max(p.last for p in a) < min(p.address for p in b)
            for a, b in itertools.pairwise(groups)
        )
        if disjoint and all(block_ok(g, profile, limit, split_before) for g in groups):
            total = sum(cost.read_s(span(g)) for g in groups)
            plan = tuple(
                (min(p.address for p in g), span(g), tuple(p.name for p in g)) for g in groups
            )
            plans.append((total, plan))
    assert plans, "no valid plan at all"
    # Ties: fewer reads, then the latest start of the last read, and so on backwards.
    cheapest = min(total for total, _ in plans)
    tied = [plan for total, plan in plans if total <= cheapest + TIE_S]
    return min(tied, key=lambda plan: (len(plan), [-address for address, _, _ in reversed(plan)]))


def set_partitions(items: list[Point]) -> Iterator[list[list[Point]]]:
    if not items:
        yield []
        return
    head, rest = items[0], items[1:]
    for partition in set_partitions(rest):
        yield [[head], *partition]
        for i in range(len(partition)):
            yield [*partition[:i], [head, *partition[i]], *partition[i + 1 :]]


def reference_s(
    points: Sequence[Point],
    profile: Profile,
    cost: CostModel,
    *,
    limit: int,
    split_before: frozenset[int] = frozenset(),
) -> float:
    """The cheapest plan's bus time, by top-down recursion over the sorted points."""
    ordered = distinct_sorted(points)
    reach = list(itertools.accumulate((p.last for p in ordered), max))

    @functools.cache
    def best(i: int) -> float:
        if i == len(ordered):
            return 0.0
        result = math.inf
        for j in range(i, len(ordered)):
            if j + 1 < len(ordered) and reach[j] >= ordered[j + 1].address:
                continue  # the next point overlaps this group: it must join it
            group = ordered[i : j + 1]
            if block_ok(group, profile, limit, split_before):
                result = min(result, cost.read_s(span(group)) + best(j + 1))
        return result

    return best(0)


def assert_valid(
    blocks: Sequence[ReadBlock],
    points: Sequence[Point],
    profile: Profile,
    *,
    limit: int,
    split_before: frozenset[int] = frozenset(),
) -> None:
    """Every rule of a plan, checked on its output."""
    for a, b in itertools.pairwise(blocks):
        assert a.last < b.address, f"{a} and {b} overlap or are out of order"
    for block in blocks:
        assert block.points, f"{block} reads nothing requested"
        assert 1 <= block.count <= limit
        run = profile.readable_run(block.address)
        assert run is not None, f"{block} starts outside the readable runs"
        assert block.last <= run[1], f"{block} crosses the end of run {run}"
        assert block_ok(block.points, profile, limit, split_before), f"{block} breaks a split"
        assert block.address == min(p.address for p in block.points)
        assert block.last == max(p.last for p in block.points)
        keys = [(p.address, p.view, p.name) for p in block.points]
        assert keys == sorted(keys)
    names = [p.name for block in blocks for p in block.points]
    assert len(names) == len(set(names)), "a point is read twice"
    assert set(names) == {p.name for p in points}


# --- synthetic maps --------------------------------------------------------------------


def float_point(name: str, address: int) -> Point:
    return Point(
        name=name,
        address=address,
        format=Format(dtype=DataType.FLOAT32, count=2),
        access=Access.READ,
        unit="",
        unit_from=None,
        enum_units={},
        storage=None,
        post_write_wait_s=0.0,
        group=PollGroup.PROCESS,
        description=name,
    )


def synthetic(points: Sequence[Point], readable: tuple[tuple[int, int], ...]) -> Profile:
    """A digiLine-like map (2 ms minimum gap, 125 registers per read) of ``points``."""
    return Profile(
        id="synthetic",
        family="synthetic",
        title="Synthetic",
        spec="",
        source="test",
        points=tuple(points),
        readable=readable,
        float_order=WordOrder.CDAB,
        float_order_register=None,
        float_faults=False,
        limits=Limits(),
        timing=Timing(min_gap_s=0.002),
        quirks=Quirks(),
        exceptions={},
        serial=None,
        identify={},
        unit_availability={},
    )


def two_floats(hole: int) -> Profile:
    """``a`` at 0x0000 and ``b`` ``hole`` registers after it, all readable."""
    return synthetic([float_point("a", 0), float_point("b", 2 + hole)], ((0, 0x1FF),))


# --- the cost model --------------------------------------------------------------------


def test_read_counts_both_frames_t1_and_two_gaps() -> None:
    cost = cost_of(S10)
    gap_s = 3.5 * CHARACTER_S  # 4.01 ms: more than the digiLine minimum of 2 ms
    assert cost.gap_s == pytest.approx(gap_s)
    assert cost.processing_s == 0.005
    # oxygen: 8 request bytes, 5 + 4 response bytes
    assert cost.read_s(2) == pytest.approx(17 * CHARACTER_S + 0.005 + 2 * gap_s)
    assert cost.read_s(3) - cost.read_s(2) == pytest.approx(2 * CHARACTER_S)


def test_gap_takes_the_larger_of_the_line_the_device_and_the_caller() -> None:
    fast = LineFormat(baudrate=38400)
    assert CostModel.for_device(S10, fast).gap_s == 0.002  # digiLine: at least 2 ms
    assert CostModel.for_device(TECLINE, fast).gap_s == pytest.approx(3.5 * 10 / 38400)
    assert CostModel.for_device(TECLINE, fast, extra_gap_s=0.01).gap_s == 0.01
    assert CostModel.for_device(S10, fast, processing_s=0.1).processing_s == 0.1


def test_negative_times_are_refused() -> None:
    with pytest.raises(ConfigError, match="negative"):
        CostModel(line=LINE_9600_8E1, processing_s=-0.001, gap_s=0.004)


# --- reference device sets, against the brute force ------------------------------------

REFERENCE_SETS = {
    "s10-process-status": (S10, S10.points_in(PollGroup.PROCESS, PollGroup.STATUS)),
    "h10-process-status": (H10, H10.points_in(PollGroup.PROCESS, PollGroup.STATUS)),
    "tecline-process": (TECLINE, TECLINE.points_in(PollGroup.PROCESS)),
    "s10-diagnostics": (S10, S10.points_in(PollGroup.DIAGNOSTICS)),
    "tecline-history": (TECLINE, tuple(p for p in TECLINE.points if p.repeat)),
}


@pytest.mark.parametrize("name", sorted(REFERENCE_SETS))
def test_plan_is_the_brute_force_optimum(name: str) -> None:
    profile, points = REFERENCE_SETS[name]
    assert 0 < len(points) <= 16
    cost = cost_of(profile)
    blocks = plan_reads(points, profile, cost)
    expected = brute_force(points, profile, cost, limit=profile.limits.max_read)
    assert shape(blocks) == expected
    assert_valid(blocks, points, profile, limit=profile.limits.max_read)
    assert cost.plan_s(blocks) <= per_point_s(points, cost)


def test_s10_process_points_cannot_merge() -> None:
    # 0x2602..0x261F and 0x2622..0x263F are not readable: one read per point, whatever
    # a transaction costs.
    points = S10.points_in(PollGroup.PROCESS, PollGroup.STATUS)
    slow = CostModel.for_device(S10, LINE_9600_8E1, processing_s=10.0)
    expected = (
        (0x2600, 2, ("oxygen",)),
        (0x2620, 2, ("temperature",)),
        (0x2640, 1, ("status",)),
    )
    assert shape(plan_reads(points, S10, cost_of(S10))) == expected
    assert shape(plan_reads(points, S10, slow)) == expected


def test_h10_process_and_status_take_two_reads_instead_of_five() -> None:
    points = H10.points_in(PollGroup.PROCESS, PollGroup.STATUS)
    cost = cost_of(H10)
    blocks = plan_reads(points, H10, cost)
    assert shape(blocks) == (
        (0x2001, 6, ("oxygen", "temperature", "error_register")),
        (0x3001, 8, ("measurement_status", "status")),  # reads the hole 0x3003..0x3006
    )
    assert cost.plan_s(blocks) == pytest.approx(0.08792, abs=1e-5)
    assert per_point_s(points, cost) == pytest.approx(0.16250, abs=1e-5)


def test_tecline_process_values_take_one_read_instead_of_three() -> None:
    points = TECLINE.points_in(PollGroup.PROCESS)
    cost = cost_of(TECLINE)
    blocks = plan_reads(points, TECLINE, cost)
    assert shape(blocks) == ((0, 6, ("concentration", "cell_current", "temperature")),)
    assert cost.plan_s(blocks) == pytest.approx(0.04167, abs=1e-5)
    assert per_point_s(points, cost) == pytest.approx(0.09750, abs=1e-5)


def test_h10_logbook_takes_four_full_reads() -> None:
    # 180 points in ten entries of 49 registers, 0x0600..0x07E9 without a hole: the
    # fewest reads of at most 125 registers are the cheapest plan.
    points = tuple(p for p in H10.points if p.repeat == "logbook")
    assert len(points) == 180
    cost = cost_of(H10)
    blocks = plan_reads(points, H10, cost)
    assert [(b.address, b.count) for b in blocks] == [
        (0x600, 123),
        (0x67B, 125),
        (0x6F8, 124),
        (0x774, 118),
    ]
    assert_valid(blocks, points, H10, limit=125)
    assert cost.plan_s(blocks) == pytest.approx(reference_s(points, H10, cost, limit=125))
    assert cost.plan_s(blocks) == pytest.approx(4 * cost.read_s(0) + 490 * 2 * CHARACTER_S)
    assert per_point_s(points, cost) > 4 * cost.plan_s(blocks)


def test_h10_diagnostics_match_the_reference() -> None:
    points = H10.points_in(PollGroup.DIAGNOSTICS)
    cost = cost_of(H10)
    blocks = plan_reads(points, H10, cost)
    assert_valid(blocks, points, H10, limit=125)
    assert cost.plan_s(blocks) == pytest.approx(reference_s(points, H10, cost, limit=125))
    assert len(blocks) == 10


# --- the cost model decides ------------------------------------------------------------


@pytest.mark.parametrize(("hole", "reads"), [(0, 1), (4, 1), (12, 1), (13, 2)])
def test_short_holes_are_read_long_ones_are_not(hole: int, reads: int) -> None:
    # 9600 8E1: a read costs about 27.9 ms more than its registers, a register 2.3 ms.
    profile = two_floats(hole)
    assert len(plan_reads(profile.points, profile, cost_of(profile))) == reads


@pytest.mark.parametrize("hole", [40, 100, 121, 200, 400])
def test_long_holes_stay_unread(hole: int) -> None:
    profile = two_floats(hole)
    assert len(plan_reads(profile.points, profile, cost_of(profile))) == 2


def test_the_line_and_the_device_move_the_break_even() -> None:
    profile = two_floats(40)
    at_9600 = cost_of(profile)
    at_115200 = cost_of(profile, LineFormat(baudrate=115200))
    slow_device = CostModel.for_device(profile, LINE_9600_8E1, processing_s=0.5)
    assert len(plan_reads(profile.points, profile, at_9600)) == 2
    assert len(plan_reads(profile.points, profile, at_115200)) == 1
    assert len(plan_reads(profile.points, profile, slow_device)) == 1


@pytest.mark.parametrize("hole", range(0, 122, 3))
def test_merging_follows_the_costs(hole: int) -> None:
    profile = two_floats(hole)
    cost = cost_of(profile)
    merged = cost.read_s(4 + hole) < 2 * cost.read_s(2)
    blocks = plan_reads(profile.points, profile, cost)
    assert len(blocks) == (1 if merged else 2)
    assert cost.plan_s(blocks) == min(cost.read_s(4 + hole), 2 * cost.read_s(2))


def test_h10_logbook_entries_merge_only_when_close() -> None:
    near = [H10.point("logbook_1_entry_type"), H10.point("logbook_1_operating_seconds")]
    far = [H10.point("logbook_1_entry_type"), H10.point("logbook_3_entry_type")]  # 97 apart
    slow_device = CostModel.for_device(H10, LINE_9600_8E1, processing_s=0.5)
    assert shape(plan_reads(near, H10, cost_of(H10))) == (
        (0x600, 5, ("logbook_1_entry_type", "logbook_1_operating_seconds")),
    )
    assert len(plan_reads(far, H10, cost_of(H10))) == 2
    assert len(plan_reads(far, H10, slow_device)) == 1


# --- limits and splits -----------------------------------------------------------------


def test_max_registers_is_honoured() -> None:
    points = TECLINE.points_in(PollGroup.PROCESS)
    cost = cost_of(TECLINE)
    assert shape(plan_reads(points, TECLINE, cost, max_registers=4)) == (
        (0, 4, ("concentration", "cell_current")),
        (4, 2, ("temperature",)),
    )
    assert len(plan_reads(points, TECLINE, cost, max_registers=2)) == 3


@pytest.mark.parametrize(("limit", "reads"), [(4, 2), (5, 1), (6, 1)])
def test_max_registers_is_exact(limit: int, reads: int) -> None:
    profile = two_floats(1)  # one read of 5 registers, or two of 2
    cost = CostModel.for_device(profile, LINE_9600_8E1)
    assert len(plan_reads(profile.points, profile, cost, max_registers=limit)) == reads


def test_equal_plans_fill_the_first_reads() -> None:
    # Ten contiguous floats, 8 registers per read: every 3-read plan costs the same.
    points = [float_point(f"f{i}", 2 * i) for i in range(10)]
    profile = synthetic(points, ((0, 0x1FF),))
    blocks = plan_reads(points, profile, cost_of(profile), max_registers=8)
    assert [(b.address, b.count) for b in blocks] == [(0, 8), (8, 8), (16, 4)]


@pytest.mark.parametrize("limit", [0, 126])
def test_max_registers_outside_the_modbus_range_is_refused(limit: int) -> None:
    with pytest.raises(ConfigError, match="max_registers"):
        plan_reads(
            TECLINE.points_in(PollGroup.PROCESS), TECLINE, cost_of(TECLINE), max_registers=limit
        )


def test_a_point_longer_than_max_registers_is_refused() -> None:
    with pytest.raises(ConfigError, match="clock, clock_year need 7 registers"):
        plan_reads(
            [S10.point("clock_year"), S10.point("clock")], S10, cost_of(S10), max_registers=6
        )


def test_split_before_separates_neighbours() -> None:
    points = H10.points_in(PollGroup.PROCESS, PollGroup.STATUS)
    blocks = plan_reads(points, H10, cost_of(H10), split_before=frozenset({0x2003, 0x3005}))
    assert shape(blocks) == (
        (0x2001, 2, ("oxygen",)),
        (0x2003, 4, ("temperature", "error_register")),
        (0x3001, 2, ("measurement_status",)),  # 0x3005 lies in the hole
        (0x3007, 2, ("status",)),
    )


def test_split_inside_a_point_is_ignored() -> None:
    points = H10.points_in(PollGroup.PROCESS)
    cost = cost_of(H10)
    inside = plan_reads(points, H10, cost, split_before=frozenset({0x2002, 0x2004}))
    assert inside == plan_reads(points, H10, cost)


def test_split_in_a_long_contiguous_set_is_honoured() -> None:
    points = tuple(p for p in H10.points if p.repeat == "logbook")
    split = frozenset({0x631, 0x662})  # the starts of entries 2 and 3
    blocks = plan_reads(points, H10, cost_of(H10), split_before=split)
    assert_valid(blocks, points, H10, limit=125, split_before=split)
    assert {0x631, 0x662} <= {b.address for b in blocks}


# --- the points given ------------------------------------------------------------------


def test_no_points_no_reads() -> None:
    assert plan_reads([], H10, cost_of(H10)) == ()


def test_duplicates_count_once() -> None:
    oxygen = S10.point("oxygen")
    assert shape(plan_reads([oxygen, oxygen], S10, cost_of(S10))) == ((0x2600, 2, ("oxygen",)),)


def test_a_view_shares_the_read_of_its_register() -> None:
    blocks = plan_reads([S10.point("clock_year"), S10.point("clock")], S10, cost_of(S10))
    assert shape(blocks) == ((0x2840, 7, ("clock", "clock_year")),)
    assert shape(plan_reads([S10.point("clock_year")], S10, cost_of(S10))) == (
        (0x2840, 1, ("clock_year",)),
    )


def test_a_point_of_another_profile_is_refused() -> None:
    with pytest.raises(ConfigError, match="not the one of profile"):
        plan_reads([TECLINE.point("temperature")], H10, cost_of(H10))
    with pytest.raises(ConfigError, match="no point"):
        plan_reads([TECLINE.point("concentration")], H10, cost_of(H10))


def test_a_point_outside_the_readable_runs_is_refused() -> None:
    profile = synthetic([float_point("a", 0), float_point("b", 0x10)], ((0, 0xF),))
    with pytest.raises(ConfigError, match="outside every readable run"):
        plan_reads(profile.points, profile, cost_of(profile))


def test_blocks_print_for_logs() -> None:
    (block,) = plan_reads(TECLINE.points_in(PollGroup.PROCESS), TECLINE, cost_of(TECLINE))
    assert str(block) == "0x0000+6 (concentration, cell_current, temperature)"


# --- the cached planner ----------------------------------------------------------------


def test_planner_caches_by_names_and_splits() -> None:
    planner = Planner(H10, cost_of(H10))
    points = H10.points_in(PollGroup.PROCESS, PollGroup.STATUS)
    first = planner.plan(points)
    assert planner.plan(reversed(points)) is first
    assert planner.plan([*points, points[0]]) is first
    assert first == plan_reads(points, H10, cost_of(H10))
    split = planner.plan(points, split_before=frozenset({0x2003}))
    assert split != first
    assert planner.plan(points, split_before=frozenset({0x2003})) is split
    planner.clear()
    assert planner.plan(points) is not first


def test_planner_keeps_the_most_recently_used_plans() -> None:
    planner = Planner(H10, cost_of(H10), cache_size=2)
    a, b, c = ([H10.point(name)] for name in ("oxygen", "temperature", "status"))
    plan_a = planner.plan(a)
    plan_b = planner.plan(b)
    assert planner.plan(a) is plan_a  # a is now the most recent
    planner.plan(c)  # evicts b
    assert planner.plan(a) is plan_a
    assert planner.plan(b) is not plan_b


def test_planner_checks_its_limit_at_once() -> None:
    with pytest.raises(ConfigError, match="max_registers"):
        Planner(H10, cost_of(H10), max_registers=200)


# --- any subset of any profile ---------------------------------------------------------


@st.composite
def requests(
    draw: st.DrawFn, max_points: int
) -> tuple[Profile, list[Point], int, frozenset[int], LineFormat]:
    profile = draw(st.sampled_from(PROFILES))
    limit = draw(st.integers(2, 125))
    candidates = [p for p in profile.points if p.count <= limit]
    points = draw(st.lists(st.sampled_from(candidates), max_size=max_points))
    low = min((p.address for p in points), default=0)
    high = max((p.last for p in points), default=0) + 1
    near = st.integers(low, high)
    if points:  # splits where they matter most: at the requested points
        near |= st.sampled_from([p.address for p in points])
    splits = draw(st.frozensets(near, max_size=8))
    line = LineFormat(
        baudrate=draw(st.sampled_from([1200, 9600, 19200, 38400, 115200])),
        parity=draw(st.sampled_from(["N", "E", "O"])),
    )
    return profile, points, limit, splits, line


@settings(max_examples=200)
@given(request=requests(max_points=9))
def test_small_sets_match_the_brute_force(
    request: tuple[Profile, list[Point], int, frozenset[int], LineFormat],
) -> None:
    profile, points, limit, splits, line = request
    cost = cost_of(profile, line)
    blocks = plan_reads(points, profile, cost, split_before=splits, max_registers=limit)
    assert_valid(blocks, points, profile, limit=limit, split_before=splits)
    assert shape(blocks) == brute_force(points, profile, cost, limit=limit, split_before=splits)


@settings(max_examples=100)
@given(request=requests(max_points=6))
def test_no_grouping_of_any_kind_beats_the_plan(
    request: tuple[Profile, list[Point], int, frozenset[int], LineFormat],
) -> None:
    # Every set partition, consecutive or not, overlapping reads allowed: the claim that
    # cutting the sorted points is enough.
    profile, points, limit, splits, line = request
    cost = cost_of(profile, line)
    plan_s = cost.plan_s(
        plan_reads(points, profile, cost, split_before=splits, max_registers=limit)
    )
    for partition in set_partitions(distinct_sorted(points)):
        if all(block_ok(g, profile, limit, splits) for g in partition):
            assert plan_s <= sum(cost.read_s(span(g)) for g in partition) + 1e-12


@settings(max_examples=60)
@given(request=requests(max_points=120))
def test_large_sets_are_valid_and_optimal(
    request: tuple[Profile, list[Point], int, frozenset[int], LineFormat],
) -> None:
    profile, points, limit, splits, line = request
    cost = cost_of(profile, line)
    blocks = plan_reads(points, profile, cost, split_before=splits, max_registers=limit)
    assert_valid(blocks, points, profile, limit=limit, split_before=splits)
    reference = reference_s(points, profile, cost, limit=limit, split_before=splits)
    assert cost.plan_s(blocks) == pytest.approx(reference)
    assert cost.plan_s(blocks) <= per_point_s(points, cost) + 1e-12
