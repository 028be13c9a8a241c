"""The read planner: the points of one device due at a tick, as the cheapest set of reads.

Cost model
----------
One read (function 03) costs bus time, :meth:`CostModel.read_s`::

    read_s(count) = wire(8 + 5 + 2 * count bytes) + processing_s + 2 * gap_s

the request (8 bytes) and the response (5 bytes and 2 per register) on the wire, the
device's answer delay t1, and the inter-frame gap before each of the two frames. Every
read pays a fixed overhead; every register pays two characters. Merging two neighbouring
reads saves one overhead and pays for the registers of the hole between them, so at
9600 8E1 (about 28 ms of overhead, 2.3 ms per register) holes of up to 12 registers are
worth reading and longer ones are not. The planner does not apply that rule of thumb: it
minimises the total ``read_s`` over every valid plan, so the line and the device decide.

A valid plan
------------
Each block is one read: it lies inside one readable run of the profile (reading an
unmapped address is exception 02 on all four families), takes at most ``max_registers``
registers, never holds both ``a - 1`` and ``a`` for an address ``a`` of ``split_before``,
and never splits a point. Points that overlap (a view and the register it views) are one
*unit*: they share a block, since reading the common registers twice never pays.

Why consecutive groups are enough
---------------------------------
A block is the address range from its first to its last requested register; registers
outside that range would only add cost. Sort the units by address. If a block holds units
``p`` and ``r`` and another block holds ``q``, with ``p < q < r``, then ``q`` already lies
inside the first block's range: move ``q`` there. The first block is unchanged and the
other shrinks or disappears; a shorter range stays inside its run, under the limit and
clear of the splits, and ``read_s`` grows with ``count``, so the plan got no dearer.
Repeating this turns any optimal plan into one whose blocks are runs of consecutive units,
so a dynamic programme over cut positions in the sorted units finds the optimum: the best
plan of the first ``j`` units is the best plan of the first ``i`` plus one block of units
``i..j-1``, minimised over ``i``. That is O(n²) block evaluations, far fewer in practice
because a block that breaks a rule only gets worse as it grows to the left.
"""

from __future__ import annotations

import bisect
import itertools
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Final

from gateway.errors import ConfigError
from gateway.wire.frames import MAX_READ_REGISTERS, READ_REQUEST_LENGTH
from gateway.wire.timing import TYPICAL_PROCESSING_S

if TYPE_CHECKING:
    from collections.abc import Iterable

    from gateway.profiles.model import Point, Profile
    from gateway.wire.timing import LineFormat

READ_RESPONSE_OVERHEAD: Final = 5  # device, function, byte count, CRC (2); S10 manual 2.4.1
TIE_S: Final = 1e-9  # plans closer than this cost the same; float noise is far smaller


@dataclass(frozen=True, slots=True, kw_only=True)
class CostModel:
    """Bus time of one read transaction on a line, for one device.

    Example::

        CostModel.for_device(get_profile("jumo-digiline-odo-s10"), LineFormat(parity="E"))
    """

    line: LineFormat
    processing_s: float  # the device's answer delay t1 (an estimate, for planning)
    gap_s: float  # inter-frame gap before each frame

    def __post_init__(self) -> None:
        """Refuse negative times: they would make larger reads look free."""
        if self.processing_s < 0 or self.gap_s < 0:
            raise ConfigError(
                f"processing_s ({self.processing_s}) and gap_s ({self.gap_s}) must not be negative",
                key="cost",
            )

    @classmethod
    def for_device(
        cls,
        profile: Profile,
        line: LineFormat,
        *,
        processing_s: float | None = None,
        extra_gap_s: float = 0.0,
    ) -> CostModel:
        """The cost model of a device of ``profile`` on ``line``.

        ``processing_s`` defaults to the typical t1 of 5 ms (S10 and H10/H20 manual 5.1),
        not the profile's ``timing.processing_time_s``: that is the upper bound the bus
        waits for before giving up, while a plan should weigh what a read usually costs.
        An upper bound would overprice every transaction and merge reads across holes
        that cost more than they save. Pass a measured t1, or add a device's configured
        minimum response time (digiLine 0x0305), when known. ``extra_gap_s`` is a
        line-wide minimum gap that a slow converter or another device may need.
        """
        return cls(
            line=line,
            processing_s=TYPICAL_PROCESSING_S if processing_s is None else processing_s,
            gap_s=line.frame_gap_s(max(profile.timing.min_gap_s, extra_gap_s)),
        )

    def read_s(self, count: int) -> float:
        """Bus time of one read of ``count`` registers: both frames, t1 and two gaps."""
        nbytes = READ_REQUEST_LENGTH + READ_RESPONSE_OVERHEAD + 2 * count
        return self.line.wire_s(nbytes) + self.processing_s + 2 * self.gap_s

    def plan_s(self, blocks: Iterable[ReadBlock]) -> float:
        """Bus time of a whole plan."""
        return sum(self.read_s(block.count) for block in blocks)


@dataclass(frozen=True, slots=True)
class ReadBlock:
    """One read: ``count`` registers from ``address``, delivering ``points``."""

    address: int
    count: int
    points: tuple[Point, ...]  # the requested points inside the block, in address order

    @property
    def last(self) -> int:
        """Address of the block's last register."""
        return self.address + self.count - 1

    def __str__(self) -> str:
        """``0x2001+6 (oxygen, temperature, error_register)``, for logs."""
        names = ", ".join(p.name for p in self.points)
        return f"{self.address:#06x}+{self.count} ({names})"


@dataclass(frozen=True, slots=True)
class _Unit:
    """Requested points that must share a read: one point, or points that overlap."""

    first: int
    last: int
    run_last: int  # end of the readable run holding the unit
    points: tuple[Point, ...]


def _read_limit(profile: Profile, max_registers: int | None) -> int:
    limit = profile.limits.max_read if max_registers is None else max_registers
    if not 1 <= limit <= MAX_READ_REGISTERS:
        raise ConfigError(
            f"max_registers must be 1 to {MAX_READ_REGISTERS}, not {limit}", key="max_registers"
        )
    return limit


def require_own(profile: Profile, point: Point) -> None:
    """A :class:`ConfigError` unless ``point`` is the profile's own.

    A check of a point already resolved, not a lookup: the name is looked up only to word
    the error of a name the profile does not have (its error lists the close ones).
    """
    if not profile.owns(point):
        profile.point(point.name)
        raise ConfigError(
            f"point {point.name!r} is not the one of profile {profile.id}", key="points"
        )


def _requested(points: Iterable[Point], profile: Profile) -> list[Point]:
    """The distinct requested points in address order; each must be the profile's own."""
    by_name: dict[str, Point] = {}
    for point in points:
        if point.name in by_name:
            continue
        require_own(profile, point)
        by_name[point.name] = point
    return sorted(by_name.values(), key=lambda p: (p.address, p.view, p.name))


def _units(points: list[Point], profile: Profile, limit: int) -> list[_Unit]:
    """Group overlapping points; check that each group can be read at all."""
    units: list[_Unit] = []
    group: list[Point] = []
    reach = -1  # last register of the group so far
    for point in points:
        if group and point.address > reach:
            units.append(_unit(group, reach, profile, limit))
            group = []
        group.append(point)
        reach = max(reach, point.last)
    if group:
        units.append(_unit(group, reach, profile, limit))
    return units


def _unit(group: list[Point], last: int, profile: Profile, limit: int) -> _Unit:
    first = group[0].address
    names = ", ".join(p.name for p in group)
    if last - first + 1 > limit:
        raise ConfigError(
            f"{names} need {last - first + 1} registers in one read; the limit is {limit}",
            key="max_registers",
        )
    run = profile.readable_run(first)
    if run is None or last > run[1]:
        raise ConfigError(
            f"{names} ({first:#06x}..{last:#06x}) lie outside every readable run "
            f"of profile {profile.id}",
            key="points",
        )
    return _Unit(first=first, last=last, run_last=run[1], points=tuple(group))


def _cheaper(candidate: tuple[float, int], incumbent: tuple[float, int]) -> bool:
    """Whether a (bus time, reads) pair beats another; a tie is broken by fewer reads."""
    if abs(candidate[0] - incumbent[0]) <= TIE_S:
        return candidate[1] < incumbent[1]
    return candidate[0] < incumbent[0]


def plan_reads(
    points: Iterable[Point],
    profile: Profile,
    cost: CostModel,
    *,
    split_before: frozenset[int] = frozenset(),
    max_registers: int | None = None,
) -> tuple[ReadBlock, ...]:
    """The cheapest valid reads of ``points``, in address order (see the module docstring).

    ``max_registers`` defaults to the profile's ``limits.max_read``. An address of
    ``split_before`` inside a requested point cannot be honoured without splitting the
    point and is ignored: the point alone is then the smallest read of it. Among plans of
    equal cost (within :data:`TIE_S`) the one with fewer reads wins, then the one whose
    last read is shortest, and so on backwards: earlier reads take all they can.

    Raises :class:`ConfigError` for a point that is not the profile's own, lies outside
    its readable runs, or (with the points overlapping it) needs more than
    ``max_registers`` registers.
    """
    limit = _read_limit(profile, max_registers)
    units = _units(_requested(points, profile), profile, limit)
    splits = sorted(a for a in split_before if not any(u.first < a <= u.last for u in units))

    def valid(first: int, last: int, run_last: int) -> bool:
        after = bisect.bisect_right(splits, first)  # first split address above ``first``
        crosses = after < len(splits) and splits[after] <= last
        return last - first + 1 <= limit and last <= run_last and not crosses

    # best[j]: (bus time, reads) of the cheapest plan of units[:j]; start[j]: where its
    # last block starts. Equal costs (to the nanosecond, not to the rounding noise of
    # the sums) go to fewer reads, then to the shortest last read, and so on backwards.
    best: list[tuple[float, int]] = [(0.0, 0)] + [(math.inf, 0)] * len(units)
    start = [0] * (len(units) + 1)
    read_s = [cost.read_s(count) for count in range(limit + 1)]  # the inner loop's costs
    for end in range(1, len(units) + 1):
        last = units[end - 1].last
        for begin in range(end - 1, -1, -1):
            unit = units[begin]
            if not valid(unit.first, last, unit.run_last):
                break  # growing the block to the left keeps it invalid
            before_s, before_reads = best[begin]
            candidate = (before_s + read_s[last - unit.first + 1], before_reads + 1)
            if _cheaper(candidate, best[end]):
                best[end], start[end] = candidate, begin

    blocks: list[ReadBlock] = []
    end = len(units)
    while end:
        begin = start[end]
        first, last = units[begin].first, units[end - 1].last
        chosen = tuple(itertools.chain.from_iterable(u.points for u in units[begin:end]))
        blocks.append(ReadBlock(first, last - first + 1, chosen))
        end = begin
    return tuple(reversed(blocks))


class Planner:
    """The plans of one device, cached by the set of point names and ``split_before``.

    The bus engine asks for the same few sets again and again (the groups due at a
    tick), so each plan is computed once. The cache keeps the ``cache_size`` most
    recently used plans. Points must be ``profile``'s own, as for :func:`plan_reads`;
    names are the key.

    Example::

        planner = Planner(profile, CostModel.for_device(profile, line))
        blocks = planner.plan(profile.points_in(PollGroup.PROCESS, PollGroup.STATUS))
    """

    __slots__ = ("_cache", "cache_size", "cost", "max_registers", "profile")

    def __init__(
        self,
        profile: Profile,
        cost: CostModel,
        *,
        max_registers: int | None = None,
        cache_size: int = 64,
    ) -> None:
        """Plan for a device of ``profile`` with the given cost model and read limit."""
        _read_limit(profile, max_registers)  # fail at construction, not at the first tick
        self.profile = profile
        self.cost = cost
        self.max_registers = max_registers
        self.cache_size = max(cache_size, 1)
        self._cache: dict[tuple[frozenset[str], frozenset[int]], tuple[ReadBlock, ...]] = {}

    def plan(
        self, points: Iterable[Point], *, split_before: frozenset[int] = frozenset()
    ) -> tuple[ReadBlock, ...]:
        """The plan of :func:`plan_reads` for ``points``, from the cache when known."""
        chosen = tuple(points)
        key = (frozenset(p.name for p in chosen), split_before)
        blocks = self._cache.pop(key, None)  # re-inserted below: most recently used last
        if blocks is None:
            blocks = plan_reads(
                chosen,
                self.profile,
                self.cost,
                split_before=split_before,
                max_registers=self.max_registers,
            )
            if len(self._cache) >= self.cache_size:
                del self._cache[next(iter(self._cache))]  # the least recently used
        self._cache[key] = blocks
        return blocks

    def plan_names(
        self, names: Iterable[str], *, split_before: frozenset[int] = frozenset()
    ) -> tuple[ReadBlock, ...]:
        """The plan of the profile's points named ``names``, as :meth:`plan` gives it.

        Keyed by the names as they come: the points are looked up only to make a plan
        the cache does not hold, not on every poll.
        """
        key = (frozenset(names), split_before)
        blocks = self._cache.pop(key, None)
        if blocks is None:
            point = self.profile.point
            return self.plan([point(name) for name in key[0]], split_before=split_before)
        self._cache[key] = blocks  # most recently used last
        return blocks

    def clear(self) -> None:
        """Forget every cached plan."""
        self._cache.clear()
