"""Faults injected into a simulated device's answers: the plan, and the seeded dice for it."""

from __future__ import annotations

import random
from collections import Counter
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from gateway.simulator.records import Reply
from gateway.wire import frames
from gateway.wire.codec import DataType

if TYPE_CHECKING:
    from gateway.simulator.device import SimulatedDevice


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

    def silent_at(self, elapsed: float) -> bool:
        """Whether a scheduled silence covers ``elapsed`` seconds since the bus started."""
        return any(begin <= elapsed < begin + length for begin, length in self.silences)


@dataclass(slots=True)
class FaultDice:
    """The seeded dice that decide which answers a plan spoils; ``injected`` counts each fault."""

    seed: int
    injected: Counter[str] = field(default_factory=Counter)
    _rng: random.Random = field(init=False)

    def __post_init__(self) -> None:
        """Seed the dice."""
        self._rng = random.Random(self.seed)

    def string_quirk(
        self, plan: FaultPlan | None, device: SimulatedDevice, request: frames.Request
    ) -> bool:
        """Whether a read of a string answers with the two-byte byte count of the manuals."""
        if plan is None or not plan.string_byte_count_16bit:
            return False
        first = next((p for p in device.profile.points if p.address == request.address), None)
        if first is None or first.dtype is not DataType.STRING:
            return False
        self.injected["string_byte_count_16bit"] += 1
        return True

    def spoil(self, plan: FaultPlan, answer: Reply, *, noise_at: float) -> list[Reply]:
        """What goes on the line for ``answer`` under ``plan``, the answer last.

        Nothing (dropped), noise first, the answer to another address, corrupted, or late
        (its kind ``"late"``): each on the plan's odds, the dice rolled in that order.
        """
        dice = self._rng.random
        if plan.drop and dice() < plan.drop:
            self.injected["drop"] += 1
            return []
        replies: list[Reply] = []
        if plan.noise and dice() < plan.noise:
            self.injected["noise"] += 1
            noise = bytes(self._rng.randrange(256) for _ in range(self._rng.randint(1, 4)))
            replies.append(Reply(at=noise_at, data=noise, kind="noise", device=answer.device))
        data, at, kind = answer.data, answer.at, answer.kind
        if plan.wrong_address and dice() < plan.wrong_address:
            self.injected["wrong_address"] += 1
            other = answer.device % 247 + 1
            data = bytes([other]) + data[1:-2]
            data += frames.crc16(data)
        if plan.crc and dice() < plan.crc:
            self.injected["crc"] += 1
            corrupted = bytearray(data)
            corrupted[self._rng.randrange(2, len(data))] ^= 1 << self._rng.randrange(8)
            data = bytes(corrupted)
        if plan.late and dice() < plan.late:
            self.injected["late"] += 1
            at += plan.late_s
            kind = "late"
        replies.append(Reply(at=at, data=data, kind=kind, device=answer.device))
        return replies
