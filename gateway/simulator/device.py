"""One simulated sensor: its register image, the manual's access rules and its behaviour.

The pieces read alone: the image and its holds (:mod:`gateway.simulator.registers`), the
access rules (:mod:`gateway.simulator.access`), the line the interface registers report
(:mod:`gateway.simulator.line_settings`). Here they meet: a read or write as the sensor
serves it, logged, and the family :class:`Behaviour` that moves values and reacts.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Protocol

from gateway.simulator.access import (
    ILLEGAL_VALUE,
    SlaveExceptionError,
    read_registers,
    write_targets,
    written_value_problem,
)
from gateway.simulator.line_settings import report_line
from gateway.simulator.registers import RegisterImage
from gateway.wire import codec, frames
from gateway.wire.codec import DataType

if TYPE_CHECKING:
    from collections.abc import Sequence

    from gateway.profiles import Point
    from gateway.wire.timing import LineFormat

__all__ = [
    "Behaviour",
    "SimulatedDevice",
    "SlaveExceptionError",
    "WriteRecord",
]


@dataclass(frozen=True, slots=True)
class WriteRecord:
    """One write the simulated sensor accepted (or, with a reason, refused)."""

    time: float
    device: int
    function: int
    address: int
    values: tuple[int, ...]
    points: tuple[str, ...]
    exception: int | None = None


class Behaviour(Protocol):
    """The family-specific part of a simulated sensor (:mod:`gateway.simulator.behaviour`)."""

    def start(self, device: SimulatedDevice, now: float) -> None:
        """Fill nameplate, configuration and first values."""

    def tick(self, device: SimulatedDevice, now: float) -> None:
        """Move values up to ``now``."""

    def filter_write(self, device: SimulatedDevice, points: list[Point]) -> list[Point]:
        """The points of an accepted write that the sensor really stores."""

    def on_write(self, device: SimulatedDevice, points: list[Point], now: float) -> None:
        """React to stored points (triggers, calibration)."""


@dataclass(slots=True, kw_only=True)
class SimulatedDevice(RegisterImage):
    """A sensor on the simulated bus, driven by its profile plus a family behaviour.

    Values by point name, holds and faults come with the :class:`RegisterImage`.
    """

    address: int
    behaviour: Behaviour
    processing_s: float = 0.005  # t1, S10 manual 5.1: typically 5 ms
    animate: bool = True
    initial: dict[str, object] = field(default_factory=dict)  # held from start (config)
    write_log: list[WriteRecord] = field(default_factory=list)
    unmapped: set[int] = field(default_factory=set)  # registers this unit does not implement
    raw: dict[int, int] = field(default_factory=dict)  # words held from start, maybe unmapped
    silent_until: float = 0.0
    last_write_end: float = float("-inf")
    last_write_wait_s: float = 0.0

    def start(self, now: float, *, line: LineFormat | None = None) -> None:
        """Power up: the behaviour's nameplate and values, the line, then the configured values.

        A sensor answers only on the line its interface registers are set to, so they say
        ``line`` (the simulated line, or the format given for RTU over TCP); a configured
        value still wins, to simulate a sensor that reports something else.
        """
        self.behaviour.start(self, now)
        if line is not None:
            report_line(self, self.address, line)
        for name, value in self.initial.items():
            self.hold(name, value)
        self.hold_registers(self.raw)

    def tick(self, now: float) -> None:
        """Let the behaviour move values up to ``now`` (called before every request)."""
        self.behaviour.tick(self, now)

    # --- Modbus access -------------------------------------------------------------------

    def read(self, address: int, count: int) -> tuple[int, ...]:
        """Registers as the sensor sends them, or a :class:`SlaveExceptionError`."""
        return read_registers(self, address, count, raw=self.raw, unmapped=self.unmapped)

    def write(
        self, address: int, values: Sequence[int], *, function: int, now: float
    ) -> list[Point]:
        """Apply a write as the sensor would: checked whole, then applied, then acted on."""
        max_write = self.profile.limits.max_write
        if not 1 <= len(values) <= max_write:
            raise SlaveExceptionError(frames.ILLEGAL_ADDRESS, f"write of {len(values)} registers")
        try:
            targets = write_targets(self, address, len(values))
        except SlaveExceptionError as exc:
            self._log(now, function=function, address=address, values=values, exception=exc.code)
            raise
        order = self.float_order
        staged: list[tuple[Point, tuple[int, ...]]] = []
        offset = 0
        for point, length in targets:
            chunk = tuple(values[offset : offset + length])
            offset += length
            if point.dtype is DataType.FLOAT32:
                chunk = codec.reorder_float(chunk, order, self.profile.float_order)
            problem = written_value_problem(self, point, chunk)
            if problem is not None:
                self._log(
                    now,
                    function=function,
                    address=address,
                    values=values,
                    points=(point.name,),
                    exception=ILLEGAL_VALUE,
                )
                raise SlaveExceptionError(ILLEGAL_VALUE, f"{point.name}: {problem}")
            staged.append((point, chunk))
        accepted = self.behaviour.filter_write(self, [p for p, _ in staged])
        for point, chunk in staged:
            if point in accepted:
                self._write_registers(point.address, chunk)
                self.held.pop(point.name, None)
        self._log(
            now,
            function=function,
            address=address,
            values=values,
            points=tuple(p.name for p in accepted),
        )
        self.behaviour.on_write(self, accepted, now)
        return accepted

    def _log(
        self,
        now: float,
        /,
        *,
        function: int,
        address: int,
        values: Sequence[int],
        points: tuple[str, ...] = (),
        exception: int | None = None,
    ) -> None:
        self.write_log.append(
            WriteRecord(
                time=now,
                device=self.address,
                function=function,
                address=address,
                values=tuple(values),
                points=points,
                exception=exception,
            )
        )
