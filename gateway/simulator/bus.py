"""A simulated RS485 line, without I/O: frames in with their arrival time, replies out.

The bus is the strict slave side of the manuals: its :class:`Referee` judges the timing
rules (a request inside the inter-frame gap, inside a device's post-write wait, or while
an answer is still on the line is ignored and counted); the bus dispatches what passes to
the device addressed, answers after the device's processing time, paces frames at the
line's speed when asked to, and lets its :class:`FaultDice` spoil answers on a seeded
schedule. What it keeps (the frame log, violations, the stats) is in
:mod:`gateway.simulator.records`. The transports in :mod:`gateway.simulator.transport` move
the bytes.
"""

from __future__ import annotations

from collections import Counter, deque
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from gateway.errors import FrameError
from gateway.simulator.device import SimulatedDevice, SlaveExceptionError
from gateway.simulator.faults import FaultDice, FaultPlan
from gateway.simulator.records import FrameRecord, Reply, Violation, bus_stats
from gateway.simulator.referee import COLLISION_WINDOW_S, Referee
from gateway.wire import frames

if TYPE_CHECKING:
    from gateway.wire.timing import LineFormat

__all__ = [
    "COLLISION_WINDOW_S",
    "FaultPlan",
    "FrameRecord",
    "Reply",
    "SimulatedBus",
    "Violation",
]


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
    # Until when the line's times rest on a frame that was not judged: its arrival time,
    # so its end and its answer's, may be later than on the wire.
    doubtful_until: float = float("-inf")
    referee: Referee = field(init=False)
    _dice: FaultDice = field(init=False)

    def __post_init__(self) -> None:
        """The referee keeps the bus's violations and counters; seed the fault dice."""
        self.referee = Referee(line=self.line, violations=self.violations, counters=self.counters)
        self._dice = FaultDice(self.seed, injected=self.injected)

    def start(self, now: float) -> None:
        """Bring every device up: nameplate, configuration, first values."""
        self.started = now
        for device in self.devices.values():
            device.start(now, line=self.line)

    # --- frames ------------------------------------------------------------------------

    def on_frame(self, frame: bytes, start: float, *, judged: bool = True) -> list[Reply]:
        """Handle one frame whose first byte arrived at ``start``; replies to put on the line.

        ``judged=False`` answers without refereeing the timing (see the transport's watch).
        """
        self.counters["frames"] += 1
        # A frame that came in while the answer to an unjudged one was still due is not
        # judged either: that frame may have waited in the kernel, so the end and the
        # answer the referee would measure this one against are later than on the wire
        # (the soak saw a master that had rightly given up on an answer blamed for a gap).
        judged = judged and start >= self.doubtful_until
        if not judged:
            self.counters["unjudged"] += 1
        record = FrameRecord.of(frame, start - self.started)
        self.frame_log.append(record)
        replies = self._on_frame(frame, start, record, judged=judged)
        answers = [r for r in replies if r.kind in {"response", "late"}]
        if not judged:
            end = start + self.line.wire_s(len(frame))
            self.doubtful_until = max(self.doubtful_until, end, *(r.at for r in replies))
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
        timing_ok = (self._judge(frame, start) if judged else True) if frame else False
        self.referee.frame_ended(end)
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
        # A slave answers once it has heard the whole request, paced or not: an answer
        # sooner than the request's and its own wire time is one no line can carry, and
        # the master rightly refuses it (it could only be the master's own echo).
        heard = start + self.line.wire_s(len(frame))
        return self._deliver(device, answer, heard, wait_s)

    def _judge(self, frame: bytes, start: float) -> bool:
        device = self.devices.get(frame[0])
        return self.referee.judge(frame, start, device=device, started=self.started)

    def _scheduled_silence(self, address: int, now: float) -> bool:
        plan = self.faults.get(address)
        return plan is not None and plan.silent_at(now - self.started)

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
                quirk = self._dice.string_quirk(self.faults.get(device.address), device, request)
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
        at = end + self._processing_s(device) + self.line.wire_s(len(answer))
        if wait_s:
            device.last_write_end = at
            device.last_write_wait_s = wait_s
        reply = Reply(at=at, data=answer, kind="response", device=device.address)
        replies = self._dice.spoil(plan, reply, noise_at=end + self._processing_s(device) / 2)
        if not replies:
            return []
        if replies[-1].kind == "response":
            self.referee.answering_until(at)
        self.counters["responses"] += 1
        return replies

    def on_sent(self, reply: Reply, now: float, *, late: bool = False) -> None:
        """Note when a reply really left, so the next gap is measured from there.

        ``late``: it left later than the device's timing says (the simulator was held up).
        """
        self.referee.on_sent(reply, now, late=late)

    def silence(self, address: int, duration_s: float, now: float) -> None:
        """Make a device ignore everything for a while, as during a power cycle."""
        self.devices[address].silent_until = now + duration_s
        self.injected["silent"] += 1

    def stats(self) -> dict[str, Any]:
        """Everything a test wants to know about the run, as JSON-ready data."""
        return bus_stats(
            line=self.line,
            pace=self.pace,
            started=self.started,
            counters=self.counters,
            exceptions=self.exceptions,
            injected=self.injected,
            violations=self.violations,
            devices=self.devices,
            requests_by_device=self.requests_by_device,
        )
