"""Operations on one sensor: set its clock, take a single measurement, read its calibration log.

Each operation is a plain async function that the command line calls directly
(:func:`set_clock`, :func:`measure`, :func:`calibration_log`) and returns a frozen value
with an ``as_dict()`` of JSON-ready data. :func:`run_operation` runs one by name, as the
MQTT ``{base}/{device}/command/{name}`` handler does, after checking the name, the
device's profile and the arguments; a refusal there raises
:class:`~gateway.errors.CommandRejectedError` before anything reaches the bus.

Which operation applies is decided from the profile's data (the points it declares), not
from vendor names:

- ``set_clock``: a writable date-and-time block: the S10 clock (0x2840-0x2846, S10 manual
  6.9) or the H10/H20 calibration date (0x300A-0x3010, manual 6.2.4), which the sensor
  copies into the logbook entries that follow and which does not run;
- ``measure``: the H10/H20 measurement control word 0x3001 (bit 1 "a measurement is in
  progress", bit 2 "set to trigger a single measurement") and the status word 0x3007
  (bit 15 "new measured values"), manual 6.2.2 and 6.2.10;
- ``calibration_log``: the H10/H20 logbook of 10 entries (manual 6.1.6) or the tecLine /
  Reiss history of 5 entries with the current calibration (tecLine annex 7.2, Reiss 5.1).

Every write goes through :class:`~gateway.control.writes.SafeWriter` as an explicit operator action:
flash-backed points need no allow-list entry but are counted against the daily budget,
and the link keeps every timing rule (the H10/H20 250 ms post-write wait included).
"""

from __future__ import annotations

import asyncio
import math
import time
from dataclasses import dataclass, field
from datetime import UTC, datetime, timedelta
from typing import TYPE_CHECKING, Final

from gateway.errors import CommandRejectedError, GatewayError, OperationTimeoutError
from gateway.line.samples import json_value
from gateway.wire import codec
from gateway.wire.codec import BitfieldValue, DataType, EnumValue

if TYPE_CHECKING:
    from collections.abc import Callable, Mapping

    from gateway.control.link import DeviceLink
    from gateway.control.writes import SafeWriter
    from gateway.profiles import Point, Profile

SET_CLOCK: Final = "set_clock"
MEASURE: Final = "measure"
CALIBRATION_LOG: Final = "calibration_log"
OPERATION_NAMES: Final = (SET_CLOCK, MEASURE, CALIBRATION_LOG)

# H10/H20 manual 6.2.2 (0x3001) and 6.2.10 (0x3007); the bit names are the profile's.
MEASUREMENT_STATUS: Final = "measurement_status"
MEASURING_BIT: Final = "measuring"  # bit 1: "Wenn 1, findet gerade eine Messung statt"
TRIGGER_BIT: Final = (
    "single_measurement_trigger"  # bit 2: "Setzen, um eine Einzelmessung auszulösen"
)
STATUS: Final = "status"
NEW_VALUES_BIT: Final = "new_values"  # 0x3007 bit 15 (0x8000): "Neue Messwerte"
MEASURED_POINTS: Final = ("oxygen", "temperature")

# The manual does not say how long a single measurement takes. Ten seconds is ours; the
# ceiling stays below the MQTT command handler's 60 s (gateway.control.command_router).
MEASURE_TIMEOUT_S: Final = 10.0
MEASURE_TIMEOUT_MAX_S: Final = 50.0
# How often the status words are read while a measurement runs: each read is one short
# request, so this keeps the line free for polling while answering within a tenth of a second.
MEASURE_POLL_S: Final = 0.1


# --- which operation applies: read from the profile's data ------------------------------


@dataclass(frozen=True, slots=True, kw_only=True)
class ClockPoint:
    """A writable date-and-time block that ``set_clock`` sets, and what it means."""

    point: str
    running: bool  # whether the sensor advances it (a clock) or keeps it (a stamp)
    meaning: str


CLOCK_POINTS: Final = (
    ClockPoint(
        point="clock",
        running=True,
        meaning="device date and time for time stamps (S10 manual 6.9)",
    ),
    ClockPoint(
        point="calibration_date",
        running=False,
        meaning=(
            "calibration date copied into the following logbook entries; the sensor "
            "keeps it, it does not run (H10/H20 manual 6.2.4, not written to flash)"
        ),
    ),
)


@dataclass(frozen=True, slots=True, kw_only=True)
class LogLayout:
    """A repeated calibration record in a profile, and how to tell an empty entry."""

    repeat: str  # the profile's repeat name: points are ``{repeat}_{index}_{field}``
    marker: str  # the field that says whether an entry holds data
    current: tuple[str, ...]  # points of the active calibration, shown with the log
    note: str


LOG_LAYOUTS: Final = (
    LogLayout(
        repeat="logbook",
        marker="entry_type",  # 6.1.6 "Eintragstyp": 0 = kein Eintrag
        current=(),
        note=(
            "H10/H20 calibration logbook (manual 6.1.6); the manual does not document the "
            "order of the entries"
        ),
    ),
    LogLayout(
        repeat="history",
        marker="stamp",  # DateTime 0 is the documented initial value: never calibrated
        current=("x_zero", "x_span", "calibration_stamp"),
        note=(
            "calibration history: entry 0 is the current calibration, 4 the oldest "
            "(tecLine annex 7.2, Reiss 5.1)"
        ),
    ),
)


def clock_point(profile: Profile) -> ClockPoint | None:
    """The date-and-time block ``set_clock`` writes on this profile, if it has one."""
    for candidate in CLOCK_POINTS:
        if profile.has_point(candidate.point):
            point = profile.point(candidate.point)
            if point.writable and point.dtype is DataType.DATETIME:
                return candidate
    return None


def log_layout(profile: Profile) -> LogLayout | None:
    """The calibration log this profile declares (logbook or history), if any."""
    repeats = {p.repeat for p in profile.points if p.repeat is not None}
    for layout in LOG_LAYOUTS:
        if layout.repeat in repeats and all(profile.has_point(p) for p in layout.current):
            return layout
    return None


def _has_bits(profile: Profile, point: str, *bits: str) -> bool:
    if not profile.has_point(point):
        return False
    return set(bits) <= set(profile.point(point).format.bits.values())


def _measure_applies(profile: Profile) -> bool:
    return (
        _has_bits(profile, MEASUREMENT_STATUS, MEASURING_BIT, TRIGGER_BIT)
        and profile.point(MEASUREMENT_STATUS).writable
        and _has_bits(profile, STATUS, NEW_VALUES_BIT)
        and all(profile.has_point(p) for p in MEASURED_POINTS)
    )


_APPLIES: Final[Mapping[str, Callable[[Profile], bool]]] = {
    SET_CLOCK: lambda profile: clock_point(profile) is not None,
    MEASURE: _measure_applies,
    CALIBRATION_LOG: lambda profile: log_layout(profile) is not None,
}


def operations_for(profile: Profile) -> list[str]:
    """The operations that apply to a profile, in :data:`OPERATION_NAMES` order."""
    return [name for name in OPERATION_NAMES if _APPLIES[name](profile)]


def require_operation(name: str, profile: Profile) -> None:
    """Refuse an unknown operation, or one the profile does not support (naming those it does)."""
    if name not in _APPLIES:
        raise CommandRejectedError(
            f"unknown operation {name!r}; operations: {', '.join(OPERATION_NAMES)}"
        )
    if _APPLIES[name](profile):
        return
    supported = operations_for(profile)
    which = ", ".join(supported) if supported else "none"
    raise CommandRejectedError(
        f"operation {name!r} does not apply to profile {profile.id} "
        f"(operations for this device: {which})"
    )


# --- arguments --------------------------------------------------------------------------


def _flag(name: str, value: object) -> bool:
    if not isinstance(value, bool):
        raise CommandRejectedError(f"argument {name!r} must be true or false, got {value!r}")
    return value


def _timeout(name: str, value: object) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise CommandRejectedError(f"argument {name!r} must be a number of seconds, got {value!r}")
    seconds = float(value)
    if not 0 < seconds <= MEASURE_TIMEOUT_MAX_S:
        raise CommandRejectedError(
            f"argument {name!r} must be more than 0 and at most {MEASURE_TIMEOUT_MAX_S:g} "
            f"seconds, got {value!r}"
        )
    return seconds


_ARGUMENTS: Final[Mapping[str, Mapping[str, Callable[[str, object], object]]]] = {
    SET_CLOCK: {"local": _flag},
    MEASURE: {"timeout": _timeout},
    CALIBRATION_LOG: {},
}


def parse_arguments(name: str, arguments: Mapping[str, object]) -> dict[str, object]:
    """An operation's arguments checked and typed, or a :class:`CommandRejectedError`.

    ``set_clock`` takes ``{"local": true}`` (write the gateway host's local time instead
    of UTC), ``measure`` takes ``{"timeout": seconds}``, ``calibration_log`` nothing.
    """
    if name not in _ARGUMENTS:
        raise CommandRejectedError(
            f"unknown operation {name!r}; operations: {', '.join(OPERATION_NAMES)}"
        )
    accepted = _ARGUMENTS[name]
    unknown = sorted(set(arguments) - set(accepted))
    if unknown:
        takes = f"it takes {', '.join(sorted(accepted))}" if accepted else "it takes none"
        raise CommandRejectedError(
            f"unknown argument {', '.join(map(repr, unknown))} for {name}; {takes}"
        )
    return {key: accepted[key](key, value) for key, value in arguments.items()}


async def run_operation(
    name: str, writer: SafeWriter, arguments: Mapping[str, object], *, now: datetime
) -> dict[str, object]:
    """Run one operation by name on ``writer``'s device; its result as JSON-ready data.

    ``now`` is the gateway's clock (time-zone aware), used by ``set_clock``. An unknown
    name, an operation the device's profile does not support, or bad arguments raise
    :class:`CommandRejectedError` before anything is sent.
    """
    require_operation(name, writer.link.profile)
    parsed = parse_arguments(name, arguments)
    result: ClockSetting | Measurement | CalibrationLog
    if name == SET_CLOCK:
        result = await set_clock(writer, now=now, local=parsed.get("local") is True)
    elif name == MEASURE:
        timeout = parsed.get("timeout", MEASURE_TIMEOUT_S)
        assert isinstance(timeout, float)  # noqa: S101 - _timeout returns a float
        result = await measure(writer, timeout_s=timeout)
    else:
        result = await calibration_log(writer.link)
    return {"operation": name, "device": writer.device, **result.as_dict()}


def as_json(value: codec.Decoded) -> object:
    """A decoded value as JSON-ready data; a sensor fault as ``{"fault": name}``."""
    if isinstance(value, codec.Fault):
        return {"fault": value.name}
    return json_value(value)


# --- set_clock --------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class _GatewayClock:
    """The caller's wall clock, advanced by the monotonic clock (immune to clock steps)."""

    start: datetime
    start_monotonic: float = field(default_factory=time.monotonic)

    def now(self) -> datetime:
        return self.start + timedelta(seconds=time.monotonic() - self.start_monotonic)


@dataclass(frozen=True, slots=True, kw_only=True)
class ClockSetting:
    """What ``set_clock`` found, wrote and read back.

    Offsets are sensor minus gateway in seconds (the sensor's resolution is one second),
    ``None`` where the sensor held no date. A non-running point (the H10/H20 calibration
    date) keeps the written time, so its offset grows from then on.
    """

    device: str
    point: str
    running: bool
    meaning: str
    before: datetime | None
    gateway_before: datetime
    written: datetime
    registers: tuple[int, ...]
    after: datetime | None
    gateway_after: datetime
    note: str = ""

    @property
    def offset_before_s(self) -> float | None:
        """How far the sensor was from the gateway before the write."""
        return _offset(self.before, self.gateway_before)

    @property
    def offset_after_s(self) -> float | None:
        """How far the sensor is from the gateway after the write (read back)."""
        return _offset(self.after, self.gateway_after)

    def as_dict(self) -> dict[str, object]:
        """The setting as JSON-ready data."""
        data: dict[str, object] = {
            "point": self.point,
            "running": self.running,
            "meaning": self.meaning,
            "before": json_value(self.before),
            "gateway_before": self.gateway_before.isoformat(),
            "offset_before_s": self.offset_before_s,
            "written": self.written.isoformat(),
            "registers": list(self.registers),
            "after": json_value(self.after),
            "gateway_after": self.gateway_after.isoformat(),
            "offset_after_s": self.offset_after_s,
        }
        if self.note:
            data["note"] = self.note
        return data


def _offset(sensor: datetime | None, gateway: datetime) -> float | None:
    if sensor is None:
        return None
    return round((sensor - gateway).total_seconds(), 3)


def _as_datetime(value: codec.Decoded) -> datetime | None:
    return value if isinstance(value, datetime) else None


async def set_clock(writer: SafeWriter, *, now: datetime, local: bool = False) -> ClockSetting:
    """Set the sensor's date and time from the gateway's clock ``now``; read before and after.

    The time written is UTC (offset 0), or with ``local`` the gateway host's local time
    and offset. The write waits for the gateway clock's next whole second, so the
    sensor, which keeps whole seconds, starts within the frame's travel time of it.
    """
    link = writer.link
    require_operation(SET_CLOCK, link.profile)
    target = clock_point(link.profile)
    assert target is not None  # noqa: S101 - require_operation checked it
    if now.tzinfo is None or now.utcoffset() is None:
        raise CommandRejectedError("the gateway's clock must carry a time zone")
    gateway = _GatewayClock(now)
    before = _as_datetime(await link.read_value(target.point))
    gateway_before = gateway.now()
    second = gateway.now().replace(microsecond=0) + timedelta(seconds=1)
    await asyncio.sleep(max(0.0, (second - gateway.now()).total_seconds()))
    written = second.astimezone() if local else second.astimezone(UTC)
    outcome = await writer.set(writer.point(target.point), written, explicit=True)
    return ClockSetting(
        device=link.device,
        point=target.point,
        running=target.running,
        meaning=target.meaning,
        before=before,
        gateway_before=gateway_before,
        written=written,
        registers=outcome.registers,
        after=_as_datetime(outcome.value),
        gateway_after=gateway.now(),
        note=outcome.note,
    )


# --- measure ----------------------------------------------------------------------------


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
    timeout_s = _timeout("timeout", timeout_s)
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


# --- calibration_log --------------------------------------------------------------------

UNIT_TEXT_SUFFIX: Final = "_unit"  # H10/H20 logbook: string[6][8] unit texts per value


@dataclass(frozen=True, slots=True, kw_only=True)
class LogEntry:
    """One entry of a calibration log; an empty one has no values at all."""

    index: int
    empty: bool
    values: Mapping[str, codec.Decoded] = field(default_factory=dict)

    def as_dict(self) -> dict[str, object]:
        """The entry as JSON-ready data: its index, ``empty``, and its fields if any."""
        data: dict[str, object] = {"index": self.index, "empty": self.empty}
        data |= {name: as_json(value) for name, value in self.values.items()}
        return data


@dataclass(frozen=True, slots=True, kw_only=True)
class CalibrationLog:
    """A device's calibration logbook or history, entries in the device's own order."""

    device: str
    profile: str
    kind: str  # the profile's repeat name: "logbook" or "history"
    note: str
    fields: tuple[str, ...]  # each entry's fields, in register order
    units: Mapping[str, str]  # fixed units of fields and current points that have one
    current: Mapping[str, codec.Decoded]
    entries: tuple[LogEntry, ...]

    def unit_of(self, entry: LogEntry, name: str) -> str:
        """A field's unit in an entry: the entry's own unit text if it has one, else fixed."""
        text = entry.values.get(f"{name}{UNIT_TEXT_SUFFIX}")
        if isinstance(text, str) and text:
            return text
        return self.units.get(name, "")

    @property
    def value_fields(self) -> tuple[str, ...]:
        """The fields that are values, not another field's unit text."""
        return tuple(f for f in self.fields if not _is_unit_text(f, self.fields))

    def as_dict(self) -> dict[str, object]:
        """The log as JSON-ready data."""
        data: dict[str, object] = {
            "profile": self.profile,
            "kind": self.kind,
            "note": self.note,
            "units": dict(self.units),
        }
        if self.current:
            data["current"] = {name: as_json(value) for name, value in self.current.items()}
        data["entries"] = [entry.as_dict() for entry in self.entries]
        return data


def _is_unit_text(name: str, fields: tuple[str, ...]) -> bool:
    return name.endswith(UNIT_TEXT_SUFFIX) and name.removesuffix(UNIT_TEXT_SUFFIX) in fields


def _is_empty(marker: codec.Decoded) -> bool:
    """Whether an entry's marker says it holds no calibration.

    A stamp of 0 decodes as ``None`` (never calibrated); an entry type 0 is "kein
    Eintrag". An entry type the manual does not document (erased flash reads 0xFFFF) is
    no entry either: its other registers would be shown as garbage.
    """
    if marker is None:
        return True
    if isinstance(marker, EnumValue):
        return marker.code == 0 or not marker.known
    return False


def _entries(profile: Profile, repeat: str) -> dict[int, dict[str, str]]:
    """Each entry's fields, ``{index: {field: point name}}``, in index and address order."""
    entries: dict[int, dict[str, str]] = {}
    for point in sorted(profile.points, key=lambda p: p.address):
        if point.repeat == repeat and point.index is not None:
            prefix = f"{repeat}_{point.index}_"
            entries.setdefault(point.index, {})[point.name.removeprefix(prefix)] = point.name
    return dict(sorted(entries.items()))


async def calibration_log(link: DeviceLink) -> CalibrationLog:
    """Read the calibration logbook or history; empty entries come back without values.

    The entries' markers (entry type, date stamp) are read first, then the fields of the
    entries that hold data, together with the current calibration: registers of empty
    entries are never decoded, so their leftovers cannot show up as values.
    """
    profile = link.profile
    require_operation(CALIBRATION_LOG, profile)
    layout = log_layout(profile)
    assert layout is not None  # noqa: S101 - require_operation checked it
    entries = _entries(profile, layout.repeat)
    markers = await link.read(*(fields[layout.marker] for fields in entries.values()))
    filled = [i for i, fields in entries.items() if not _is_empty(markers[fields[layout.marker]])]
    wanted = [name for i in filled for name in entries[i].values() if name not in markers]
    values = await link.read(*layout.current, *wanted) if layout.current or wanted else {}
    values |= markers
    first = next(iter(entries.values()))
    fields = tuple(first)
    units = {
        name: unit
        for name, point_name in (*first.items(), *((c, c) for c in layout.current))
        if (unit := profile.point(point_name).unit)
    }
    return CalibrationLog(
        device=link.device,
        profile=profile.id,
        kind=layout.repeat,
        note=layout.note,
        fields=fields,
        units=units,
        current={name: values[name] for name in layout.current},
        entries=tuple(
            LogEntry(
                index=index,
                empty=index not in filled,
                values=(
                    {}
                    if index not in filled
                    else {name: values[point] for name, point in entries[index].items()}
                ),
            )
            for index in entries
        ),
    )
