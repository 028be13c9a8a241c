"""One device's poll: a plan for the moment, run by the transactions, results back in one call.

A poll is three steps, each with its own owner, as a compiled request list is in the masters
users know (Telegraf compiles its requests once and executes them):

1. **plan**: the schedule says which points are due and in which order their reads go
   (:meth:`~gateway.line.engine.schedule.Schedule.due_points`,
   :meth:`~gateway.line.engine.schedule.Schedule.in_order`); the read plans say which
   reads cover them (:class:`~gateway.line.engine.read_plans.ReadPlans`, cached blocks).
   The result is a :class:`PollPlan`, made before the first request goes out and not
   changed while it runs.
2. **run**: the transactions read the plan's blocks in order
   (:meth:`~gateway.line.engine.transactions.Transactions.read_plan`), stopping early
   where a failure's wait or an offline verdict holds the device, or (diagnostics) where
   values fall due elsewhere.
3. **report**: what was read goes back to the schedule in one call
   (:meth:`~gateway.line.engine.schedule.Schedule.advance`); a late poll is explained;
   the samples go through the identity guard to the sinks.

The poll step keeps nothing of a device's state itself: every field it reads is written
by the part that owns it (``line/engine/devices``).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

from gateway.line.engine.lateness import Lateness

if TYPE_CHECKING:
    from collections.abc import Sequence

    from gateway.line.boundary import Line
    from gateway.line.engine.devices import DeviceState
    from gateway.line.engine.identity_guard import IdentityGuard
    from gateway.line.engine.lateness import LoopWatch
    from gateway.line.engine.plan import ReadBlock
    from gateway.line.engine.schedule import Schedule
    from gateway.line.engine.transactions import Transactions
    from gateway.line.samples import Sample, Sink

_LOGGER = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True)
class PollPlan:
    """The reads of one poll of one device, in the order they go out."""

    state: DeviceState
    at: float  # the moment it was planned for: the poll's deadlines are judged from it
    slow: bool  # diagnostics (read in the time values leave free) or values
    blocks: Sequence[ReadBlock]
    held_until: float  # the device's wait when planned, ended by then: for a late poll's reason


class Poller:
    """Polls one device at a time for a line's worker: plan, run, report."""

    def __init__(
        self,
        *,
        bus: str,
        line: Line,
        schedule: Schedule,
        transactions: Transactions,
        identity: IdentityGuard,
        sinks: list[Sink],
    ) -> None:
        """Poll with the worker's parts; ``sinks`` is the worker's list, read at each poll."""
        self.bus = bus
        self.schedule = schedule
        self.transactions = transactions
        self.identity = identity
        self.sinks = sinks
        self.lateness = Lateness(line)  # what made a late poll late, for the log

    def use_line(self, line: Line) -> None:
        """Mark the busy time of ``line`` from now on (a reload changed the bus's settings)."""
        self.lateness = Lateness(line, self.lateness.watch)

    def watch_loop(self, watch: LoopWatch) -> None:
        """Tell the loop's lateness apart from the line's with ``watch`` (while the worker runs)."""
        self.lateness.watch = watch

    def plan(self, state: DeviceState, now: float, *, slow: bool) -> PollPlan:
        """What one poll of ``state`` reads at ``now``: the due points' reads, oldest first."""
        names = self.schedule.due_points(state, now, slow=slow)
        plans = self.transactions.plans
        blocks = plans.plan_slow(state, names) if slow else plans.plan(state, names)
        return PollPlan(
            state=state,
            at=now,
            slow=slow,
            blocks=self.schedule.in_order(state, blocks),
            held_until=state.holds.not_before,
        )

    async def poll(self, state: DeviceState, now: float, *, slow: bool) -> None:
        """Plan, run and report one poll of ``state``."""
        self.lateness.mark(now)
        plan = self.plan(state, now, slow=slow)
        # Run as planned: the plan, not the caller's arguments, says what and how.
        samples = await self.transactions.read_plan(
            plan.state, plan.blocks, yield_to_values=self._values_due if plan.slow else None
        )
        self._report_late(plan, samples)
        # Only a pinned device's samples wait on its identity: the others go as they are.
        published = (
            await self.identity.screen(state, samples) if self.identity.screens(state) else samples
        )
        if published:
            for sink in self.sinks:
                await sink.publish(published)

    def _values_due(self) -> bool:
        """Whether values are due on the line now: diagnostics give way to them."""
        return self.schedule.pick(time.monotonic(), slow=False) is not None

    def _report_late(self, plan: PollPlan, samples: Sequence[Sample]) -> None:
        """The read points' deadlines moved on; a poll more than an interval late explained."""
        state = plan.state
        late = self.schedule.advance(state, [s.point for s in samples], plan.at)
        if late is not None:
            # The line, or the process: what took the time decides the remedy.
            _LOGGER.warning(
                "%s/%s: %s",
                self.bus,
                state.target.name,
                self.lateness.explain(late, plan.at, held_until=plan.held_until),
            )
