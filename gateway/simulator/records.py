"""What the simulated bus sends and keeps: replies, the frame log, violations and the stats."""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from collections.abc import Mapping

    from gateway.simulator.device import SimulatedDevice
    from gateway.wire.timing import LineFormat


@dataclass(frozen=True, slots=True)
class Reply:
    """Bytes to put on the line at ``at`` (monotonic seconds, end of transmission)."""

    at: float
    data: bytes
    kind: str  # "response", "late", "noise"
    device: int


@dataclass(slots=True)
class FrameRecord:
    """One frame the bus received, and what became of it: for wire-timed tests."""

    start: float  # first byte, seconds since the bus started
    device: int
    function: int
    address: int
    quantity: int  # bytes 4-5: registers of a 03, 04 or 16 (an 06's value), else -1
    outcome: str  # "answered", "broadcast", "ignored:<rule>", "silent", "crc", ...
    answer_at: float | None = None

    @classmethod
    def of(cls, frame: bytes, start: float) -> FrameRecord:
        """The record of ``frame`` as it arrives (``start`` since the bus started)."""
        return cls(
            start=start,
            device=frame[0] if frame else -1,
            function=frame[1] if len(frame) > 1 else -1,
            address=int.from_bytes(frame[2:4], "big") if len(frame) >= 4 else -1,  # noqa: PLR2004
            quantity=int.from_bytes(frame[4:6], "big") if len(frame) >= 6 else -1,  # noqa: PLR2004
            outcome="answered",
        )


@dataclass(slots=True)
class Violation:
    """A request the referee ignored because the master broke a timing rule."""

    time: float
    rule: str  # "inter_frame_gap", "post_write_wait", "answer_in_progress"
    device: int
    required_s: float
    actual_s: float
    request: str

    def as_dict(self) -> dict[str, Any]:
        """The violation as stats-file data."""
        return {
            "time": round(self.time, 6),
            "rule": self.rule,
            "device": self.device,
            "required_s": round(self.required_s, 6),
            "actual_s": round(self.actual_s, 6),
            "request": self.request,
        }


def bus_stats(
    *,
    line: LineFormat,
    pace: bool,
    started: float,
    counters: Counter[str],
    exceptions: Counter[int],
    injected: Counter[str],
    violations: list[Violation],
    devices: Mapping[int, SimulatedDevice],
    requests_by_device: Counter[int],
) -> dict[str, Any]:
    """Everything a test wants to know about a run, as JSON-ready data."""
    by_rule = Counter(v.rule for v in violations)
    return {
        "line": str(line),
        "pace": pace,
        "counters": dict(counters),
        "exceptions": {str(code): n for code, n in sorted(exceptions.items())},
        "faults_injected": dict(injected),
        "timing_violations": len(violations),
        "violations_by_rule": dict(by_rule),
        "violations": [v.as_dict() for v in violations[-1000:]],
        "devices": {
            str(address): {
                "profile": device.profile.id,
                "requests": requests_by_device[address],
                "writes": _writes(device, started),
            }
            for address, device in sorted(devices.items())
        },
    }


def _writes(device: SimulatedDevice, started: float) -> list[dict[str, Any]]:
    return [
        {
            "time": round(w.time - started, 6),
            "function": w.function,
            "address": w.address,
            "values": list(w.values),
            "points": list(w.points),
            "exception": w.exception,
        }
        for w in device.write_log
    ]
