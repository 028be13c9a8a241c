"""What MQTT sends where: value topics, status bits, state documents, availability, discovery.

Every message of the contract that a sample or a device event becomes is built here, and
nothing here touches the broker: :class:`Topics` turns one device's poll cycle into its
messages, in the order they go out, and the connection sends them as they are (topic,
payload, QoS, retain). Kept apart from the connection so that what a subscriber sees can be
read, and changed, without the reconnect loop and the in-flight window in the way.

A value in fault or unreadable is never published as a number: its plain topic is cleared
(an empty retained payload, so no stale number lingers) and the state document names the
fault.
"""

from __future__ import annotations

import json
import operator
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

import orjson

from gateway.config import PublishMode, PublishSettings
from gateway.line.samples import Quality, hex_registers, json_value
from gateway.profiles import get_profile
from gateway.publish.discovery import (
    CARE_TOPIC_SUFFIX,
    care_discovery_messages,
    discovery_messages,
)
from gateway.publish.message import Message
from gateway.shared.state import STALE_FACTOR, STALE_MARGIN_S
from gateway.wire.codec import BitfieldValue

if TYPE_CHECKING:
    from collections.abc import Callable, Iterable, Mapping, Sequence
    from datetime import datetime

    from gateway.config import MqttConfig
    from gateway.line.samples import DeviceEvent, Sample
    from gateway.profiles import Profile
    from gateway.shared.state import GatewayState


@dataclass(slots=True)
class _Published:
    """What was last published on a value topic, for the change and deadband modes."""

    value: object
    at: float


# The state document's serialiser. orjson, not the standard library's json, on purpose:
# the document carries every point of the device at every cycle (an H10's 289 points, some
# 20 KB), and json took about 200 µs to encode it where orjson takes 17 µs (bench/README.md,
# "Issue 23's targets, the night's session"). Its text is compact (no spaces after ``:`` and
# ``,``), UTF-8, and a float that is not a number (none reaches it: a value that does not
# decode is a fault) would be ``null``, where json wrote the invalid ``NaN``.
_encode_json = orjson.dumps


def _payload(value: object) -> str:
    """A plain value as text: numbers as numbers, true/false, labels, ISO date-times."""
    data = json_value(value)  # type: ignore[arg-type]
    if isinstance(data, bool):
        return "true" if data else "false"
    if isinstance(data, dict):
        return str(value.raw) if isinstance(value, BitfieldValue) else json.dumps(data)
    return "" if data is None else str(data)


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


class Topics:
    """The contract's messages, built from samples, device events and the gateway state.

    It remembers across cycles only what the contract needs to stay correct: the last value
    sent on each topic (the change and deadband modes), the status bits last sent (a bit is
    sent when it changes), the value topics already cleared for a fault (cleared once, not
    every cycle), the discovery configs each device was announced with (sent again as they
    are when Home Assistant restarts: :meth:`announced`), and each device's document count
    (``seq``, so a subscriber sees a document it missed).
    """

    def __init__(
        self,
        settings: MqttConfig,
        state: GatewayState,
        *,
        client_id: str,
        publish: Mapping[tuple[str, str], PublishSettings] | None = None,
    ) -> None:
        """Take the publish settings per ``(device, point)``; others publish every poll."""
        self.settings = settings
        self.state = state
        self.base = settings.base_topic
        self.client_id = client_id
        # Only the points whose settings are not the default need an entry.
        self._publish = dict(publish or {})
        self._default_publish = PublishSettings()
        self._last: dict[str, _Published] = {}  # the change modes' last publish per topic
        # The status bits last sent, by device, then bit (the profile's name of it: a
        # string shared by every device of the profile, not a topic made per bit).
        self._flags: dict[str, dict[str, bool]] = {}
        self._fault_cleared: set[str] = set()
        # The discovery configs sent, by device: kept (some 1 KB an entity, 42 KB for an
        # H10; built once anyway) so that a re-announce is the retained bytes again, not a
        # rebuild from whatever was read since, and costs the poll loop no JSON encoding
        # just as Home Assistant starts.
        self._discovered: dict[tuple[str, str], list[Message]] = {}
        # The points each device's announcement covers: a point first read after it (a
        # slower rate, or a first read put off by a late line) is announced then.
        self._discovered_points: dict[tuple[str, str], frozenset[str]] = {}
        self._care_announced: dict[str, list[Message]] = {}  # the care entities' configs
        self._sequence: dict[str, int] = {}  # state documents per device since the start
        # Each device's points in the document's order with their intervals, made once.
        self._layouts: dict[str, _DocumentLayout] = {}
        self._care_sent: dict[str, int] = {}  # each device's care version last sent

    def cycle(self, samples: Sequence[Sample]) -> list[Message]:
        """One device's poll cycle as messages, in the order they go out.

        Its values and status bits, its state document, then (at its first cycle, when
        enabled, and again at a cycle with a point the announcement lacks) its Home
        Assistant discovery.
        """
        if not samples:
            return []
        messages: list[Message] = []
        for sample in samples:
            self._value_messages(sample, messages)
        first = samples[0]
        messages.append(self._state_document(first.bus, first.device, first.time))
        if self.settings.discovery.enabled:
            self._announce(first.bus, first.device, samples, messages)
        self._care(first.bus, first.device, messages)
        return messages

    def _announce(
        self, bus: str, device: str, samples: Sequence[Sample], messages: list[Message]
    ) -> None:
        """The device's discovery at its first cycle; a point's when it is first read later.

        A later point adds the configs of its own entities only: those sent are kept as they
        were sent, and are what a restart of Home Assistant gets again.
        """
        covered = self._discovered_points.get((bus, device))
        if covered is not None and all(sample.point in covered for sample in samples):
            return
        sent = self._discovered.setdefault((bus, device), [])
        topics = {message.topic for message in sent}
        added = [m for m in self._discovery(bus, device) if m.topic not in topics]
        known = self.state.device_samples(bus, device).keys()
        self._discovered_points[bus, device] = frozenset(known).union(s.point for s in samples)
        sent.extend(added)
        messages.extend(added)

    def _care(self, bus: str, device: str, messages: list[Message]) -> None:
        """The device's care document (retained), when its content changed since the last.

        The first one also announces the care entities to Home Assistant (if enabled).
        """
        care = self.state.care
        version = care.version(device)
        if version == self._care_sent.get(device, 0):
            return
        report = care.report(device)
        if report is None:
            return
        first = device not in self._care_sent
        self._care_sent[device] = version
        payload = orjson.dumps(report.as_dict())
        messages.append(
            Message(
                topic=f"{self.base}/{device}/{CARE_TOPIC_SUFFIX}",
                payload=payload,
                qos=self.settings.qos,
                retain=True,
            )
        )
        if first and self.settings.discovery.enabled:
            mine = self.state.device_samples(bus, device)
            announced = self._care_announced[device] = care_discovery_messages(
                prefix=self.settings.discovery.prefix,
                base_topic=self.base,
                gateway_id=self.client_id,
                device=device,
                profile=get_profile(report.profile),
                identity={p: s.value for p, s in mine.items() if s.group == "identity" and s.good},
                slope=report.slope_limit is not None,
                qos=self.settings.qos,
            )
            messages.extend(announced)

    def announced(self) -> list[Message]:
        """Every discovery config announced and still standing, as it was sent (retained).

        What Home Assistant is sent again when it restarts: the devices' entities, then the
        care entities. A device a reload changed is left out until its next cycle announces
        it anew; one a reload removed, for good.
        """
        entities = [message for sent in self._discovered.values() for message in sent]
        return entities + [message for sent in self._care_announced.values() for message in sent]

    def for_a_new_server(self) -> list[Message]:
        """What a server without this gateway's retained messages needs first.

        That is, after a switch to another server of ``mqtt.servers``: the discovery
        configs and each device's availability, at once. Separate servers (not a cluster)
        share no retained messages: Home Assistant and every new subscriber there would
        otherwise lack the entities, and a value published on change only (or a status
        bit) until it changed. So the memory of what was sent is dropped: at each device's
        next cycle every value and status bit goes again, as at the start.
        """
        self._last.clear()
        for sent in self._flags.values():
            sent.clear()
        availability = [
            self._message(
                f"{info.name}/availability", "online" if info.online else "offline", retain=True
            )
            for info in list(self.state.devices.values())
            if info.online is not None
        ]
        return availability + self.announced()

    def set_publish(self, publish: Mapping[tuple[str, str], PublishSettings]) -> None:
        """The publish settings per ``(device, point)`` after a reload."""
        self._publish = dict(publish)

    def replan(
        self, bus: str, device: str, profile: Profile, dropped: Iterable[str]
    ) -> list[Message]:
        """A device a reload changed, the same sensor: announced again at its next cycle.

        Home Assistant learns its points as they are now; the retained values and the
        entities of the points it no longer polls (``dropped``) are cleared.
        """
        dropped = tuple(dropped)
        clear = [f"{self.base}/{device}/{point}" for point in dropped]
        if dropped and (bus, device) in self._discovered:
            clear += self._entity_topics(device, profile, dropped)
        self._discovered = {
            known: sent for known, sent in self._discovered.items() if known[1] != device
        }
        self._discovered_points = {
            known: points for known, points in self._discovered_points.items() if known[1] != device
        }
        self._layouts.pop(device, None)
        for topic in clear:
            self._last.pop(topic, None)
        return [
            Message(topic=topic, payload=b"", qos=self.settings.qos, retain=True) for topic in clear
        ]

    def _entity_topics(self, device: str, profile: Profile, points: Iterable[str]) -> list[str]:
        """The discovery topics of the points' Home Assistant entities (to clear them)."""
        announced = discovery_messages(
            prefix=self.settings.discovery.prefix,
            base_topic=self.base,
            gateway_id=self.client_id,
            device=device,
            profile=profile,
            points=points,
            identity={},
            units={},
        )
        return [message.topic for message in announced]

    def forget(
        self, bus: str, device: str, profile: Profile, points: Iterable[str]
    ) -> list[Message]:
        """A device a reload removed: said offline, then every retained topic of it cleared.

        Its values (``points``: those it polled), status bits, state and care documents and
        availability, and its Home Assistant discovery, so that the entities go too. What
        was remembered of it goes: a device added again later starts afresh.
        """
        points = tuple(points)
        clear = [f"{self.base}/{device}/{point}" for point in points] + [
            f"{self.base}/{device}/status/{flag}" for flag in self._flags.pop(device, {})
        ]
        clear += [f"{self.base}/{device}/state", f"{self.base}/{device}/{CARE_TOPIC_SUFFIX}"]
        if (bus, device) in self._discovered or device in self._care_sent:
            clear += self._entity_topics(device, profile, points)
            announced = care_discovery_messages(
                prefix=self.settings.discovery.prefix,
                base_topic=self.base,
                gateway_id=self.client_id,
                device=device,
                profile=profile,
                identity={},
                slope=True,
            )
            clear += [message.topic for message in announced]
        self._discovered.pop((bus, device), None)
        self._discovered_points.pop((bus, device), None)
        self._care_sent.pop(device, None)
        self._care_announced.pop(device, None)
        self._sequence.pop(device, None)
        self._layouts.pop(device, None)
        prefix = f"{self.base}/{device}/"
        for topic in [t for t in self._last if t.startswith(prefix)]:
            del self._last[topic]
        self._fault_cleared = {t for t in self._fault_cleared if not t.startswith(prefix)}
        offline = self._message(f"{device}/availability", "offline", retain=True)
        cleared = [
            Message(topic=topic, payload=b"", qos=self.settings.qos, retain=True) for topic in clear
        ]
        return [offline, *cleared, self._message(f"{device}/availability", "", retain=True)]

    def availability(self, event: DeviceEvent) -> Message:
        """A device's ``online``/``offline`` (retained)."""
        payload = "online" if event.online else "offline"
        return self._message(f"{event.device}/availability", payload, retain=True)

    def _discovery(self, bus: str, device: str) -> list[Message]:
        """Home Assistant discovery for a device, from its identity and units read so far."""
        info = self.state.devices.get((bus, device))
        if info is None:
            return []
        mine = self.state.device_samples(bus, device)
        return discovery_messages(
            prefix=self.settings.discovery.prefix,
            base_topic=self.base,
            gateway_id=self.client_id,
            device=device,
            profile=get_profile(info.profile),
            points=[p for p in info.intervals if p in mine],
            identity={p: s.value for p, s in mine.items() if s.group == "identity" and s.good},
            units={p: s.unit for p, s in mine.items()},
            qos=self.settings.qos,
        )

    def _message(
        self, suffix: str, payload: str, *, retain: bool, qos: int | None = None
    ) -> Message:
        return Message(
            topic=f"{self.base}/{suffix}",
            payload=payload.encode(),
            qos=self.settings.qos if qos is None else qos,
            retain=retain,
        )

    def _value_messages(self, sample: Sample, messages: list[Message]) -> None:
        """Append a sample's value (and status bit) messages to ``messages``."""
        # Made for each message, not kept: tens of thousands of points would keep a string
        # each (some 80 bytes a point), for an f-string's time per message sent.
        topic = f"{self.base}/{sample.device}/{sample.point}"
        value_qos = self.settings.value_qos
        if sample.quality is not Quality.GOOD:
            # No number for a fault or a failed read: clear the retained value once.
            if topic not in self._fault_cleared:
                self._fault_cleared.add(topic)
                self._last.pop(topic, None)
                messages.append(Message(topic=topic, payload=b"", qos=value_qos, retain=True))
            return
        if self._fault_cleared:
            self._fault_cleared.discard(topic)
        settings = (
            self._publish.get((sample.device, sample.point), self._default_publish)
            if self._publish
            else self._default_publish
        )
        value = sample.value
        if settings.mode is PublishMode.EVERY_POLL or self._due(topic, settings, sample):
            if settings.mode is not PublishMode.EVERY_POLL:
                self._last[topic] = _Published(value=value, at=sample.monotonic)
            payload = repr(value) if type(value) is float else _payload(value)
            messages.append(
                Message(topic=topic, payload=payload.encode(), qos=value_qos, retain=True)
            )
        if isinstance(value, BitfieldValue):
            self._flag_messages(sample.device, value, messages)

    def _flag_messages(self, device: str, value: BitfieldValue, messages: list[Message]) -> None:
        """Append a message for each status bit that changed since it was last sent."""
        sent = self._flags.get(device)
        if sent is None:
            sent = self._flags[device] = {}
        for flag, on in value.flags:
            if sent.get(flag) != on:
                sent[flag] = on
                key = f"{device}/status/{flag}"
                messages.append(self._message(key, "true" if on else "false", retain=True))

    def _due(self, topic: str, settings: PublishSettings, sample: Sample) -> bool:
        """Whether a change mode wants this value out now."""
        last = self._last.get(topic)
        if last is None:
            return True
        if sample.monotonic - last.at >= settings.heartbeat_s:
            return True
        if settings.mode is PublishMode.ON_CHANGE:
            return sample.value != last.value
        value, previous = sample.value, last.value
        if isinstance(value, int | float) and isinstance(previous, int | float):
            return abs(value - previous) > settings.deadband
        return value != previous

    def _state_document(self, bus: str, device: str, when: datetime) -> Message:
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
