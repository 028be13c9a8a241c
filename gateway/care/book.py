"""Every device's care while the gateway runs: its records as polled, its report kept current.

The records are points the bus already polls (the history and logbook with the
diagnostics, the nominal slope with the identity), so care adds no request to the line:
it sees each poll cycle's samples, keeps those of its points, and assesses the device
again whenever they arrive, which is also when time alone may have made a calibration
due. A write that can change the records makes the bus read them again at once
(:mod:`gateway.profiles.effects`), so a calibration shows within one read, whoever made
it. Publishers compare :meth:`CareBook.version` with the one they last sent.
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass, field
from datetime import UTC, datetime
from typing import TYPE_CHECKING

from gateway.care.assess import assess
from gateway.care.records import Records, care_points, same_record
from gateway.line.samples import Quality

if TYPE_CHECKING:
    from collections.abc import Callable, Collection, Sequence
    from datetime import tzinfo

    from gateway.care.report import CareReport
    from gateway.care.rules import CareRules
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
    ) -> None:
        """Assess at ``clock()``; zone-less stamps in ``zone`` (None: the host's)."""
        self._clock = clock
        self._zone = zone
        self._devices: dict[str, _Device] = {}
        self._lock = threading.Lock()

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
        if len(tracked.values) + len(tracked.unreadable) >= len(points):
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

    def _assess(self, tracked: _Device) -> None:
        report = assess(
            Records(values=dict(tracked.values), unreadable=dict(tracked.unreadable)),
            tracked.rules,
            device=tracked.name,
            bus=tracked.bus,
            profile=tracked.profile,
            now=self._clock(),
            zone=self._zone,
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
