"""A device's acts recorded: each write before it is sent and after, and acts as a whole.

:class:`WriteRecorder` is :class:`~gateway.control.writes.SafeWriter`'s part that speaks to
the record store (:mod:`gateway.records`): the device as records name it (with the serial
number the sensor reports now), the value as found, the write's record before the
registers go out (a record that cannot be written refuses the write), its outcome after,
and the record of an act as a whole (a calibration, a verification). The actor is the
request's (:func:`gateway.records.actor.current`).
"""

from __future__ import annotations

import json
import logging
from collections.abc import Mapping
from datetime import datetime
from typing import TYPE_CHECKING

from gateway.errors import BusError, CommandRejectedError, RecordError
from gateway.profiles.serial_number import serial_point
from gateway.records import actor as actors
from gateway.records.model import DeviceRef, Entry, Kind, PointChange, Result, json_decoded
from gateway.records.store import Query
from gateway.wire import codec

if TYPE_CHECKING:
    from gateway.control.link import DeviceLink
    from gateway.profiles.model import Point
    from gateway.records.model import Record
    from gateway.records.store import RecordStore

_LOGGER = logging.getLogger(__name__)


def json_ready(value: object) -> object:
    """A value as asked for, as a record keeps it (JSON data, or its text)."""
    if isinstance(value, (codec.Fault, codec.EnumValue, codec.BitfieldValue, datetime)):
        return json_decoded(value)
    try:
        json.dumps(value)
    except (TypeError, ValueError):
        return str(value)
    return value


class WriteRecorder:
    """The records of one device's writes and acts, in one store."""

    def __init__(self, link: DeviceLink, records: RecordStore) -> None:
        """Record the acts on ``link``'s device in ``records``."""
        self.link = link
        self.records = records

    async def device_ref(self) -> DeviceRef:
        """The device as records name it, with the serial number it reports now.

        Read from the sensor at each recorded act (a replaced sensor at the same address is
        recorded under its own serial); ``None`` where it cannot be read, and the record
        still made.
        """
        link = self.link
        serial: str | None = None
        point = serial_point(link.profile)
        if point is not None:
            try:
                answered = await link.read_point(point)
            except BusError as exc:
                _LOGGER.debug("%s: serial number not read for the record: %s", link.device, exc)
            else:
                serial = None if isinstance(answered, codec.Fault) else str(answered).strip()
        return DeviceRef(
            name=link.device,
            profile=link.profile.id,
            bus=link.bus,
            address=link.address,
            serial=serial,
        )

    async def act(
        self,
        kind: Kind,
        *,
        action: str,
        result: Result,
        note: str = "",
        points: tuple[PointChange, ...] = (),
        data: Mapping[str, object] | None = None,
    ) -> Record:
        """A record of an act on this device as a whole (a calibration, a verification).

        By the current actor, with the device's serial number read now. A
        :class:`~gateway.errors.RecordError` if it cannot be written.
        """
        return self.records.append(
            Entry(
                kind=kind,
                actor=actors.current(),
                device=await self.device_ref(),
                action=action,
                result=result,
                points=points,
                note=note,
                data=dict(data or {}),
            )
        )

    def writes_since(self, seq: int) -> list[int]:
        """The numbers of this device's write records after record ``seq``."""
        return [
            record.seq
            for record in self.records.records(Query(device=self.link.device, kinds=(Kind.WRITE,)))
            if record.seq > seq
        ]

    async def as_found(self, point: Point) -> tuple[codec.Decoded, str]:
        """The point's value before the write, or why it could not be read."""
        try:
            return await self.link.read_point(point), ""
        except BusError as exc:
            return None, f"as found: not read ({exc})"

    async def write(
        self,
        point: Point,
        value: object,
        registers: tuple[int, ...],
        found: tuple[codec.Decoded, str],
    ) -> Record:
        """The write's record, on disk before it is sent; a refusal if it cannot be."""
        as_found, note = found
        entry = Entry(
            kind=Kind.WRITE,
            actor=actors.current(),
            device=await self.device_ref(),
            action=f"write {point.name}",
            result=Result.PENDING,
            points=(
                PointChange(
                    point=point.name,
                    unit=point.unit,
                    as_found=json_decoded(as_found) if not note else None,
                    sent=json_ready(value),
                    registers=registers,
                ),
            ),
            note=note,
        )
        try:
            return self.records.append(entry)
        except RecordError as exc:
            raise CommandRejectedError(str(exc), point=point.name) from exc

    def outcome(
        self,
        pending: Record,
        point: Point,
        result: Result,
        *,
        note: str = "",
        as_left: object = None,
    ) -> None:
        """What became of a recorded write; if that cannot be written, the next start says."""
        device = pending.body.get("device")
        entry = Entry(
            kind=Kind.OUTCOME,
            actor=actors.current(),
            device=DeviceRef.from_dict(device) if isinstance(device, Mapping) else None,
            action=f"write {point.name}",
            result=result,
            points=(PointChange(point=point.name, unit=point.unit, as_left=as_left),),
            note=note,
            completes=pending.seq,
        )
        try:
            self.records.append(entry)
        except RecordError as exc:
            _LOGGER.error(  # noqa: TRY400 - the cause is the message; no trace helps
                "%s: the outcome of record %d could not be recorded (%s); the next start "
                "records it as unknown",
                self.link.device,
                pending.seq,
                exc,
            )
