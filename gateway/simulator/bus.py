"""A simulated RS485 line, without I/O: frames in with their arrival time, replies out.

The bus is the strict slave side of the manuals: it referees the timing rules (a request
inside the inter-frame gap, inside a device's post-write wait, or while an answer is
still on the line is ignored and counted), answers after the device's processing time,
paces frames at the line's speed when asked to, and injects faults on a seeded schedule.
The transports in :mod:`gateway.simulator.transport` move the bytes.
"""

from __future__ import annotations

import random
from collections import Counter, deque
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Final

from gateway.errors import FrameError
from gateway.simulator.device import SimulatedDevice, SlaveExceptionError
from gateway.wire import frames
from gateway.wire.codec import DataType

if TYPE_CHECKING:
    from gateway.wire.timing import LineFormat

# A request that starts this soon after a late answer or noise began had been sent before
# the master could hear it: a collision, not a gap the master failed to keep.
COLLISION_WINDOW_S: Final = 0.001


@dataclass(slots=True, kw_only=True)
class FaultPlan:
    """Faults to inject into one device's answers: a probability per answer, or a schedule.

    Example::

        FaultPlan(crc=0.05, drop=0.02, silences=[(30.0, 10.0)])
    """

    crc: float = 0.0  # flip one byte of the answer
    drop: float = 0.0  # no answer at all
    late: float = 0.0  # answer after ``late_s``: past a careful master's timeout
    late_s: float = 0.5
    noise: float = 0.0  # random bytes on the line before the answer
    wrong_address: float = 0.0  # the answer carries another device address
    string_byte_count_16bit: bool = False  # answer string reads as both digiLine manuals print
    silences: list[tuple[float, float]] = field(default_factory=list)  # (start_s, duration_s)


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


@dataclass(slots=True)
class SimulatedBus:
    """The devices on one line and the referee of its timing."""

    line: LineFormat
    devices: dict[int, SimulatedDevice]
    faults: dict[int, FaultPlan] = field(default_factory=dict)
    pace: bool = False
    seed: int = 0
    started: float = 0.0
    counters: Counter[str] = field(default_factory=Counter)
    injected: Counter[str] = field(default_factory=Counter)
    exceptions: Counter[int] = field(default_factory=Counter)
    violations: list[Violation] = field(default_factory=list)
    frame_log: deque[FrameRecord] = field(default_factory=lambda: deque(maxlen=200_000))
    requests_by_device: Counter[int] = field(default_factory=Counter)
    last_frame_end: float = float("-inf")
    answer_until: float = float("-inf")
    unsolicited_end: float = float("-inf")  # the last late answer or noise on the line
    _rng: random.Random = field(init=False)

    def __post_init__(self) -> None:
        """Seed the fault dice."""
        self._rng = random.Random(self.seed)

    def start(self, now: float) -> None:
        """Bring every device up: nameplate, configuration, first values."""
        self.started = now
        for device in self.devices.values():
            device.start(now, line=self.line)

    # --- referee -----------------------------------------------------------------------

    def _gap_required(self, address: int) -> float:
        device = self.devices.get(address)
        min_gap = device.profile.timing.min_gap_s if device else 0.0
        return self.line.frame_gap_s(min_gap)

    def _violate(
        self, rule: str, frame: bytes, start: float, required: float, actual: float
    ) -> None:
        self.violations.append(
            Violation(
                time=start - self.started,
                rule=rule,
                device=frame[0] if frame else -1,
                required_s=required,
                actual_s=actual,
                request=frame.hex(" "),
            )
        )
        self.counters["ignored"] += 1

    def _timing_ok(self, frame: bytes, start: float) -> bool:
        gap = start - self.last_frame_end
        required = self._gap_required(frame[0])
        if gap < required and start - self.unsolicited_end < COLLISION_WINDOW_S:
            # A late answer or noise went out as the master was already sending: on a real
            # line the two collide. The slave's fault, not the master's: counted apart,
            # and the garbled request is not answered.
            self.counters["collisions"] += 1
            return False
        if gap < required:
            self._violate("inter_frame_gap", frame, start, required, gap)
            return False
        if start < self.answer_until:
            self._violate("answer_in_progress", frame, start, self.answer_until - start, 0.0)
            return False
        device = self.devices.get(frame[0])
        if device is not None and start < device.last_write_end + device.last_write_wait_s:
            since = start - device.last_write_end
            self._violate("post_write_wait", frame, start, device.last_write_wait_s, since)
            return False
        return True

    # --- frames ------------------------------------------------------------------------

    def on_frame(self, frame: bytes, start: float, *, judged: bool = True) -> list[Reply]:
        """Handle one frame whose first byte arrived at ``start``; replies to put on the line.

        ``judged=False`` answers without refereeing the timing (see the transport's watch).
        """
        self.counters["frames"] += 1
        if not judged:
            self.counters["unjudged"] += 1
        record = FrameRecord(
            start=start - self.started,
            device=frame[0] if frame else -1,
            function=frame[1] if len(frame) > 1 else -1,
            address=int.from_bytes(frame[2:4], "big") if len(frame) >= 4 else -1,  # noqa: PLR2004
            quantity=int.from_bytes(frame[4:6], "big") if len(frame) >= 6 else -1,  # noqa: PLR2004
            outcome="answered",
        )
        self.frame_log.append(record)
        replies = self._on_frame(frame, start, record, judged=judged)
        answers = [r for r in replies if r.kind in {"response", "late"}]
        if answers:
            record.answer_at = answers[-1].at - self.started
        elif record.outcome == "answered":
            record.outcome = "dropped"
        return replies

    def _on_frame(
        self, frame: bytes, start: float, record: FrameRecord, *, judged: bool
    ) -> list[Reply]:
        end = start + (self.line.wire_s(len(frame)) if self.pace else 0.0)
        violations = len(self.violations)
        timing_ok = (self._timing_ok(frame, start) if judged else True) if frame else False
        self.last_frame_end = max(self.last_frame_end, end)
        if not timing_ok:
            record.outcome = (
                f"ignored:{self.violations[-1].rule}"
                if len(self.violations) > violations
                else "ignored"
            )
            return []
        if not frames.crc_ok(frame) or len(frame) < 4:  # noqa: PLR2004 - address, function, CRC
            self.counters["crc_errors"] += 1
            record.outcome = "crc"
            return []
        if frame[0] == frames.BROADCAST:
            self._broadcast(frame, end)
            record.outcome = "broadcast"
            return []
        device = self.devices.get(frame[0])
        if device is None:
            self.counters["other_address"] += 1
            record.outcome = "other_address"
            return []
        self.requests_by_device[device.address] += 1
        if end < device.silent_until or self._scheduled_silence(device.address, end):
            self.counters["silent"] += 1
            record.outcome = "silent"
            return []
        device.tick(end)
        answer, wait_s = self._answer(device, frame, end)
        if answer[1] & 0x80:
            record.outcome = f"exception_{answer[2]:02d}"
        return self._deliver(device, answer, end, wait_s)

    def _scheduled_silence(self, address: int, now: float) -> bool:
        plan = self.faults.get(address)
        if plan is None:
            return False
        elapsed = now - self.started
        return any(begin <= elapsed < begin + length for begin, length in plan.silences)

    def _broadcast(self, frame: bytes, end: float) -> None:
        self.counters["broadcasts"] += 1
        try:
            request = frames.parse_request(frame)
        except FrameError:
            return
        if not request.is_write:
            return
        for device in self.devices.values():
            device.tick(end)
            try:
                device.write(request.address, request.values, function=request.function, now=end)
            except SlaveExceptionError:
                continue
            device.last_write_end = end + device.processing_s
            device.last_write_wait_s = device.profile.post_write_wait(
                request.address, request.count
            )

    def _answer(self, device: SimulatedDevice, frame: bytes, now: float) -> tuple[bytes, float]:
        """The device's answer bytes and the post-write wait the request starts."""
        try:
            request = frames.parse_request(frame)
        except FrameError:
            self.exceptions[frames.ILLEGAL_FUNCTION] += 1
            return frames.exception_response(
                device.address, frame[1] & 0x7F, frames.ILLEGAL_FUNCTION
            ), 0.0
        try:
            if request.function in frames.READ_FUNCTIONS:
                registers = device.read(request.address, request.count)
                quirk = self._string_quirk(device, request)
                self.counters["reads"] += 1
                return frames.read_response(
                    device.address, request.function, registers, byte_count_16bit=quirk
                ), 0.0
            device.write(request.address, request.values, function=request.function, now=now)
        except SlaveExceptionError as exc:
            self.exceptions[exc.code] += 1
            return frames.exception_response(device.address, request.function, exc.code), 0.0
        self.counters["writes"] += 1
        wait = device.profile.post_write_wait(request.address, request.count)
        if request.function == frames.WRITE_SINGLE:
            return frames.write_single_response(
                device.address, request.address, request.values[0]
            ), wait
        return frames.write_multiple_response(device.address, request.address, request.count), wait

    def _string_quirk(self, device: SimulatedDevice, request: frames.Request) -> bool:
        plan = self.faults.get(device.address)
        if plan is None or not plan.string_byte_count_16bit:
            return False
        first = next((p for p in device.profile.points if p.address == request.address), None)
        if first is None or first.dtype is not DataType.STRING:
            return False
        self.injected["string_byte_count_16bit"] += 1
        return True

    def _processing_s(self, device: SimulatedDevice) -> float:
        extra = 0.0
        name = device.profile.timing.min_response_time_point
        if name is not None:
            extra = device.registers[device.profile.point(name).address] / 1000
        return device.processing_s + extra

    def _deliver(
        self, device: SimulatedDevice, answer: bytes, end: float, wait_s: float
    ) -> list[Reply]:
        plan = self.faults.get(device.address, FaultPlan())
        at = (
            end + self._processing_s(device) + (self.line.wire_s(len(answer)) if self.pace else 0.0)
        )
        if wait_s:
            device.last_write_end = at
            device.last_write_wait_s = wait_s
        dice = self._rng.random
        if plan.drop and dice() < plan.drop:
            self.injected["drop"] += 1
            return []
        replies: list[Reply] = []
        if plan.noise and dice() < plan.noise:
            self.injected["noise"] += 1
            noise = bytes(self._rng.randrange(256) for _ in range(self._rng.randint(1, 4)))
            replies.append(
                Reply(
                    at=end + self._processing_s(device) / 2,
                    data=noise,
                    kind="noise",
                    device=device.address,
                )
            )
        if plan.wrong_address and dice() < plan.wrong_address:
            self.injected["wrong_address"] += 1
            other = device.address % 247 + 1
            answer = bytes([other]) + answer[1:-2]
            answer += frames.crc16(answer)
        if plan.crc and dice() < plan.crc:
            self.injected["crc"] += 1
            corrupted = bytearray(answer)
            corrupted[self._rng.randrange(2, len(answer))] ^= 1 << self._rng.randrange(8)
            answer = bytes(corrupted)
        kind = "response"
        if plan.late and dice() < plan.late:
            self.injected["late"] += 1
            at += plan.late_s
            kind = "late"
        else:
            self.answer_until = at
        self.counters["responses"] += 1
        replies.append(Reply(at=at, data=answer, kind=kind, device=device.address))
        return replies

    def on_sent(self, reply: Reply, now: float, *, late: bool = False) -> None:
        """Note when a reply really left, so the next gap is measured from there.

        ``late``: it left later than the device's timing says (the simulator was held up).
        """
        self.last_frame_end = max(self.last_frame_end, now)
        if reply.kind == "response" and not late:
            self.answer_until = now  # the answer is complete on the line
        else:
            self.unsolicited_end = now  # a late answer or noise: no master can foresee it

    def silence(self, address: int, duration_s: float, now: float) -> None:
        """Make a device ignore everything for a while, as during a power cycle."""
        self.devices[address].silent_until = now + duration_s
        self.injected["silent"] += 1

    def stats(self) -> dict[str, Any]:
        """Everything a test wants to know about the run, as JSON-ready data."""
        by_rule = Counter(v.rule for v in self.violations)
        return {
            "line": str(self.line),
            "pace": self.pace,
            "counters": dict(self.counters),
            "exceptions": {str(code): n for code, n in sorted(self.exceptions.items())},
            "faults_injected": dict(self.injected),
            "timing_violations": len(self.violations),
            "violations_by_rule": dict(by_rule),
            "violations": [v.as_dict() for v in self.violations[-1000:]],
            "devices": {
                str(address): {
                    "profile": device.profile.id,
                    "requests": self.requests_by_device[address],
                    "writes": [
                        {
                            "time": round(w.time - self.started, 6),
                            "function": w.function,
                            "address": w.address,
                            "values": list(w.values),
                            "points": list(w.points),
                            "exception": w.exception,
                        }
                        for w in device.write_log
                    ],
                }
                for address, device in sorted(self.devices.items())
            },
        }
