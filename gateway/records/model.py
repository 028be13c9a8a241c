"""What a record says: its kind, the actor, the device, each point as found and as left.

One record is one act (a write sent to a sensor, its outcome, a calibration as a whole, a
grab-sample verification, a reload, a change of the host clock's trust, an entry of a
sensor's own history copied before the sensor's ring overwrites it, a correction). The
fields are those an auditor asks of an audit trail (21 CFR Part 11 §11.10(e), EU GMP
Annex 11 §9): who (:class:`~gateway.records.actor.Actor`), when (UTC, and whether the
host clock was synchronised), what (the device with its serial number, each point's
value as read before and after), the result, and why; a correction names the record it
corrects and changes nothing in it.

Values are kept as JSON data that reads back as the sensor gave them: a number, an
enumeration's code with its label, a bit field's word with its bits, a fault by name.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from datetime import datetime
from enum import StrEnum
from typing import TYPE_CHECKING, Any

from gateway.records.actor import Actor
from gateway.wire.codec import BitfieldValue, EnumValue, Fault

if TYPE_CHECKING:
    from collections.abc import Mapping

    from gateway.wire import codec


class Kind(StrEnum):
    """The kinds of record."""

    WRITE = "write"  # registers sent to a sensor, recorded before they are sent
    OUTCOME = "outcome"  # what became of a write: written and read back, failed, unknown
    CALIBRATION = "calibration"  # a calibration as a whole, with its result
    VERIFICATION = "verification"  # a grab sample compared with the sensor's value
    HISTORY = "history"  # an entry of the sensor's own calibration history or logbook
    RELOAD = "reload"  # the config changed while running
    CLOCK = "clock"  # the host clock's trust changed, or the clock stepped
    FEEDS = "feeds"  # compensation values fed to volatile registers, counted per day
    CORRECTION = "correction"  # a note that corrects an earlier record (which stays)


class Result(StrEnum):
    """How an act ended (a record's ``result``); the text of a failure is in ``note``."""

    PENDING = "pending"  # recorded, not yet answered: an outcome record follows
    DONE = "done"  # written (and read back if it could be), or completed
    FAILED = "failed"  # the sensor or the line refused or did not answer
    UNKNOWN = "unknown"  # the gateway stopped between the record and the answer
    PASSED = "passed"  # a verification within its acceptance rule
    NOT_PASSED = "failed-check"  # a verification outside it
    NOTED = "noted"  # a record of something that happened (a reload, the clock, history)


def json_decoded(value: codec.Decoded) -> object:
    """A decoded value as a record keeps it: nothing the sensor said is lost."""
    if isinstance(value, Fault):
        return {"fault": value.name, "raw": value.raw, "reason": value.reason or None}
    if isinstance(value, EnumValue):
        return {"code": value.code, "label": value.label}
    if isinstance(value, BitfieldValue):
        return {"word": value.raw, "bits": list(value.active)}
    if isinstance(value, datetime):
        return value.isoformat()
    return value


@dataclass(frozen=True, slots=True, kw_only=True)
class DeviceRef:
    """The device as a record names it: its name in the config, profile, place, serial."""

    name: str
    profile: str
    bus: str = ""
    address: int | None = None
    serial: str | None = None  # as read from the sensor; None until it was read

    @classmethod
    def from_dict(cls, data: Mapping[str, object]) -> DeviceRef:
        """Back from a record's ``device``."""
        address = data.get("address")
        serial = data.get("serial")
        return cls(
            name=str(data.get("name", "")),
            profile=str(data.get("profile", "")),
            bus=str(data.get("bus", "")),
            address=address if isinstance(address, int) else None,
            serial=None if serial is None else str(serial),
        )

    def as_dict(self) -> dict[str, object]:
        """The fields as a record stores them."""
        return {
            "name": self.name,
            "profile": self.profile,
            "bus": self.bus,
            "address": self.address,
            "serial": self.serial,
        }


@dataclass(frozen=True, slots=True, kw_only=True)
class PointChange:
    """One point of an act: the value found, what was sent, the value left.

    ``as_found`` and ``as_left`` are JSON data (:func:`json_decoded`) as read from the
    sensor before and after; ``None`` where a value was not read (with the reason in the
    record's note). ``sent`` is the value as asked and the registers that went out.
    """

    point: str
    unit: str | None = None
    as_found: object = None
    sent: object = None
    registers: tuple[int, ...] = ()
    as_left: object = None

    def as_dict(self) -> dict[str, object]:
        """The fields as a record stores them (registers as the manuals print them)."""
        return {
            "point": self.point,
            "unit": self.unit,
            "as_found": self.as_found,
            "sent": self.sent,
            "registers": [f"0x{word:04X}" for word in self.registers],
            "as_left": self.as_left,
        }


@dataclass(frozen=True, slots=True, kw_only=True)
class Entry:
    """A record to append: everything but its number, time and hash, which the store adds."""

    kind: Kind
    actor: Actor
    action: str
    result: Result
    device: DeviceRef | None = None
    points: tuple[PointChange, ...] = ()
    note: str = ""
    completes: int | None = None  # the record whose outcome this is
    corrects: int | None = None  # the record this one corrects
    data: Mapping[str, object] = field(default_factory=dict)  # what only this kind has

    def body(self, *, seq: int, time: datetime, clock_synchronised: bool) -> dict[str, object]:
        """The record's content, whose canonical text the chain hashes."""
        return {
            "seq": seq,
            "time": time.isoformat(timespec="milliseconds"),
            "clock_synchronised": clock_synchronised,
            "kind": str(self.kind),
            "actor": self.actor.as_dict(),
            "device": None if self.device is None else self.device.as_dict(),
            "action": self.action,
            "points": [change.as_dict() for change in self.points],
            "result": str(self.result),
            "note": self.note,
            "completes": self.completes,
            "corrects": self.corrects,
            "data": dict(self.data),
        }


@dataclass(frozen=True, slots=True, kw_only=True)
class Record:
    """A record as stored: its number, hash and content (read back from the store)."""

    seq: int
    hash: str
    body: Mapping[str, Any]  # JSON as stored: its fields are read by name

    @property
    def kind(self) -> str:
        """The record's kind (a :class:`Kind` value)."""
        return str(self.body.get("kind", ""))

    @property
    def device(self) -> str | None:
        """The name of the record's device, if it has one."""
        device = self.body.get("device")
        return str(device.get("name")) if isinstance(device, dict) else None

    @property
    def time(self) -> str:
        """The record's UTC time, ISO 8601."""
        return str(self.body.get("time", ""))


__all__ = [
    "Actor",
    "DeviceRef",
    "Entry",
    "Kind",
    "PointChange",
    "Record",
    "Result",
    "json_decoded",
]
