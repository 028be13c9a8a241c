"""``measure``: a single measurement triggered, waited for, and its fresh values read.

H10/H20 manual 6.2.2 (the control word 0x3001: bit 1 "a measurement is in progress", bit
2 "set to trigger a single measurement") and 6.2.10 (the status word 0x3007: bit 15 "new
measured values"). The trigger is written through
:class:`~gateway.control.writes.SafeWriter`, and the link keeps the 250 ms post-write wait.
"""

from __future__ import annotations

import asyncio
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Final

from gateway.control.operations.catalogue import (
    MEASURE,
    MEASURE_TIMEOUT_S,
    MEASURED_POINTS,
    MEASUREMENT_STATUS,
    MEASURING_BIT,
    NEW_VALUES_BIT,
    STATUS,
    TRIGGER_BIT,
    as_json,
    measure_timeout,
    require_operation,
)
from gateway.errors import GatewayError, OperationTimeoutError
from gateway.wire.codec import BitfieldValue, EnumValue

if TYPE_CHECKING:
    from collections.abc import Mapping

    from gateway.control.writes import SafeWriter
    from gateway.profiles import Point, Profile
    from gateway.wire import codec

# How often the status words are read while a measurement runs: each read is one short
# request, so this keeps the line free for polling while answering within a tenth of a second.
MEASURE_POLL_S: Final = 0.1


@dataclass(frozen=True, slots=True, kw_only=True)
class Measurement:
    """A single measurement's fresh values and how it went."""

    device: str
    values: Mapping[str, codec.Decoded]  # oxygen, temperature (a Fault if the sensor says so)
    units: Mapping[str, str | None]
    registers: tuple[int, ...]  # the 0x3001 word written (high word first)
    duration_s: float  # from the trigger's write to the completion seen
    saw_running: bool  # whether bit 1 was seen set (a short measurement may hide it)
    status: tuple[str, ...]  # the bits of 0x3007 set at completion

    def as_dict(self) -> dict[str, object]:
        """The measurement as JSON-ready data."""
        data: dict[str, object] = {}
        for name, value in self.values.items():
            data[name] = as_json(value)
            data[f"{name}_unit"] = self.units.get(name)
        data |= {
            "registers": list(self.registers),
            "duration_s": self.duration_s,
            "saw_running": self.saw_running,
            "status": list(self.status),
        }
        return data


def _bits(value: codec.Decoded) -> BitfieldValue:
    if not isinstance(value, BitfieldValue):
        raise GatewayError(f"expected a bit field, read {value!r}")
    return value


def _bit_number(point: Point, name: str) -> int:
    return next(bit for bit, bit_name in point.format.bits.items() if bit_name == name)


async def measure(
    writer: SafeWriter,
    *,
    timeout_s: float = MEASURE_TIMEOUT_S,
    poll_s: float = MEASURE_POLL_S,
) -> Measurement:
    """Trigger a single measurement, wait for it to finish, return oxygen and temperature.

    H10/H20 manual 6.2.2: 0x3001 bit 2 triggers, bit 1 is set while a measurement runs;
    6.2.10: 0x3007 bit 15 flags new measured values. The word is read, bit 2 set and the
    word written back whole (bit 0 "continuous measurement" is kept as the sensor reports
    it). A measurement already running is let finish first, so its end is not taken for
    ours. Done is bit 1 clear *and* bit 15 set: bit 1 alone may still be clear when the
    sensor has not yet started, bit 15 alone may come from a continuous measurement
    while ours runs. Raises :class:`OperationTimeoutError` after ``timeout_s``.
    """
    link = writer.link
    require_operation(MEASURE, link.profile)
    timeout_s = measure_timeout("timeout", timeout_s)
    profile = link.profile
    control = profile.point(MEASUREMENT_STATUS)
    measuring = _bit_number(control, MEASURING_BIT)
    trigger = _bit_number(control, TRIGGER_BIT)
    new_values = _bit_number(profile.point(STATUS), NEW_VALUES_BIT)
    deadline = time.monotonic() + timeout_s

    word = _bits(await link.read_value(MEASUREMENT_STATUS))
    while word.raw >> measuring & 1:
        if time.monotonic() >= deadline:
            raise OperationTimeoutError(
                f"{link.device}: a measurement was still running after {timeout_s:g} s; "
                "no single measurement was triggered"
            )
        await asyncio.sleep(poll_s)
        word = _bits(await link.read_value(MEASUREMENT_STATUS))

    outcome = await writer.set(control, word.raw | 1 << trigger, explicit=True, read_back=False)
    triggered = time.monotonic()
    saw_running = False
    while True:
        status = await link.read(MEASUREMENT_STATUS, STATUS)
        running = bool(_bits(status[MEASUREMENT_STATUS]).raw >> measuring & 1)
        flags = _bits(status[STATUS])
        saw_running |= running
        if not running and flags.raw >> new_values & 1:
            break
        if time.monotonic() >= deadline:
            raise OperationTimeoutError(
                f"{link.device}: the single measurement did not finish within {timeout_s:g} s "
                f"(measuring: {running}, new values: {bool(flags.raw >> new_values & 1)})"
            )
        await asyncio.sleep(poll_s)
    duration_s = round(time.monotonic() - triggered, 3)

    units = {p: profile.point(p).unit_from for p in MEASURED_POINTS}
    selectors = sorted({u for u in units.values() if u is not None})
    fresh = await link.read(*MEASURED_POINTS, *selectors)
    return Measurement(
        device=link.device,
        values={p: fresh[p] for p in MEASURED_POINTS},
        units={p: _unit(profile, profile.point(p), fresh) for p in MEASURED_POINTS},
        registers=outcome.registers,
        duration_s=duration_s,
        saw_running=saw_running,
        status=flags.active,
    )


def _unit(profile: Profile, point: Point, values: Mapping[str, codec.Decoded]) -> str | None:
    """A point's unit: fixed, or the one its unit-selecting register names now."""
    if point.unit_from is None:
        return point.unit
    selector = values.get(point.unit_from)
    if not isinstance(selector, EnumValue):
        return None
    return profile.point(point.unit_from).enum_units.get(selector.code)
