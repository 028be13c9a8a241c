"""The referee of a simulated line: the master's timing, judged as the strict manuals read it.

A request inside the inter-frame gap, inside a device's post-write wait, or while an
answer is still on the line is ignored and recorded as a :class:`Violation`; one that
collides with a late answer or noise is the slave's fault and only counted.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Final

from gateway.simulator.records import Violation

if TYPE_CHECKING:
    from collections import Counter

    from gateway.simulator.device import SimulatedDevice
    from gateway.simulator.records import Reply
    from gateway.wire.timing import LineFormat

# A request that starts this soon after a late answer or noise began had been sent before
# the master could hear it: a collision, not a gap the master failed to keep.
COLLISION_WINDOW_S: Final = 0.001


@dataclass(slots=True, kw_only=True)
class Referee:
    """What is on the line and when it ended; whether a request keeps the timing rules.

    ``violations`` and ``counters`` are the bus's own: the referee appends and counts.
    """

    line: LineFormat
    violations: list[Violation]
    counters: Counter[str]
    last_frame_end: float = float("-inf")
    answer_until: float = float("-inf")
    unsolicited_end: float = float("-inf")  # the last late answer or noise on the line

    def judge(
        self, frame: bytes, start: float, *, device: SimulatedDevice | None, started: float
    ) -> bool:
        """Whether a request whose first byte arrived at ``start`` may be answered.

        ``device``: the one the frame addresses, if it is on the line; ``started``: when
        the bus started, the origin of a violation's time.
        """
        gap = start - self.last_frame_end
        min_gap = device.profile.timing.min_gap_s if device else 0.0
        required = self.line.frame_gap_s(min_gap)
        if gap < required and start - self.unsolicited_end < COLLISION_WINDOW_S:
            # A late answer or noise went out as the master was already sending: on a real
            # line the two collide. The slave's fault, not the master's: counted apart,
            # and the garbled request is not answered.
            self.counters["collisions"] += 1
            return False
        if gap < required:
            self._violate("inter_frame_gap", frame, start - started, required, gap)
            return False
        if start < self.answer_until:
            until = self.answer_until - start
            self._violate("answer_in_progress", frame, start - started, until, 0.0)
            return False
        if device is not None and start < device.last_write_end + device.last_write_wait_s:
            since = start - device.last_write_end
            wait_s = device.last_write_wait_s
            self._violate("post_write_wait", frame, start - started, wait_s, since)
            return False
        return True

    def frame_ended(self, end: float) -> None:
        """A frame was on the line until ``end``: the next gap counts from there."""
        self.last_frame_end = max(self.last_frame_end, end)

    def answering_until(self, at: float) -> None:
        """An answer will be on the line until ``at``: a request before then is too early."""
        self.answer_until = at

    def on_sent(self, reply: Reply, now: float, *, late: bool = False) -> None:
        """Note when a reply really left, so the next gap is measured from there.

        ``late``: it left later than the device's timing says (the simulator was held up).
        """
        self.last_frame_end = max(self.last_frame_end, now)
        if reply.kind == "response" and not late:
            self.answer_until = now  # the answer is complete on the line
        else:
            self.unsolicited_end = now  # a late answer or noise: no master can foresee it

    def _violate(
        self, rule: str, frame: bytes, time: float, required: float, actual: float
    ) -> None:
        self.violations.append(
            Violation(
                time=time,
                rule=rule,
                device=frame[0] if frame else -1,
                required_s=required,
                actual_s=actual,
                request=frame.hex(" "),
            )
        )
        self.counters["ignored"] += 1
