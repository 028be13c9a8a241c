"""Every device's care while the gateway runs: its records as polled, its report kept current.

The records are points the bus already polls (the history and logbook with the
diagnostics, the nominal slope with the identity), so care adds no request to the line:
it sees each poll cycle's samples, keeps those of its points, and assesses the device
again whenever they arrive, which is also when time alone may have made a calibration
due. A write that can change the records makes the bus read them again at once
(:mod:`gateway.profiles.effects`), so a calibration shows within one read, whoever made
it. Publishers compare :meth:`CareBook.version` with the one they last sent.

The sensors' rings overwrite (5 calibrations in a tecLine's history, 10 entries in an
H10's logbook); the records keep every entry, a floor above. So the book hands each ring
it assesses to the :class:`~gateway.care.records.PastEntries` the app gives it
(:meth:`CareBook.keep_history`) and fits its trends over what comes back.

Grab-sample verifications are not polled: the app hands each new one to
:meth:`CareBook.verified` as it is recorded, and those in the records at start, so the
book keeps each device's latest and latest passed one and assesses the device again at
once (a passed one moves the due date, a failed one makes it due).
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass, field
from datetime import UTC, datetime
from typing import TYPE_CHECKING

from gateway.care.assess import assess
from gateway.care.records import Records, care_points, ring_entries, same_record
from gateway.care.rules import CareKind
from gateway.care.verifications import later
from gateway.line.samples import Quality

if TYPE_CHECKING:
    from collections.abc import Callable, Collection, Sequence
    from datetime import tzinfo

    from gateway.care.records import PastEntries, SensorEntry
    from gateway.care.report import CareReport
    from gateway.care.rules import CareRules
    from gateway.care.verifications import Verification
    from gateway.line.samples import Sample
    from gateway.profiles import Profile
    from gateway.wire import codec

NOT_POLLED = "not polled: switched off in the config"
# Records that did not change are assessed again at most this often, for what time alone
# changes (a calibration falling due); a change is assessed at once.
REASSESS_S = 60.0


@dataclass(slots=True)
class _Device:
    bus: str
    name: str
    profile: str
    rules: CareRules
    points: frozenset[str]
    values: dict[str, codec.Decoded] = field(default_factory=dict)
    unreadable: dict[str, str] = field(default_factory=dict)
    report: CareReport | None = None
    version: int = 0
    assessed: float = -math.inf  # monotonic time of the last assessment


@dataclass(frozen=True, slots=True)
class _Checks:
    """A device's latest grab-sample verification, and its latest passed one."""

    latest: Verification | None = None
    passed: Verification | None = None


class CareBook:
    """The care of every configured device; read from any thread, written by the bus tasks.

    Example::

        book = CareBook()
        book.add_device(bus="line1", device="basin_chlorine", profile=profile, rules=rules,
                        polled=target.intervals)
        book.observe(samples)  # a poll cycle of that device
        book.report("basin_chlorine")  # CareReport, once every record was read
    """

    def __init__(
        self,
        *,
        clock: Callable[[], datetime] = lambda: datetime.now(UTC),
        zone: tzinfo | None = None,
        history: PastEntries | None = None,
    ) -> None:
        """Assess at ``clock()``; zone-less stamps in ``zone`` (None: the host's).

        ``history``: where the rings' entries are kept (:meth:`keep_history`).
        """
        self._clock = clock
        self._zone = zone
        self._history = history
        self._devices: dict[str, _Device] = {}
        # By device name, apart from the tracked devices: a reload that adds a device
        # afresh, or verifications read from the records before the devices are added,
        # lose none of them.
        self._checks: dict[str, _Checks] = {}
        self._lock = threading.Lock()

    def keep_history(self, history: PastEntries | None) -> None:
        """Hand every ring assessed from now on to ``history``, and fit over what it gives back.

        Set once when the gateway starts, before the first poll: the state that owns the
        book is built before the records are opened. None: the rings alone, as before.
        """
        self._history = history

    def add_device(
        self,
        *,
        bus: str,
        device: str,
        profile: Profile,
        rules: CareRules | None,
        polled: Collection[str],
    ) -> None:
        """Track a device (``rules`` None: care is off for it); ``polled``: its polled points.

        Adding a device tracked already (a reload changed it) starts it afresh.
        """
        if rules is None:
            self.remove_device(device)
            return
        points = care_points(profile, rules.kind)
        tracked = _Device(
            bus=bus, name=device, profile=profile.id, rules=rules, points=frozenset(points)
        )
        tracked.unreadable = {name: NOT_POLLED for name in points if name not in polled}
        with self._lock:
            self._devices[device] = tracked

    def remove_device(self, device: str) -> None:
        """Stop tracking a device (a reload removed it, or its care is off now)."""
        with self._lock:
            self._devices.pop(device, None)

    def observe(self, samples: Sequence[Sample]) -> None:
        """Take one device's poll cycle; assess it again if care's records were in it."""
        if not samples:
            return
        tracked = self._devices.get(samples[0].device)
        if tracked is None:
            return
        points = tracked.points
        changed = False
        now = samples[0].monotonic
        for sample in samples:
            if sample.point in points:
                changed = self._keep(tracked, sample) or changed
        if not changed and now - tracked.assessed < REASSESS_S:
            return  # status words come every poll: assessed on a change, or once a minute
        if _all_read(tracked):
            tracked.assessed = now
            self._assess(tracked)

    @staticmethod
    def _keep(tracked: _Device, sample: Sample) -> bool:
        """Keep one record; whether it changed what care knows."""
        name = sample.point
        if sample.quality is Quality.GOOD:
            if name in tracked.values and same_record(name, tracked.values[name], sample.value):
                return False
            tracked.values[name] = sample.value
            tracked.unreadable.pop(name, None)
            return True
        if sample.quality is Quality.FAULT:
            reason = f"the sensor sent {sample.fault or 'a fault'}"
            if tracked.unreadable.get(name) == reason:
                return False
            tracked.values.pop(name, None)
            tracked.unreadable[name] = reason
            return True
        if name in tracked.values or name in tracked.unreadable:
            # No answer: what was read before still stands (the device's availability
            # says it is offline); only a record never read is missing.
            return False
        tracked.unreadable[name] = "no answer from the sensor"
        return True

    def verified(self, device: str, verification: Verification) -> None:
        """Take a grab-sample verification of ``device``: keep it if newest, assess again.

        Called with each verification as it is recorded, and at start with each one in
        the records (any order: the sample taken last is kept, not the last one handed
        over, and the latest passed one apart). A device whose records were all read is
        assessed at once, so its care document is published again; one not tracked (yet)
        keeps it for when it is. Call it from the event loop the bus tasks run in, as
        they write the records it assesses.
        """
        with self._lock:
            kept = self._checks.get(device, _Checks())
            checks = _Checks(
                latest=later(kept.latest, verification),
                passed=later(kept.passed, verification) if verification.passed else kept.passed,
            )
            if checks == kept:
                return
            self._checks[device] = checks
        tracked = self._devices.get(device)
        if tracked is not None and _all_read(tracked):
            self._assess(tracked)

    def _assess(self, tracked: _Device) -> None:
        records = Records(values=dict(tracked.values), unreadable=dict(tracked.unreadable))
        checks = self._checks.get(tracked.name, _Checks())
        past: Sequence[SensorEntry] = ()
        if self._history is not None and tracked.rules.kind is not CareKind.OPTICAL:
            past = self._history(tracked.name, ring_entries(records, tracked.rules.ring))
        report = assess(
            records,
            tracked.rules,
            device=tracked.name,
            bus=tracked.bus,
            profile=tracked.profile,
            now=self._clock(),
            zone=self._zone,
            past=past,
            last_verification=checks.latest,
            last_passed=checks.passed,
        )
        with self._lock:
            if tracked.report is None or tracked.report.key != report.key:
                tracked.version += 1
            tracked.report = report

    def report(self, device: str) -> CareReport | None:
        """The device's latest report; None before all its records were read once."""
        tracked = self._devices.get(device)
        return None if tracked is None else tracked.report

    def version(self, device: str) -> int:
        """Changes with every report whose content changed (not with its time alone)."""
        tracked = self._devices.get(device)
        return 0 if tracked is None else tracked.version

    def reports(self) -> list[CareReport]:
        """Every device's latest report, in the order the devices were added."""
        with self._lock:
            return [d.report for d in self._devices.values() if d.report is not None]

    def tracked(self, device: str) -> bool:
        """Whether care follows this device."""
        return device in self._devices


def _all_read(tracked: _Device) -> bool:
    """Whether every record of the device was read once (or is known unreadable)."""
    return len(tracked.values) + len(tracked.unreadable) >= len(tracked.points)
