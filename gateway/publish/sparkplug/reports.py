"""Births, data and deaths, without I/O: what the host is told, and what it was told last.

:class:`Reporter` keeps, per device, whether it is born (a DBIRTH went out since the last
NBIRTH or DDEATH), whether it is dead (a DDEATH went out and it has not answered since) and
the value, quality and unit last reported of each metric. A device is born by its first
cycle with an answer, once the unit registers its metrics need are read (or
``birth_wait_s`` after its first answer, whichever comes first): one DBIRTH with its units.
A device announced offline stays dead until it is announced online again: what its failed
cycle brings after the DDEATH is not news of it. A poll cycle of a born device becomes a
DDATA of the metrics that changed (report by exception): a Float by at least its deadband,
anything else by any change, any metric whose quality changed.

Each sample reads as its metrics' values as :mod:`gateway.publish.sparkplug.readings` says
(one meaning per quality code).

The care metrics (group ``care``) are not samples: they are the device's care report as
the state's care book holds it (:class:`CareSource`). A cycle compares the book's version
of the device with the one last reported, and only when it changed reads the report and
reports the care metrics that differ, in the same DDATA as the values (stale nulls before
the first report). A birth carries them only for a device the book follows (care is not
switched off for it).

Payloads are built without ``seq``; the session adds it as they go out.
"""

from __future__ import annotations

import time
from typing import TYPE_CHECKING, Protocol

from gateway.line.samples import Quality
from gateway.publish.message import Message
from gateway.publish.sparkplug import payloads
from gateway.publish.sparkplug.catalogue import BD_SEQ, REBIRTH
from gateway.publish.sparkplug.payloads import (
    QUALITY_GOOD,
    QUALITY_STALE,
    Payload,
    SpType,
)
from gateway.publish.sparkplug.readings import CARE_VALUES, Reported, differs, fill, readings

if TYPE_CHECKING:
    from collections.abc import Callable, Iterable, Sequence

    from gateway.care import CareReport
    from gateway.line.samples import Sample
    from gateway.publish.sparkplug.catalogue import Catalogue, DeviceMetrics, MetricSpec
    from gateway.publish.sparkplug.topics import SparkplugTopics

BIRTH_WAIT_S = 10.0  # sparkplug.birth_wait_s: the unit registers are read in the first cycle


class CareSource(Protocol):
    """Where the care reports come from: :class:`gateway.care.CareBook` (``state.care``)."""

    def report(self, device: str) -> CareReport | None:
        """The device's latest report; None before the first."""

    def version(self, device: str) -> int:
        """Changes whenever the content of the device's report does."""

    def tracked(self, device: str) -> bool:
        """Whether care follows the device."""


def ndeath_payload(bd_seq: int, now_ms: int) -> bytes:
    """The NDEATH: the ``bdSeq`` of the session it ends, and no ``seq`` (Sparkplug 3.0, 6.4.2)."""
    payload = payloads.new_payload(now_ms)
    metric = payload.metrics.add()
    metric.name = BD_SEQ
    metric.datatype = SpType.INT64
    metric.long_value = bd_seq
    return bytes(payload.SerializeToString())


class Reporter:
    """Builds the node's messages and remembers what each device last reported."""

    def __init__(
        self,
        catalogue: Catalogue,
        topics: SparkplugTopics,
        *,
        birth_wait_s: float = BIRTH_WAIT_S,
        clock: Callable[[], float] = time.monotonic,
        care: CareSource | None = None,
    ) -> None:
        """Report the metrics of ``catalogue`` on ``topics``.

        A birth waits for its units at most ``birth_wait_s`` after the device's first
        answer, on ``clock`` (monotonic seconds). The care metrics come from ``care``
        (None: no care metric is reported).
        """
        self.catalogue = catalogue
        self.topics = topics
        self.birth_wait_s = birth_wait_s
        self._clock = clock
        self.care = care
        # The care book's version of each device whose care metrics are recorded.
        self._care_versions: dict[str, int] = {}
        self.born: set[str] = set()
        # Announced offline, and not online again since: nothing of them is reported.
        self.dead: set[str] = set()
        # When a device not born first answered: its birth waits for its units from then.
        self._waiting_since: dict[str, float] = {}
        self._last: dict[str, dict[int, Reported]] = {d: {} for d in catalogue.devices}
        # The engineering unit each metric's last DBIRTH announced, where it had one.
        self._units: dict[str, dict[int, str | None]] = {d: {} for d in catalogue.devices}

    def last(self, device: str) -> dict[int, Reported]:
        """What was last reported of each metric of ``device``, by alias."""
        return self._last[device]

    # --- births and deaths -------------------------------------------------------------

    def births(self, bd_seq: int, now_ms: int) -> list[Message]:
        """NBIRTH, then a DBIRTH of every device born (Sparkplug 3.0, 5.8 and 5.9)."""
        return [self.nbirth(bd_seq, now_ms), *(self.dbirth(d, now_ms) for d in self._born())]

    def _born(self) -> list[str]:
        return [d for d in self.catalogue.devices if d in self.born]

    def nbirth(self, bd_seq: int, now_ms: int) -> Message:
        """The node's birth: ``bdSeq`` (as in the will) and ``Node Control/Rebirth``.

        Neither has an alias: the rebirth metric must not have one
        (``tck-id-operational-behavior-data-commands-rebirth-name-aliases``), so a host
        commands it by name.
        """
        payload = payloads.new_payload(now_ms)
        metric = payload.metrics.add()
        metric.name = BD_SEQ
        metric.timestamp = now_ms
        metric.datatype = SpType.INT64
        metric.long_value = bd_seq
        rebirth = payload.metrics.add()
        rebirth.name = REBIRTH
        rebirth.timestamp = now_ms
        rebirth.datatype = SpType.BOOLEAN
        rebirth.boolean_value = False
        return self._message(self.topics.nbirth, payload)

    def dbirth(self, device: str, now_ms: int) -> Message:
        """A device's birth: every metric with name, alias, type, unit, description, value."""
        metrics = self.catalogue.devices[device]
        self._care_changes(metrics, now_ms)
        cared = self.care is not None and self.care.tracked(device)
        last = self._last[device]
        units = self._units[device] = {}
        payload = payloads.new_payload(now_ms)
        for spec in metrics.metrics:
            if spec.care is not None and not cared:
                continue
            reported = last.get(spec.alias)
            metric = payload.metrics.add()
            metric.name = spec.name
            metric.alias = spec.alias
            metric.datatype = spec.datatype
            if reported is None:
                metric.timestamp = now_ms
                metric.is_null = True
                quality = QUALITY_GOOD if spec.point is None else QUALITY_STALE
            else:
                metric.timestamp = reported.time_ms
                fill(metric, spec, reported)
                quality = reported.quality
            payloads.set_property(metric, payloads.QUALITY, SpType.INT32, quality)
            unit = reported.unit if reported is not None and reported.unit else spec.unit
            units[spec.alias] = unit
            if unit:
                payloads.set_property(metric, payloads.ENG_UNIT, SpType.STRING, unit)
            if spec.description:
                payloads.set_property(metric, payloads.DESCRIPTION, SpType.STRING, spec.description)
            payloads.set_property(metric, payloads.READ_ONLY, SpType.BOOLEAN, not spec.writable)
        self.born.add(device)
        self._waiting_since.pop(device, None)
        return self._message(self.topics.device("DBIRTH", device), payload)

    def ddeath(self, device: str, now_ms: int) -> Message | None:
        """A device's death: dead until it is online again; a DDEATH if it was born.

        What it reported is forgotten: its next birth carries only what it answers then.
        """
        self._last[device] = {}
        self._care_versions.pop(device, None)
        self._waiting_since.pop(device, None)
        if device in self.catalogue.devices:
            self.dead.add(device)
        if device not in self.born:
            return None
        self.born.discard(device)
        return self._message(self.topics.device("DDEATH", device), payloads.new_payload(now_ms))

    def forget(self, device: str, now_ms: int) -> Message | None:
        """A device a reload removed or changed: its DDEATH if it was born; nothing kept."""
        message = self.ddeath(device, now_ms)
        self.dead.discard(device)
        self._last.pop(device, None)
        self._units.pop(device, None)
        return message

    def track(self, devices: Iterable[str]) -> None:
        """Devices a reload added to the catalogue: born at their first answer, as at a start."""
        for device in devices:
            self._last[device] = {}
            self._units[device] = {}

    def alive(self, device: str) -> None:
        """The device is online again: its next cycle with an answer may birth it."""
        self.dead.discard(device)

    # --- data ----------------------------------------------------------------------------

    def cycle(self, samples: Sequence[Sample], *, live: bool, now_ms: int) -> list[Message]:
        """One device's poll cycle: its DBIRTH once it is ready, else a DDATA of the changes.

        A dead device's cycle is dropped (the failed cycle that took it offline reaches
        the sinks after its DDEATH), and so is a cycle without any answer of a device not
        born. A device not born is born once ready (:meth:`ready`); until then its values
        are kept for the birth. While not ``live`` (the host or the broker away) a device
        ready is only marked born (the births sent when the host is back carry it), and a
        DDATA is historical.
        """
        device = samples[0].device
        metrics = self.catalogue.devices.get(device)
        if metrics is None or device in self.dead:
            return []
        if device not in self.born:
            return self._unborn_cycle(metrics, samples, live=live, now_ms=now_ms)
        changed = self._changes(metrics, samples) + self._care_changes(metrics, now_ms)
        if live and self._unit_changed(device, changed):
            # A unit is a property of the birth: a new one (a unit register changed on the
            # sensor, or read only after the wait) is told by a new DBIRTH.
            return [self.dbirth(device, now_ms)]
        if not changed:
            return []
        return [self.ddata(device, changed, historical=not live, now_ms=now_ms)]

    def _unborn_cycle(
        self, metrics: DeviceMetrics, samples: Sequence[Sample], *, live: bool, now_ms: int
    ) -> list[Message]:
        """A cycle of a device not born: kept for its birth, which goes once it is ready."""
        device = metrics.device
        if all(s.quality is Quality.COMMS_ERROR for s in samples):
            return []  # no answer: nothing to birth
        self._changes(metrics, samples)
        self._waiting_since.setdefault(device, self._clock())
        if not self.ready(device):
            return []
        if not live:
            self.born.add(device)
            self._waiting_since.pop(device, None)
            return []
        return [self.dbirth(device, now_ms)]

    def ready(self, device: str) -> bool:
        """Whether a device not born may be: its units known, or waited for long enough.

        A metric whose unit comes from a unit register (a tecLine's or a Reiss's
        concentration) has it once that register is read; a birth without it would be
        followed by another as soon as it is. The wait is bounded (``birth_wait_s`` from
        the first answer): a unit register that cannot be read does not keep the device
        from the host, and a unit that comes later still brings a new DBIRTH.
        """
        since = self._waiting_since.get(device)
        if since is not None and self._clock() - since >= self.birth_wait_s:
            return True
        last = self._last[device]
        for spec in self.catalogue.devices[device].metrics:
            if spec.needs_unit:
                reported = last.get(spec.alias)
                if reported is None or reported.unit is None:
                    return False
        return True

    def _unit_changed(
        self, device: str, changed: Iterable[tuple[MetricSpec, Reported, int | None]]
    ) -> bool:
        units = self._units[device]
        return any(
            reported.unit is not None and units.get(spec.alias) != reported.unit
            for spec, reported, _ in changed
        )

    def ddata(
        self,
        device: str,
        changed: Iterable[tuple[MetricSpec, Reported, int | None]],
        *,
        historical: bool,
        now_ms: int,
    ) -> Message:
        """A DDATA of ``(metric, reported, quality before)``; aliases only, no names."""
        payload = payloads.new_payload(now_ms)
        for spec, reported, before in changed:
            metric = payload.metrics.add()
            metric.alias = spec.alias
            metric.timestamp = reported.time_ms
            if historical:
                metric.is_historical = True
            fill(metric, spec, reported)
            if reported.quality != QUALITY_GOOD or before != QUALITY_GOOD:
                payloads.set_property(metric, payloads.QUALITY, SpType.INT32, reported.quality)
        return self._message(self.topics.device("DDATA", device), payload)

    def record(
        self, device: str, spec: MetricSpec, reported: Reported
    ) -> tuple[MetricSpec, Reported, int | None]:
        """Take ``reported`` as the metric's last value; with the quality it had before."""
        last = self._last[device]
        before = last.get(spec.alias)
        last[spec.alias] = reported
        return spec, reported, None if before is None else before.quality

    def _changes(
        self, metrics: DeviceMetrics, samples: Sequence[Sample]
    ) -> list[tuple[MetricSpec, Reported, int | None]]:
        """The metrics of the cycle that changed beyond their deadband, recorded as reported."""
        last = self._last[metrics.device]
        changed = []
        for sample in samples:
            spec = metrics.of_point.get(sample.point)
            if spec is None:
                continue
            for target, reported in readings(metrics, spec, sample):
                if differs(target, last.get(target.alias), reported):
                    changed.append(self.record(metrics.device, target, reported))
        return changed

    def _care_changes(
        self, metrics: DeviceMetrics, now_ms: int
    ) -> list[tuple[MetricSpec, Reported, int | None]]:
        """The care metrics that differ, recorded, once the book's version moved."""
        device = metrics.device
        if not metrics.care or self.care is None or not self.care.tracked(device):
            return []
        version = self.care.version(device)
        if self._care_versions.get(device) == version:
            return []
        self._care_versions[device] = version
        report = self.care.report(device)
        last = self._last[device]
        changed = []
        for spec in metrics.care:
            if report is None:  # not assessed yet: no current reading
                reported = Reported(None, QUALITY_STALE, now_ms)
            else:
                value = CARE_VALUES[spec.care or ""](report)
                reported = Reported(value, QUALITY_GOOD, payloads.epoch_ms(report.assessed_at))
            if differs(spec, last.get(spec.alias), reported):
                changed.append(self.record(device, spec, reported))
        return changed

    def _message(self, topic: str, payload: Payload) -> Message:
        return Message(topic=topic, payload=payload.SerializeToString(), qos=0)
