"""Which reads cover which points of each device of one line: the planners and their plans.

A plan depends on the profile, the line's format and the device's extra gap (its cost
model), and on the addresses the device refused to read together (its splits): so one
planner, with its cache of plans, serves every device of one profile and cost on the line.
A reload that changes the line starts them anew (:meth:`ReadPlans.use_format`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Final

from gateway.line.engine.plan import CostModel, Planner

if TYPE_CHECKING:
    from collections.abc import Sequence

    from gateway.line.engine.devices import DeviceState
    from gateway.line.engine.plan import ReadBlock
    from gateway.profiles import Point
    from gateway.wire.timing import LineFormat

_NO_SPLITS: Final[frozenset[int]] = frozenset()


class ReadPlans:
    """The read blocks of the points a poll, a command or a probe asks of a device."""

    def __init__(self, line_format: LineFormat) -> None:
        """Plan for a line of ``line_format``; devices come with :meth:`add`."""
        self.line_format = line_format
        # One planner (and its cache of plans) for the devices of one profile and cost: a
        # plan depends on nothing else, and a bus of sixteen sensors of four families kept
        # sixteen caches of the same plans.
        self._shared: dict[tuple[str, CostModel], Planner] = {}
        self._planners: dict[str, Planner] = {}

    def add(self, state: DeviceState) -> None:
        """Plan the reads of a device (at the start, or one a reload added or re-planned)."""
        cost = CostModel.for_device(
            state.profile, self.line_format, extra_gap_s=state.target.extra_gap_s
        )
        key = (state.profile.id, cost)
        if key not in self._shared:
            self._shared[key] = Planner(state.profile, cost)
        self._planners[state.target.name] = self._shared[key]

    def use_format(self, line_format: LineFormat) -> None:
        """Another line, maybe of another format (a reload): every device to be added again."""
        self.line_format = line_format
        self._shared.clear()
        self._planners.clear()

    def remove(self, state: DeviceState) -> None:
        """Forget a device a reload removed or re-plans."""
        self._planners.pop(state.target.name, None)

    def plan(self, state: DeviceState, names: Sequence[str]) -> tuple[ReadBlock, ...]:
        """The reads of the named points of the device (the schedule names what is due)."""
        planner = self._planners[state.target.name]
        split = frozenset(state.holds.split_before) if state.holds.split_before else _NO_SPLITS
        return self._learn_first(state, planner.plan_names(names, split_before=split))

    def plan_points(self, state: DeviceState, points: Sequence[Point]) -> tuple[ReadBlock, ...]:
        """The reads of points of the device's profile."""
        planner = self._planners[state.target.name]
        split = frozenset(state.holds.split_before) if state.holds.split_before else _NO_SPLITS
        return self._learn_first(state, planner.plan(points, split_before=split))

    @staticmethod
    def _learn_first(state: DeviceState, blocks: tuple[ReadBlock, ...]) -> tuple[ReadBlock, ...]:
        learn = state.target.min_response_point
        if learn is not None and len(blocks) > 1 and learn.name not in state.values:
            # The block with the device's minimum response time first: the reads after
            # it in the same turn then wait as long as the device takes (``learning_wait``).
            first = [b for b in blocks if learn in b.points]
            blocks = (*first, *(b for b in blocks if b not in first))
        return blocks

    def plan_slow(self, state: DeviceState, names: Sequence[str]) -> tuple[ReadBlock, ...]:
        """The reads of due diagnostics: the blocks of their whole interval classes.

        Diagnostics are read a block at a time and cut short whenever values fall due, so
        the set still due is a different one after every interruption. Planning each such
        set anew missed the plan cache nearly every time (an H10 has some 260 slow points)
        and took a third of the gateway's CPU at 480 devices. The plan of every slow point
        sharing an interval with a due one has a stable key; its blocks that hold a due
        point are the ones to read, and points that come along were read in the same phase.
        """
        intervals = state.target.intervals
        wanted = {intervals.get(name) for name in names}
        members = [  # in any order: the planner keys its cache by the set
            name
            for name in state.target.slow_points
            if intervals.get(name) in wanted
            and name not in state.holds.unreadable
            and name not in state.deadlines.identity_pending
        ]
        due = set(names)
        return tuple(
            block
            for block in self.plan(state, members)
            if any(point.name in due for point in block.points)
        )
