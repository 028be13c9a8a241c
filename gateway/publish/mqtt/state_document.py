"""The state document: every point of a device as the gateway sees it, once per cycle.

``{base}/{device}/state`` carries each point's latest value, unit, fault and quality
(``stale`` past its interval), the registers of a value that would not decode, the time
of the cycle and a count (``seq``) by which a subscriber sees a document it missed.
:class:`StateDocuments` builds them for :class:`~gateway.publish.mqtt.topics.Topics`,
with what makes that cheap at every cycle: each device's points in the document's order,
made once.
"""

from __future__ import annotations

import operator
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

import orjson

from gateway.line.samples import Quality, hex_registers, json_value
from gateway.publish.message import Message
from gateway.shared.state import STALE_FACTOR, STALE_MARGIN_S

if TYPE_CHECKING:
    from collections.abc import Callable, Mapping, Sequence
    from datetime import datetime

    from gateway.config import MqttConfig
    from gateway.line.samples import Sample
    from gateway.shared.state import GatewayState

# The state document's serialiser. orjson, not the standard library's json, on purpose:
# the document carries every point of the device at every cycle (an H10's 289 points, some
# 20 KB), and json took about 200 µs to encode it where orjson takes 17 µs (bench/README.md,
# "Issue 23's targets, the night's session"). Its text is compact (no spaces after ``:`` and
# ``,``), UTF-8, and a float that is not a number (none reaches it: a value that does not
# decode is a fault) would be ``null``, where json wrote the invalid ``NaN``.
_encode_json = orjson.dumps


@dataclass(frozen=True, slots=True)
class _DocumentLayout:
    """A device's points in the state document's order, and their intervals: made once.

    Per device some 8 bytes a point (two tuples of references to strings and floats the
    profile and the config hold already); it saves the sort, and a lookup per point, at
    every cycle.
    """

    order: tuple[str, ...]
    intervals: tuple[float | None, ...]  # of each point in ``order``; None: read once
    distinct_intervals: frozenset[float]
    rows: Callable[[Mapping[str, Sample]], Sequence[Sample]]  # the samples in ``order``

    @classmethod
    def of(
        cls, samples: Mapping[str, Sample], intervals: Mapping[str, float | None]
    ) -> _DocumentLayout:
        order = tuple(sorted(samples))
        point_intervals = tuple(intervals.get(point) for point in order)
        rows: Callable[[Mapping[str, Sample]], Sequence[Sample]]
        if len(order) > 1:
            rows = operator.itemgetter(*order)
        elif order:  # itemgetter of one key gives the item itself, not a tuple of one
            only = order[0]
            rows = lambda found: (found[only],)  # noqa: E731 - one of three shapes
        else:  # none recorded yet: itemgetter takes no empty list of keys
            rows = lambda _: ()  # noqa: E731
        return cls(
            order=order,
            intervals=point_intervals,
            distinct_intervals=frozenset(i for i in point_intervals if i is not None),
            rows=rows,
        )


class StateDocuments:
    """Each device's state document; the count of those sent and the layout, per device."""

    def __init__(self, settings: MqttConfig, state: GatewayState) -> None:
        """Build from ``state``'s latest samples, under ``settings``' base topic and QoS."""
        self.settings = settings
        self.state = state
        self.base = settings.base_topic
        self._sequence: dict[str, int] = {}  # state documents per device since the start
        # Each device's points in the document's order with their intervals, made once.
        self._layouts: dict[str, _DocumentLayout] = {}

    def sent(self, device: str) -> int:
        """How many state documents of ``device`` were built since the start (its ``seq``)."""
        return self._sequence.get(device, 0)

    def replanned(self, device: str) -> None:
        """A reload changed the device's points: its layout is made again at its next cycle."""
        self._layouts.pop(device, None)

    def forget(self, device: str) -> None:
        """A reload removed the device: a device added again later counts from one."""
        self._sequence.pop(device, None)
        self._layouts.pop(device, None)

    def build(self, bus: str, device: str, when: datetime) -> Message:
        """Every point's latest value, unit, fault and quality, as the gateway sees them now.

        A value that could not be decoded also has its registers under ``raw`` (a key
        present only then), so a subscriber sees what the sensor sent. Built once per
        cycle: the device's intervals and the clock are read once, not per point.
        """
        values: dict[str, object] = {}
        faults: dict[str, str] = {}
        quality: dict[str, str] = {}
        raw: dict[str, list[str]] = {}
        samples = self.state.device_samples(bus, device)
        layout = self._layouts.get(device)
        if layout is None or len(layout.order) != len(samples):  # points are added, not removed
            info = self.state.devices.get((bus, device))
            layout = self._layouts[device] = _DocumentLayout.of(
                samples, info.intervals if info is not None else {}
            )
        order = layout.order
        rows = layout.rows(samples)
        # A value is stale once older than STALE_FACTOR of its interval (and a margin): one
        # cut-off per distinct interval, a handful per device, not one sum per point.
        now = time.monotonic()
        cutoffs = {
            interval: now - (STALE_FACTOR * interval + STALE_MARGIN_S)
            for interval in layout.distinct_intervals
        }
        good = Quality.GOOD
        for point, sample, interval in zip(order, rows, layout.intervals, strict=True):
            if sample.quality is good:
                value = sample.value
                kind = type(value)
                values[point] = value if kind is float or kind is int else json_value(value)
                stale = interval is not None and sample.monotonic < cutoffs[interval]
                quality[point] = "stale" if stale else "good"
            else:
                faults[point] = sample.fault or sample.quality.value
                quality[point] = sample.quality.value
            if sample.raw:
                raw[point] = hex_registers(sample.raw)
        units = {point: sample.unit for point, sample in zip(order, rows, strict=True)}
        seq = self._sequence[device] = self._sequence.get(device, 0) + 1
        document = {
            "time": when.isoformat(),
            "seq": seq,
            "values": values,
            "units": units,
            "faults": faults,
            "quality": quality,
        }
        if raw:
            document["raw"] = raw
        return Message(
            topic=f"{self.base}/{device}/state",
            payload=_encode_json(document),
            qos=self.settings.qos,
            retain=False,
        )
