"""A clocked master for sans-I/O tests of the simulated bus: time passes only when told."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from gateway.simulator import SimulatedBus, build_bus, parse_settings
from gateway.wire import frames

if TYPE_CHECKING:
    from gateway.simulator.bus import Reply


def make_bus(*devices: dict[str, Any], **settings: Any) -> SimulatedBus:
    bus = build_bus(parse_settings({"devices": list(devices), **settings}))
    bus.start(0.0)
    return bus


@dataclass
class ClockedMaster:
    """Sends requests at chosen moments and collects what comes back."""

    bus: SimulatedBus
    now: float = 1.0
    gap_s: float = 0.3  # default wait before each request; H10/H20 tests need 0.65 s
    replies: list[Reply] = field(default_factory=list)

    def send(self, request: frames.Request | bytes, *, gap_s: float | None = None) -> list[Reply]:
        """Wait ``gap_s`` after the last frame, send, and take every reply off the line."""
        frame = request.frame if isinstance(request, frames.Request) else request
        self.now += self.gap_s if gap_s is None else gap_s
        replies = self.bus.on_frame(frame, self.now)
        for reply in sorted(replies, key=lambda r: r.at):
            self.bus.on_sent(reply, reply.at)
            self.now = max(self.now, reply.at)
        self.replies.extend(replies)
        return replies

    def ask(
        self, request: frames.Request, *, gap_s: float | None = None, **options: Any
    ) -> frames.Response:
        """Send and parse the single answer (exceptions raise as DeviceExceptionError)."""
        replies = [r for r in self.send(request, gap_s=gap_s) if r.kind == "response"]
        assert len(replies) == 1, f"expected one answer, got {replies}"
        return frames.parse_response(request, replies[0].data, **options)
