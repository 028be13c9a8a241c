"""Home Assistant discovery as announced: each device's configs, kept as they were sent.

MQTT discovery tells Home Assistant a device's entities: at its first cycle, and for a
point first read later, its own entities then. The configs sent are kept (some 1 KB an
entity, 42 KB for an H10; built once anyway), so that a re-announce when Home Assistant
restarts is the retained bytes again, not a rebuild from whatever was read since, and
costs the poll loop no JSON encoding just as Home Assistant starts. A reload that changes
a device has it announced anew; one that removes it clears its entities.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from gateway.profiles import get_profile
from gateway.publish.discovery import care_discovery_messages, discovery_messages

if TYPE_CHECKING:
    from collections.abc import Iterable, Sequence

    from gateway.care.report import CareReport
    from gateway.config import MqttConfig
    from gateway.line.samples import Sample
    from gateway.profiles import Profile
    from gateway.publish.message import Message
    from gateway.shared.state import GatewayState


class Announcements:
    """The discovery configs announced per device, and the points each covers."""

    def __init__(self, settings: MqttConfig, state: GatewayState, *, client_id: str) -> None:
        """Announce under ``settings``' prefix and base topic, for the gateway ``client_id``."""
        self.settings = settings
        self.state = state
        self.base = settings.base_topic
        self.client_id = client_id
        self._discovered: dict[tuple[str, str], list[Message]] = {}  # the configs sent
        # The points each device's announcement covers: a point first read after it (a
        # slower rate, or a first read put off by a late line) is announced then.
        self._discovered_points: dict[tuple[str, str], frozenset[str]] = {}
        self._care_announced: dict[str, list[Message]] = {}  # the care entities' configs

    def cycle(self, bus: str, device: str, samples: Sequence[Sample]) -> list[Message]:
        """The device's discovery at its first cycle; a point's when it is first read later.

        A later point adds the configs of its own entities only: those sent are kept as they
        were sent, and are what a restart of Home Assistant gets again.
        """
        covered = self._discovered_points.get((bus, device))
        if covered is not None and all(sample.point in covered for sample in samples):
            return []
        sent = self._discovered.setdefault((bus, device), [])
        topics = {message.topic for message in sent}
        added = [m for m in self._discovery(bus, device) if m.topic not in topics]
        known = self.state.device_samples(bus, device).keys()
        self._discovered_points[bus, device] = frozenset(known).union(s.point for s in samples)
        sent.extend(added)
        return added

    def care(self, bus: str, device: str, report: CareReport) -> list[Message]:
        """The care entities of a device, at its first care document; kept as sent."""
        mine = self.state.device_samples(bus, device)
        announced = self._care_announced[device] = self._care_configs(
            device,
            get_profile(report.profile),
            identity={p: s.value for p, s in mine.items() if s.group == "identity" and s.good},
            slope=report.slope_limit is not None,
        )
        return announced

    def announced(self) -> list[Message]:
        """Every discovery config announced and still standing, as it was sent (retained).

        What Home Assistant is sent again when it restarts: the devices' entities, then the
        care entities. A device a reload changed is left out until its next cycle announces
        it anew; one a reload removed, for good.
        """
        entities = [message for sent in self._discovered.values() for message in sent]
        return entities + [message for sent in self._care_announced.values() for message in sent]

    def replan(self, bus: str, device: str, profile: Profile, dropped: Sequence[str]) -> list[str]:
        """A device a reload changed: announced anew; the topics of ``dropped``'s entities."""
        clear = (
            self.entity_topics(device, profile, dropped)
            if dropped and (bus, device) in self._discovered
            else []
        )
        self._discovered = {
            known: sent for known, sent in self._discovered.items() if known[1] != device
        }
        self._discovered_points = {
            known: points for known, points in self._discovered_points.items() if known[1] != device
        }
        return clear

    def forget(
        self, bus: str, device: str, profile: Profile, points: Sequence[str], *, care_sent: bool
    ) -> list[str]:
        """A device a reload removed: the topics of its entities and care entities, forgotten.

        ``care_sent``: whether a care document of it went out (its care entities may have).
        """
        clear: list[str] = []
        if (bus, device) in self._discovered or care_sent:
            clear += self.entity_topics(device, profile, points)
            announced = self._care_configs(device, profile, identity={}, slope=True)
            clear += [message.topic for message in announced]
        self._discovered.pop((bus, device), None)
        self._discovered_points.pop((bus, device), None)
        self._care_announced.pop(device, None)
        return clear

    def _care_configs(
        self, device: str, profile: Profile, *, identity: dict[str, object], slope: bool
    ) -> list[Message]:
        """The discovery configs of a device's care entities (their topics alone, to clear)."""
        return care_discovery_messages(
            prefix=self.settings.discovery.prefix,
            base_topic=self.base,
            gateway_id=self.client_id,
            device=device,
            profile=profile,
            identity=identity,
            slope=slope,
            qos=self.settings.qos,
        )

    def entity_topics(self, device: str, profile: Profile, points: Iterable[str]) -> list[str]:
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
