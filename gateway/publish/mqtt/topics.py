"""What MQTT sends where: value topics, status bits, state documents, availability, discovery.

Every message of the contract that a sample or a device event becomes is built here or by
the parts :class:`Topics` holds (the state documents: :mod:`.state_document`; the Home
Assistant announcements: :mod:`.announcements`), and nothing here touches the broker:
:class:`Topics` turns one device's poll cycle into its messages, in the order they go out,
and the connection sends them as they are (topic, payload, QoS, retain). Kept apart from
the connection so that what a subscriber sees can be read, and changed, without the
reconnect loop and the in-flight window in the way.

A value in fault or unreadable is never published as a number: its plain topic is cleared
(an empty retained payload, so no stale number lingers) and the state document names the
fault.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from typing import TYPE_CHECKING

import orjson

from gateway.config import PublishMode, PublishSettings
from gateway.line.samples import Quality, json_value
from gateway.publish.discovery import CARE_TOPIC_SUFFIX
from gateway.publish.message import Message
from gateway.publish.mqtt.announcements import Announcements
from gateway.publish.mqtt.state_document import StateDocuments
from gateway.wire.codec import BitfieldValue

if TYPE_CHECKING:
    from collections.abc import Iterable, Mapping, Sequence

    from gateway.config import MqttConfig
    from gateway.line.samples import DeviceEvent, Sample
    from gateway.profiles import Profile
    from gateway.shared.state import GatewayState


@dataclass(slots=True)
class _Published:
    """What was last published on a value topic, for the change and deadband modes."""

    value: object
    at: float


def _payload(value: object) -> str:
    """A plain value as text: numbers as numbers, true/false, labels, ISO date-times."""
    data = json_value(value)  # type: ignore[arg-type]
    if isinstance(data, bool):
        return "true" if data else "false"
    if isinstance(data, dict):
        return str(value.raw) if isinstance(value, BitfieldValue) else json.dumps(data)
    return "" if data is None else str(data)


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
        self.announcements = Announcements(settings, state, client_id=client_id)
        self.documents = StateDocuments(settings, state)
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
        messages.append(self.documents.build(first.bus, first.device, first.time))
        if self.settings.discovery.enabled:
            messages.extend(self.announcements.cycle(first.bus, first.device, samples))
        self._care(first.bus, first.device, messages)
        return messages

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
            messages.extend(self.announcements.care(bus, device, report))

    def announced(self) -> list[Message]:
        """Every discovery config announced and still standing, as it was sent (retained)."""
        return self.announcements.announced()

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
        return availability + self.announcements.announced()

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
        clear += self.announcements.replan(bus, device, profile, dropped)
        self.documents.replanned(device)
        for topic in clear:
            self._last.pop(topic, None)
        return [
            Message(topic=topic, payload=b"", qos=self.settings.qos, retain=True) for topic in clear
        ]

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
        clear += self.announcements.forget(
            bus, device, profile, points, care_sent=device in self._care_sent
        )
        self._care_sent.pop(device, None)
        self.documents.forget(device)
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
