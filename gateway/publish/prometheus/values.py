"""The families of values: numbers, faults, status bits, enums, and the age of each point.

Faults are never numbers: a point whose latest sample is a fault has no value sample, and
``gateway_value_fault{fault="overrange"}`` says why. Strings and date-times are left to MQTT.
Only the points of the poll groups selected (:class:`~.selection.Selection`) are exported;
with ``legacy_names`` the values whose family was renamed are also exported under the old
name, as the sensor sent them (:mod:`~gateway.publish.prometheus.legacy`).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Final

from prometheus_client.metrics_core import Metric
from prometheus_client.samples import Sample as PromSample

from gateway.line.samples import Quality
from gateway.publish.prometheus.legacy import legacy_labelled_families, legacy_of
from gateway.publish.prometheus.naming import (
    POINT_LABELS,
    VALUE_LABELS,
    is_log_entry,
    labelled_families,
    naming_of,
)
from gateway.publish.prometheus.selection import Selection
from gateway.wire.codec import BitfieldValue, EnumValue

if TYPE_CHECKING:
    from collections.abc import Callable, Iterator, Sequence

    from gateway.line.samples import Sample
    from gateway.publish.prometheus.naming import ValueNaming
    from gateway.shared.state import GatewayState

_LOGGER = logging.getLogger(__name__)
_Row = Any  # what a lazy family's samples are made from: its own kind of row


class LazySamples:
    """A family's samples, made one at a time as the exposition reads them.

    A large plant's scrape has tens of thousands of samples (16 buses x 16 devices with
    every poll group: some 30,000); made at once as ``prometheus_client`` samples (a named
    tuple and a dict of labels each) they took some 200 bytes each (25 MB for 130,000),
    which the process kept as resident memory after the scrape. Here a family keeps what
    it was built from (the snapshot's own samples) and makes each exposition sample when
    it is read; iterable more than once.
    """

    __slots__ = ("_make", "_rows")

    def __init__(self, rows: Sequence[_Row], make: Callable[[_Row], Iterator[PromSample]]) -> None:
        """``make`` turns one of ``rows`` into its samples (none, one or several)."""
        self._rows = rows
        self._make = make

    def __iter__(self) -> Iterator[PromSample]:
        """Every sample of the family, in the order of the rows."""
        make = self._make
        for row in self._rows:
            yield from make(row)

    def __len__(self) -> int:
        """How many samples there are (made and counted, not kept)."""
        return sum(1 for _ in self)


def lazy_gauge(
    name: str,
    documentation: str,
    rows: Sequence[_Row],
    make: Callable[[_Row], Iterator[PromSample]],
) -> Metric:
    """A gauge family whose samples are made from ``rows`` when read (:class:`LazySamples`)."""
    family = Metric(name, documentation, "gauge")
    family.samples = LazySamples(rows, make)  # type: ignore[assignment] # iterated only
    return family


def _labels(names: Sequence[str], values: Sequence[str]) -> dict[str, str]:
    return dict(zip(names, values, strict=True))


# One value of a family: the sample, its record entry, its unit, the value as exported.
_ValueRow = tuple["Sample", str | None, str | None, float]


@dataclass(slots=True)
class _ValueFamily:
    documentation: str
    entry_label: str | None  # the record entry's label name, for a record's family
    rows: list[_ValueRow] = field(default_factory=list)
    keys: set[tuple[str, str | None]] = field(default_factory=set)  # (device, entry): once
    has_unit: bool = False


def value_families(
    snapshot: GatewayState, now: float, selection: Selection | None = None
) -> Iterator[Metric]:
    """Values, faults, status bits, enums and ages of the selected points' latest samples."""
    selection = selection or Selection()
    values = _Values(legacy=selection.legacy_names)
    for sample in snapshot.latest.values():
        # An old reading is not the present; a point of a group not selected is not exported.
        if _exported(sample, selection) and not snapshot.is_stale(sample, now):
            values.add(sample)
    yield from values.families()
    yield _ages(snapshot, now, selection)


def _exported(sample: Sample, selection: Selection) -> bool:
    """A point of a selected group, and not a log's entry (unless the old names are asked)."""
    if not selection.exports(sample):
        return False
    return selection.legacy_names or not is_log_entry(sample)


class _Values:
    """The value-like families of one scrape, filled sample by sample.

    What is kept is the snapshot's samples (a reference each), sorted into families; the
    exposition's samples are made when the family is read.
    """

    def __init__(self, *, legacy: bool = False) -> None:
        self._legacy = legacy
        self._values: dict[str, _ValueFamily] = {}
        self._faults: list[Sample] = []
        self._flags: list[Sample] = []
        self._enums: list[Sample] = []

    def add(self, sample: Sample) -> None:
        """Export one latest sample: a fault by name, never a number; comms errors not."""
        if sample.quality is Quality.FAULT:
            self._faults.append(sample)
            return
        if sample.quality is not Quality.GOOD:
            return
        value = sample.value
        if isinstance(value, BitfieldValue):
            self._flags.append(sample)
        elif isinstance(value, EnumValue):
            self._enums.append(sample)
        elif isinstance(value, bool | int | float):
            naming, description = naming_of(sample)
            if naming is not None:
                self._add_value(sample, naming, description, naming.convert(float(value)))
            if self._legacy and (old := legacy_of(sample.profile, sample.point)) is not None:
                self._add_value(sample, old[0], old[1], float(value))
        # strings and date-times are not numbers: MQTT carries them

    def _add_value(
        self, sample: Sample, naming: ValueNaming, description: str, value: float
    ) -> None:
        unit: str | None = None
        if naming.from_register:
            if not sample.unit:
                return  # the unit register is unread or unknown: a number without its unit
            unit = sample.unit
        elif naming.fixed_unit is not None:
            unit = naming.fixed_unit
        entry_label, entry = naming.entry if naming.entry is not None else (None, None)
        family = self._values.get(naming.family)
        if family is None:
            family = self._values[naming.family] = _ValueFamily(description, entry_label)
        if (sample.device, entry) in family.keys:
            # Two points of one device named into one family (``x`` in s next to a
            # dimensionless ``x_seconds``): no profile has such a pair; keep the first.
            _LOGGER.debug("%s: %s also maps to %s; left out", sample.device, sample.point, naming)
            return
        family.keys.add((sample.device, entry))
        family.rows.append((sample, entry, unit, value))
        family.has_unit |= unit is not None

    def families(self) -> Iterator[Metric]:
        """One gauge per value family (label names fixed per family), then the rest."""
        labelled = labelled_families()
        if self._legacy:
            labelled |= legacy_labelled_families()
        for name in sorted(self._values):
            family = self._values[name]
            yield _value_family(name, family, with_unit=family.has_unit or name in labelled)
        yield lazy_gauge(
            "gateway_value_fault",
            "1 while the latest sample of a point is a sensor fault (named in 'fault')",
            self._faults,
            _fault_samples,
        )
        yield lazy_gauge(
            "gateway_status_flag",
            "State of one named bit of a status or error word (0 or 1)",
            self._flags,
            _flag_samples,
        )
        yield lazy_gauge(
            "gateway_enum_info",
            "The current label (and code) of an enumerated point; always 1",
            self._enums,
            _enum_samples,
        )


_FAULT_LABELS: Final = (*POINT_LABELS, "fault")
_FLAG_LABELS: Final = (*POINT_LABELS, "flag")
_ENUM_LABELS: Final = (*POINT_LABELS, "label", "code")


def _point(sample: Sample) -> tuple[str, str, str, str]:
    return (sample.bus, sample.device, sample.profile, sample.point)


def _fault_samples(sample: _Row) -> Iterator[PromSample]:
    labels = _labels(_FAULT_LABELS, (*_point(sample), sample.fault or "unknown"))
    yield PromSample("gateway_value_fault", labels, 1.0)


def _flag_samples(sample: _Row) -> Iterator[PromSample]:
    value = sample.value
    assert isinstance(value, BitfieldValue)  # noqa: S101 - sorted so by _Values.add
    point = _point(sample)
    for flag, state in value.flags:
        yield PromSample("gateway_status_flag", _labels(_FLAG_LABELS, (*point, flag)), float(state))


def _enum_samples(sample: _Row) -> Iterator[PromSample]:
    value = sample.value
    assert isinstance(value, EnumValue)  # noqa: S101 - sorted so by _Values.add
    labels = _labels(_ENUM_LABELS, (*_point(sample), value.label, str(value.code)))
    yield PromSample("gateway_enum_info", labels, 1.0)


def _value_family(name: str, family: _ValueFamily, *, with_unit: bool) -> Metric:
    """One value family; its samples made when read."""
    names = (*VALUE_LABELS, *(() if family.entry_label is None else (family.entry_label,)))
    if with_unit:
        names = (*names, "unit")

    def make(row: _ValueRow) -> Iterator[PromSample]:
        sample, entry, unit, value = row
        values: tuple[str, ...] = (sample.bus, sample.device, sample.profile)
        if entry is not None:
            values = (*values, entry)
        if with_unit:
            values = (*values, unit or "")
        yield PromSample(name, _labels(names, values), value)

    return lazy_gauge(name, family.documentation, family.rows, make)


def _ages(snapshot: GatewayState, now: float, selection: Selection) -> Metric:
    def make(item: tuple[tuple[str, str, str], Sample]) -> Iterator[PromSample]:
        (bus, device, point), sample = item
        if not _exported(sample, selection):
            return
        info = snapshot.devices.get((bus, device))
        if info is not None and point in info.intervals and info.intervals[point] is None:
            return  # identity, read once per connection: its age says nothing
        labels = _labels(POINT_LABELS, (bus, device, sample.profile, point))
        yield PromSample("gateway_value_age_seconds", labels, max(0.0, now - sample.monotonic))

    return lazy_gauge(
        "gateway_value_age_seconds",
        "Seconds since the last good sample of a polled point",
        list(snapshot.last_good.items()),
        make,
    )
