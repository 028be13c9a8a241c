"""The host clock's trust, recorded whenever it changes, and every step of the wall clock.

A record's time is only as good as the host clock: an auditor reading "10:02 UTC" must be
able to see that the clock was unsynchronised then, and when it was stepped (an NTP
service setting a Raspberry Pi's clock hours after boot). Each record carries the
synchronisation status of its moment; this watch adds a record of kind ``clock`` when the
status changes (synchronised or not, trusted by the override or not) and when the wall
clock jumps against the monotonic clock by more than :data:`STEP_S`. The running gateway
looks every few seconds (:class:`gateway.app.audit.AuditTrail`).
"""

from __future__ import annotations

import logging
import time
from datetime import UTC, datetime
from typing import TYPE_CHECKING, Final

from gateway.errors import RecordError
from gateway.records.actor import GATEWAY
from gateway.records.model import Entry, Kind, Result

if TYPE_CHECKING:
    from collections.abc import Callable

    from gateway.records.store import RecordStore
    from gateway.shared.host_clock import ClockStatus, HostClock

_LOGGER = logging.getLogger(__name__)

STEP_S: Final = 2.0  # a wall clock that moved this much more or less than the monotonic one


class ClockWatch:
    """Compares each reading of the host clock with the last, and records the changes."""

    def __init__(
        self,
        store: RecordStore,
        clock: HostClock,
        *,
        wall: Callable[[], float] = time.time,
        monotonic: Callable[[], float] = time.monotonic,
    ) -> None:
        """Watch ``clock`` into ``store``; ``wall`` and ``monotonic`` are the seams for tests."""
        self.store = store
        self.clock = clock
        self._wall = wall
        self._monotonic = monotonic
        self._last: ClockStatus | None = None
        self._offset: float | None = None  # wall minus monotonic at the last look

    def look(self) -> None:
        """One comparison: a record for a change of trust and for a step."""
        status = self.clock.status()
        offset = self._wall() - self._monotonic()
        last, last_offset = self._last, self._offset
        self._last, self._offset = status, offset
        if last is None or last_offset is None:
            self._append(
                "the gateway started",
                status,
                note=status.problem or "the host clock is synchronised",
            )
            return
        if (last.synchronised, last.trusted) != (status.synchronised, status.trusted):
            said = "synchronised" if status.synchronised else "no longer synchronised"
            trust = "trusted" if status.trusted else "not trusted for writing dates"
            self._append(f"the host clock is {said}", status, note=f"{said}; {trust}")
        step = offset - last_offset
        if abs(step) > STEP_S:
            self._append(
                "the host clock was stepped",
                status,
                note=f"the wall clock moved {step:+.1f} s against the monotonic clock",
                data={"step_s": round(step, 3)},
            )

    def _append(
        self,
        action: str,
        status: ClockStatus,
        *,
        note: str,
        data: dict[str, object] | None = None,
    ) -> None:
        try:
            self.store.append(
                Entry(
                    kind=Kind.CLOCK,
                    actor=GATEWAY,
                    action=action,
                    result=Result.NOTED,
                    note=note,
                    data={
                        "synchronised": status.synchronised,
                        "trusted": status.trusted,
                        "max_error_s": status.max_error_s,
                        "wall": datetime.now(UTC).isoformat(timespec="milliseconds"),
                        **(data or {}),
                    },
                )
            )
        except RecordError as exc:
            _LOGGER.warning("the clock's change was not recorded: %s", exc)
