"""``calibration_log``: a device's calibration logbook or history, empty entries told apart.

The H10/H20 logbook of 10 entries (manual 6.1.6) or the tecLine / Reiss history of 5
entries with the current calibration (tecLine annex 7.2, Reiss 5.1), both declared in the
profile once with a stride (:func:`~gateway.control.operations.catalogue.log_layout`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Final

from gateway.control.operations.catalogue import (
    CALIBRATION_LOG,
    as_json,
    log_layout,
    require_operation,
)
from gateway.wire.codec import EnumValue

if TYPE_CHECKING:
    from collections.abc import Mapping

    from gateway.control.link import DeviceLink
    from gateway.profiles import Profile
    from gateway.wire import codec

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
