"""The history the sensors forget: each entry of their rings copied into the records, once.

A tecLine/Reiss keeps its last 5 calibrations (annex 7.2 / Reiss 5.1), an H10/H20 its
last 10 logbook entries (6.1.6); the next one overwrites the oldest. Sensor care reads
those rings with every diagnostics poll (:func:`gateway.care.records.ring_entries`); the
:class:`HistoryKeeper` appends one ``history`` record for each entry it has not copied
before, so that the records hold every calibration of a sensor's life, and gives the whole
copy back to care, which fits its trends over it (:class:`gateway.care.records.PastEntries`).

"Copied before" is decided by the entry itself, never by its place in the ring (which
moves with every calibration): each record carries an ``entry_key`` of the sensor (its
serial number, or the device's name where the profile reads none) and the entry's own
content (its date stamp and its values). The keys are read back from the store when the
keeper starts, so an entry seen again after a restart, or in another place after the ring
turned, is recognised and not copied twice. A sensor moved to another address or renamed
in the config keeps its history: it is the serial number's.

No I/O of its own: the store's appends and its one read at start.
"""

from __future__ import annotations

import contextlib
import logging
import math
from datetime import datetime
from typing import TYPE_CHECKING, Final

from gateway.care.records import Calibration, LogbookEntry
from gateway.care.rules import HISTORY, LOGBOOK
from gateway.errors import RecordError
from gateway.profiles.serial_number import SERIAL_NUMBER_POINT
from gateway.records.actor import Actor, Via
from gateway.records.model import DeviceRef, Entry, Kind, Record, Result
from gateway.records.store import Query

if TYPE_CHECKING:
    from collections.abc import Callable, Iterable, Mapping, Sequence

    from gateway.care.records import PastEntries, SensorEntry
    from gateway.records.store import RecordStore
    from gateway.shared.state import GatewayState

_LOGGER = logging.getLogger(__name__)

HISTORY_ACTOR: Final = Actor(
    user="gateway", via=Via.GATEWAY, detail="copied from the sensor's own history"
)
# A record's data["ring"]: which ring the entry was read from.
HISTORY_RING: Final = HISTORY  # the ring's name, as the profile and care call it
LOGBOOK_RING: Final = LOGBOOK
_ACTIONS: Final = {
    HISTORY_RING: "calibration history entry copied",
    LOGBOOK_RING: "calibration logbook entry copied",
}


def sensor_key(device: DeviceRef) -> str:
    """Whose history: the sensor's serial number, or the device's name without one."""
    return f"serial:{device.serial}" if device.serial else f"device:{device.name}"


def entry_key(device: DeviceRef, entry: SensorEntry) -> str:
    """The entry's identity: the sensor and the entry's own content, not its place.

    Values as Python writes a float back exactly (``repr``): what the sensor sent as a
    float32 reads back the same on every poll, and from the record's JSON.
    """
    if isinstance(entry, Calibration):
        content = f"{HISTORY_RING}|{entry.stamp.isoformat()}|{entry.x_zero!r}|{entry.x_span!r}"
    else:
        date = "-" if entry.date is None else entry.date.isoformat()
        content = (
            f"{LOGBOOK_RING}|{entry.kind}|{date}|{entry.operating_s!r}|{entry.cap_counter!r}"
            f"|{entry.phase!r}|{entry.rating}|{entry.manual}"
        )
    return f"{sensor_key(device)}|{content}"


def _ring(entry: SensorEntry) -> str:
    return HISTORY_RING if isinstance(entry, Calibration) else LOGBOOK_RING


def _finite(value: float | None) -> float | None:
    """A value JSON keeps as a number (no NaN or infinity), or None."""
    return value if value is not None and math.isfinite(value) else None


def entry_data(entry: SensorEntry) -> dict[str, object]:
    """The entry's fields as a record keeps them (dates in ISO 8601; the stamp zone-less)."""
    if isinstance(entry, Calibration):
        return {
            "x_zero": entry.x_zero,
            "x_span": entry.x_span,
            "stamp": entry.stamp.isoformat(),
        }
    return {
        "entry_type": entry.kind,
        "manual_change": entry.manual,
        "rating": entry.rating,
        "operating_seconds": _finite(entry.operating_s),
        "date": None if entry.date is None else entry.date.isoformat(),
        "sensor_replacement_counter": _finite(entry.cap_counter),
        "phase": _finite(entry.phase),
    }


def _number(value: object) -> float | None:
    return float(value) if isinstance(value, int | float) and not isinstance(value, bool) else None


def _date(value: object) -> datetime | None:
    return datetime.fromisoformat(value) if isinstance(value, str) else None


def entry_from(ring: str, data: Mapping[str, object]) -> SensorEntry | None:
    """An entry back from a record's ``data["entry"]``; None if it is not one."""
    try:
        if ring == HISTORY_RING:
            zero, span, stamp = _number(data["x_zero"]), _number(data["x_span"]), data["stamp"]
            if zero is None or span is None or not isinstance(stamp, str):
                return None
            return Calibration(x_zero=zero, x_span=span, stamp=datetime.fromisoformat(stamp))
        if ring == LOGBOOK_RING:
            return LogbookEntry(
                kind=str(data["entry_type"]),
                manual=data["manual_change"] is True,
                rating=str(data["rating"]),
                operating_s=_number(data["operating_seconds"]),
                date=_date(data["date"]),
                cap_counter=_number(data["sensor_replacement_counter"]),
                phase=_number(data["phase"]),
            )
    except (KeyError, ValueError):
        return None
    return None


_EPOCH: Final = datetime(1970, 1, 1)  # noqa: DTZ001 - the origin of zone-less stamps


def _oldest_first(entry: SensorEntry) -> tuple[float, float]:
    """Sort key: the calibration's time, then the operating counter (an H10's tie-break)."""
    if isinstance(entry, Calibration):
        # Zone-less wall-clock times: ordered among themselves, as the sensor orders them.
        return (entry.stamp.replace(tzinfo=None) - _EPOCH).total_seconds(), 0.0
    when = -math.inf if entry.date is None else entry.date.timestamp()
    return when, entry.operating_s or 0.0


class HistoryKeeper:
    """Every entry of the sensors' rings, copied into the records once; handed back to care.

    Example::

        keeper = HistoryKeeper(store)
        keeper.copy(device, ring)  # the records appended, one per entry not copied before
        keeper.history(device)  # every entry of that sensor, oldest first
        book.keep_history(keeper.for_care(device_refs(state)))  # the running gateway's care
    """

    def __init__(self, store: RecordStore) -> None:
        """Learn from ``store`` what was copied already (one read of its history records)."""
        self.store = store
        self._copied: set[str] = set()
        self._kept: dict[str, list[SensorEntry]] = {}  # by sensor_key, in order of copying
        self._learned = False
        with contextlib.suppress(RecordError):  # unreadable now: learnt at the first copy
            self._learn_all()

    def _learn_all(self) -> None:
        """What was copied already, read once (a :class:`RecordError` if it cannot be)."""
        if self._learned:
            return
        for record in self.store.records(Query(kinds=(Kind.HISTORY,))):
            self._learn(record)
        self._learned = True

    def _learn(self, record: Record) -> None:
        data = record.body.get("data")
        if not isinstance(data, dict):
            return
        key, sensor, ring, fields = (
            data.get("entry_key"),
            data.get("sensor"),
            data.get("ring"),
            data.get("entry"),
        )
        if not isinstance(key, str) or key in self._copied:
            return
        self._copied.add(key)
        if isinstance(sensor, str) and isinstance(ring, str) and isinstance(fields, dict):
            entry = entry_from(ring, fields)
            if entry is not None:
                self._kept.setdefault(sensor, []).append(entry)
                return
        _LOGGER.debug("record %d: a history entry that cannot be read back", record.seq)

    def copied(self, device: DeviceRef, entry: SensorEntry) -> bool:
        """Whether this entry of this sensor is in the records already."""
        return entry_key(device, entry) in self._copied

    def copy(self, device: DeviceRef, ring: Iterable[SensorEntry]) -> list[Record]:
        """One ``history`` record for each entry of ``ring`` not copied before, oldest first.

        ``ring``: the entries the sensor holds now, as care reads them, in any order. The
        records appended are returned; a :class:`~gateway.errors.RecordError` from the
        store stops the copy, and what was not copied is copied at the next call.
        """
        self._learn_all()  # a store unreadable at the start: before anything is copied
        made = []
        for entry in sorted(ring, key=_oldest_first):
            key = entry_key(device, entry)
            if key in self._copied:
                continue
            made.append(self.store.append(self._entry(device, entry, key)))
            self._copied.add(key)
            self._kept.setdefault(sensor_key(device), []).append(entry)
        return made

    @staticmethod
    def _entry(device: DeviceRef, entry: SensorEntry, key: str) -> Entry:
        ring = _ring(entry)
        where = "" if entry.number is None else f", {ring} entry {entry.number} of the sensor"
        if isinstance(entry, Calibration):
            note = (
                f"calibration stamped {entry.stamp:%Y-%m-%d %H:%M} (the sensor's clock, no "
                f"zone): X_Zero {entry.x_zero:g}, X_Span {entry.x_span:g}{where}"
            )
        else:
            dated = "undated" if entry.date is None else f"dated {entry.date:%Y-%m-%d %H:%M %z}"
            note = f"{entry.kind} {dated}, rated {entry.rating}{where}"
        return Entry(
            kind=Kind.HISTORY,
            actor=HISTORY_ACTOR,
            device=device,
            action=_ACTIONS[ring],
            result=Result.NOTED,
            note=note,
            data={
                "entry_key": key,
                "sensor": sensor_key(device),
                "ring": ring,
                "position": entry.number,
                "entry": entry_data(entry),
            },
        )

    def history(self, device: DeviceRef) -> tuple[SensorEntry, ...]:
        """Every entry copied of this sensor, oldest first (as :meth:`copy` numbers none)."""
        return tuple(sorted(self._kept.get(sensor_key(device), ()), key=_oldest_first))

    def keep(self, device: DeviceRef, ring: Sequence[SensorEntry]) -> tuple[SensorEntry, ...]:
        """Copy what is new in ``ring``; the whole history, the ring's own entries included.

        While the store cannot be written the ring's entries are given back with what was
        copied before, and copied at a later call (the store logs its failure once).
        """
        try:
            self.copy(device, ring)
        except RecordError as exc:
            _LOGGER.debug("%s: its history not copied this time: %s", device.name, exc)
            kept = self.history(device)
            new = [entry for entry in ring if entry not in kept]
            return tuple(sorted([*kept, *new], key=_oldest_first))
        return self.history(device)

    def for_care(self, identify: Callable[[str], DeviceRef | None]) -> PastEntries:
        """The seam sensor care calls (:meth:`gateway.care.CareBook.keep_history`).

        ``identify`` names a device as its records do, with the serial number its sensor
        reports; None while that serial number was not read yet: nothing is copied then
        (an entry keyed on the name first and on the serial later would be copied twice),
        and care fits over the ring alone until it is.
        """

        def past(device: str, ring: Sequence[SensorEntry], /) -> Sequence[SensorEntry]:
            ref = identify(device)
            return ring if ref is None else self.keep(ref, ring)

        return past


def device_refs(state: GatewayState) -> Callable[[str], DeviceRef | None]:
    """A device by name as the running gateway knows it, with the serial its sensor sent.

    The serial is the newest good sample of the profile's serial-number point, which the
    bus reads with the identity (and :class:`~gateway.shared.state.StateSink` records
    before care sees the same poll); a profile that polls none is keyed on the name.
    Called from the bus tasks, on the event loop's thread that records the samples.
    """

    def identify(device: str) -> DeviceRef | None:
        info = next((i for i in state.devices.values() if i.name == device), None)
        if info is None:
            return None
        serial: str | None = None
        if SERIAL_NUMBER_POINT in info.intervals:
            sample = state.last_good.get((info.bus, info.name, SERIAL_NUMBER_POINT))
            if sample is None or not str(sample.value).strip():
                return None  # not read yet: wait for it
            serial = str(sample.value).strip()
        return DeviceRef(
            name=info.name,
            profile=info.profile,
            bus=info.bus,
            address=info.address,
            serial=serial,
        )

    return identify
