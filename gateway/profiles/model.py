"""The register map of one sensor variant, as immutable values built by the loader."""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import StrEnum
from typing import TYPE_CHECKING, Any

from gateway.errors import ConfigError
from gateway.wire.codec import BITFIELD_TYPES, ENUM_TYPES, DataType, Format, WordOrder

if TYPE_CHECKING:
    from collections.abc import Mapping


class Access(StrEnum):
    """Whether the gateway may write a point."""

    READ = "r"
    READ_WRITE = "rw"


class Storage(StrEnum):
    """Where a writable register lives, which decides how often it may be written."""

    FLASH = "flash"  # EEPROM/flash: ~10,000-100,000 cycles, never written cyclically
    RAM = "ram"  # S10 RAM compensation block: meant for cyclic writes
    VOLATILE = "volatile"  # H10/H20 "not written to flash"


class PollGroup(StrEnum):
    """How often a point is worth reading."""

    PROCESS = "process"  # measured values, at the device's poll interval
    STATUS = "status"  # status and error words, at the device's poll interval
    DIAGNOSTICS = "diagnostics"  # counters, logbooks: slowly
    IDENTITY = "identity"  # nameplate: once at start and after reconnection
    CONFIGURATION = "configuration"  # settings: slowly, and after writes


@dataclass(frozen=True, slots=True, kw_only=True)
class Point:
    """One value in a register map: where it is, how to decode it, how it may be written."""

    name: str
    address: int
    format: Format
    access: Access
    unit: str | None  # None when the unit comes from another register (unit_from)
    unit_from: str | None
    enum_units: Mapping[int, str]  # for unit-selecting enums: code -> unit text
    storage: Storage | None
    post_write_wait_s: float
    group: PollGroup
    description: str
    view: bool = False
    repeat: str | None = None
    index: int | None = None

    @property
    def dtype(self) -> DataType:
        """The point's data type."""
        return self.format.dtype

    @property
    def count(self) -> int:
        """Registers the point occupies."""
        return self.format.count

    @property
    def last(self) -> int:
        """Address of the point's last register."""
        return self.address + self.format.count - 1

    @property
    def writable(self) -> bool:
        """Whether the gateway may write the point at all."""
        return self.access is Access.READ_WRITE

    def as_dict(self) -> dict[str, Any]:
        """The point as plain data, the contract of ``gateway profiles show --json``."""
        fmt = self.format
        data: dict[str, Any] = {
            "name": self.name,
            "address": self.address,
            "address_hex": f"0x{self.address:04X}",
            "type": fmt.dtype.value,
            "count": fmt.count,
            "access": self.access.value,
            "unit": self.unit,
            "unit_from": self.unit_from,
            "group": self.group.value,
            "description": self.description,
            "storage": self.storage.value if self.storage else None,
            "post_write_wait_s": self.post_write_wait_s,
        }
        if fmt.dtype in ENUM_TYPES:
            data["enum"] = {str(code): label for code, label in fmt.enum.items()}
            if self.enum_units:
                data["enum_units"] = {str(code): unit for code, unit in self.enum_units.items()}
        if fmt.dtype in BITFIELD_TYPES:
            data["bits"] = {str(bit): name for bit, name in fmt.bits.items()}
        if fmt.minimum is not None or fmt.maximum is not None:
            data["range"] = [fmt.minimum, fmt.maximum]
        if fmt.dtype is DataType.STRING:
            data["encoding"] = fmt.encoding
        if self.view:
            data["view"] = True
        if self.repeat is not None:
            data["repeat"] = self.repeat
            data["index"] = self.index
        return data


@dataclass(frozen=True, slots=True, kw_only=True)
class WaitRule:
    """A longer post-write wait after writes touching ``first``..``last``."""

    first: int
    last: int
    wait_s: float


@dataclass(frozen=True, slots=True, kw_only=True)
class Timing:
    """A family's timing rules, each named after its manual section in the data file."""

    min_gap_s: float = 0.0  # minimum inter-frame gap on top of 3.5 character times
    processing_time_s: float = 0.1  # t1 upper bound before the device answers
    min_response_time_point: str | None = None  # register adding to t1 (digiLine 0x0305)
    post_write_wait_s: float = 0.0  # wait after every write before the next request
    post_write_waits: tuple[WaitRule, ...] = ()

    def wait_after_write(self, address: int, count: int) -> float:
        """Wait after writing ``count`` registers from ``address`` before the next request."""
        last = address + count - 1
        wait = self.post_write_wait_s
        for rule in self.post_write_waits:
            if address <= rule.last and rule.first <= last:
                wait = max(wait, rule.wait_s)
        return wait


@dataclass(frozen=True, slots=True, kw_only=True)
class SerialSettings:
    """Factory serial settings where a manual documents them."""

    address: int | None = None
    baudrate: int | None = None
    parity: str | None = None
    stopbits: int | None = None


@dataclass(frozen=True, slots=True, kw_only=True)
class Limits:
    """Registers per request the family accepts."""

    max_read: int = 125
    max_write: int = 123


@dataclass(frozen=True, slots=True, kw_only=True)
class Quirks:
    """Documented deviations from standard Modbus that the gateway tolerates."""

    string_byte_count_16bit: bool = False


@dataclass(frozen=True, slots=True, kw_only=True)
class Slope:
    """An amperometric cell's slope as its manual relates it to the nominal one.

    ``limit``: the fraction of the nominal slope below which the sensor needs maintenance
    (tecLine annex 7.3.4: 30 %). ``ppm_per_unit``: ppm in one unit of each label of the
    concentration unit (0x0200), since X_Span is in nA per that unit and the nominal slope
    (0x030A) in nA/ppm (annex 7.1, 7.5.1).
    """

    limit: float
    ppm_per_unit: Mapping[str, float]

    def nominal_in(self, nominal_na_per_ppm: float, unit: str) -> float | None:
        """The nominal slope in nA per ``unit`` (a label of 0x0200); None: no known relation."""
        per_unit = self.ppm_per_unit.get(unit)
        return None if per_unit is None else nominal_na_per_ppm * per_unit


@dataclass(frozen=True, slots=True, kw_only=True)
class FloatOrderRegister:
    """A register that selects the float word order (digiLine 0x0307)."""

    point: str
    orders: Mapping[int, WordOrder]


@dataclass(frozen=True, slots=True)
class Ring:
    """A record kept as numbered entries of the same fields: a calibration history, a logbook.

    The sensor overwrites the oldest; declared once, in the profile's ``repeats``.
    ``numbers`` as the sensor numbers its entries, the newest first (the tecLine's history
    0 to 4, annex 7.2; the H10/H20's logbook 1 to 10, 6.1.6); ``fields`` each entry's.
    """

    name: str
    numbers: tuple[int, ...]
    fields: tuple[str, ...]

    def point(self, number: int, field: str) -> str:
        """The name of one entry's field (``history_0_x_zero``)."""
        return f"{self.name}_{number}_{field}"

    def points(self, *fields: str) -> tuple[str, ...]:
        """Every entry's points of ``fields`` (all its fields when none), entry by entry."""
        wanted = fields or self.fields
        return tuple(self.point(number, field) for number in self.numbers for field in wanted)


def _rings(points: tuple[Point, ...]) -> dict[str, Ring]:
    """The rings of a map, from its points that ``repeats`` expanded (name and index kept)."""
    numbers: dict[str, list[int]] = {}
    fields: dict[str, list[str]] = {}
    for point in points:
        if point.repeat is None or point.index is None:
            continue
        if point.index not in numbers.setdefault(point.repeat, []):
            numbers[point.repeat].append(point.index)
        field = point.name.removeprefix(f"{point.repeat}_{point.index}_")
        if field not in fields.setdefault(point.repeat, []):
            fields[point.repeat].append(field)
    return {
        name: Ring(name=name, numbers=tuple(sorted(found)), fields=tuple(fields[name]))
        for name, found in numbers.items()
    }


@dataclass(frozen=True, slots=True, kw_only=True)
class Profile:
    """A complete, validated register map of one sensor variant.

    ``care`` names the records the family keeps, so the rules sensor care judges it by
    (``amperometric``, ``optical_hygienic``, ``optical``; None: none care knows);
    ``slope`` an amperometric cell's slope facts, which care and the calibrations use.
    """

    id: str
    family: str
    title: str
    spec: str
    source: str
    points: tuple[Point, ...]
    readable: tuple[tuple[int, int], ...]
    float_order: WordOrder
    float_order_register: FloatOrderRegister | None
    float_faults: bool
    limits: Limits
    timing: Timing
    quirks: Quirks
    exceptions: Mapping[int, str]
    serial: SerialSettings | None
    identify: Mapping[str, int]
    unit_availability: Mapping[str, tuple[str, ...]]
    care: str | None = None
    slope: Slope | None = None
    _by_name: dict[str, Point] = field(init=False, repr=False, compare=False)
    _rings: dict[str, Ring] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        """Index points by name, and the rings they make, once."""
        object.__setattr__(self, "_by_name", {p.name: p for p in self.points})
        object.__setattr__(self, "_rings", _rings(self.points))

    def ring(self, name: str) -> Ring | None:
        """The ring of that name (``history``, ``logbook``), if the sensor keeps one."""
        return self._rings.get(name)

    def has_point(self, name: str) -> bool:
        """Whether the map defines a point of that name."""
        return name in self._by_name

    def owns(self, point: Point) -> bool:
        """Whether ``point`` is this map's own, not one of another map with the same name.

        A check of a :class:`Point` already resolved, for code handed one (the planner);
        resolving a name is :meth:`point`.
        """
        return self._by_name.get(point.name) == point

    def point(self, name: str) -> Point:
        """The point of that name, or a :class:`ConfigError` listing close names."""
        try:
            return self._by_name[name]
        except KeyError:
            close = [n for n in self._by_name if name in n or n in name][:5]
            hint = f"; did you mean {', '.join(close)}?" if close else ""
            raise ConfigError(
                f"profile {self.id} has no point {name!r}{hint}", key="points"
            ) from None

    def points_in(self, *groups: PollGroup) -> tuple[Point, ...]:
        """Points of the given poll groups, in address order."""
        return tuple(p for p in self.points if p.group in groups)

    def exception_meaning(self, code: int) -> str:
        """The family's meaning of a Modbus exception code."""
        return self.exceptions.get(code, f"exception_{code}")

    def post_write_wait(self, address: int, count: int) -> float:
        """Wait after writing ``count`` registers from ``address`` before the next request."""
        return self.timing.wait_after_write(address, count)

    def readable_run(self, address: int) -> tuple[int, int] | None:
        """The readable run containing ``address``, if any; gaps outside runs are unread."""
        for first, last in self.readable:
            if first <= address <= last:
                return first, last
        return None
