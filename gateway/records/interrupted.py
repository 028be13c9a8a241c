"""Writes a kill or a power cut left unanswered: found at the next start, and closed.

A write is recorded before it is sent and its outcome after (:mod:`gateway.control.writes`).
A gateway killed in between leaves the write without an outcome. At its next start the
gateway adds the outcome ``unknown`` with what to do (:func:`close_interrupted`), so the
record says what happened, and nothing is lost (tests/records/test_power_cut.py).
"""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING, Final

from gateway.records.actor import GATEWAY
from gateway.records.model import DeviceRef, Entry, Kind, Result
from gateway.records.store import Query

if TYPE_CHECKING:
    from gateway.records.model import Record
    from gateway.records.store import RecordStore

_LOGGER = logging.getLogger(__name__)

INTERRUPTED: Final = (
    "the gateway stopped (a power cut or a kill) after this write was recorded and before "
    "the sensor's answer: whether the sensor took the value is not known; read it to see"
)


def unanswered(store: RecordStore) -> list[Record]:
    """Writes recorded as pending that no outcome record completes."""
    completed = {
        record.body.get("completes") for record in store.records(Query(kinds=(Kind.OUTCOME,)))
    }
    return [
        record
        for record in store.records(Query(kinds=(Kind.WRITE,)))
        if record.body.get("result") == Result.PENDING and record.seq not in completed
    ]


def close_interrupted(store: RecordStore) -> list[Record]:
    """At start: an outcome ``unknown`` for every write the last run left unanswered."""
    closed = []
    for pending in unanswered(store):
        device = pending.body.get("device")
        _LOGGER.warning(
            "record %d: a write to %s was recorded but its answer never was (the gateway "
            "stopped in between); recorded its outcome as unknown",
            pending.seq,
            device.get("name") if isinstance(device, dict) else "?",
        )
        closed.append(
            store.append(
                Entry(
                    kind=Kind.OUTCOME,
                    actor=GATEWAY,
                    device=DeviceRef.from_dict(device) if isinstance(device, dict) else None,
                    action=str(pending.body.get("action", "")),
                    result=Result.UNKNOWN,
                    completes=pending.seq,
                    note=INTERRUPTED,
                )
            )
        )
    return closed
