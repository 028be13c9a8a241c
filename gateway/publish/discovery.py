"""Home Assistant MQTT discovery: the retained config messages that make a sensor a device.

Pure: the MQTT sink calls :func:`discovery_messages` when a device comes online or its
identity or units change, and :func:`removal_messages` to take the entities away again.
Each configured device becomes one Home Assistant device with

- a ``sensor`` per numeric process or diagnostics point, reading the plain value topic
  ``{base}/{device}/{point}``;
- a ``binary_sensor`` per named bit of its status words, reading
  ``{base}/{device}/status/{flag}`` (``true``/``false``);

all of them unavailable unless both ``{base}/status`` and ``{base}/{device}/availability``
say ``online``. Config topics are ``{prefix}/{component}/{gateway_id}_{device}/{object}/config``;
payloads are compact JSON with sorted keys, so identical inputs give identical bytes and the
sink can skip republishing what Home Assistant already has.

Home Assistant says ``online`` on ``{prefix}/status`` when it (re)starts (its birth message);
:class:`ReannounceGate` decides which of those messages ask for the configs again, and how
long to wait first (a random time, so that a plant's gateways do not all answer at once).
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass
from types import MappingProxyType
from typing import TYPE_CHECKING, Final

from gateway import __version__
from gateway.errors import ConfigError
from gateway.profiles.model import PollGroup
from gateway.publish.message import Message
from gateway.wire.codec import BITFIELD_TYPES, NUMERIC_TYPES

if TYPE_CHECKING:
    import random
    from collections.abc import Iterable, Mapping

    from gateway.profiles.model import Point, Profile

DEFAULT_PREFIX: Final = "homeassistant"
# Home Assistant's birth message: ``online`` on ``{prefix}/status``, QoS 0, not retained by
# default (Home Assistant's MQTT documentation, "Birth and last will messages"); its last
# will says ``offline`` there.
HA_ONLINE: Final = b"online"
ORIGIN: Final = MappingProxyType({"name": "rs485-sensor-gateway", "sw_version": __version__})

# Entity category of the sensors each poll group yields; groups not listed yield none.
_SENSOR_GROUPS: Final = MappingProxyType(
    {PollGroup.PROCESS: None, PollGroup.DIAGNOSTICS: "diagnostic"}
)

# Home Assistant sensor device classes by the point's fixed unit, only pairs that Home
# Assistant accepts (its sensor device-class unit table). Points whose unit comes from a
# register (oxygen, concentration) never get one: their class must not change with a setting.
_DEVICE_CLASS_BY_UNIT: Final = MappingProxyType(
    {
        "°C": "temperature",
        "hPa": "pressure",
        "mbar": "pressure",
        "ms": "duration",
        "s": "duration",
        "min": "duration",
        "h": "duration",
    }
)

# Units as Home Assistant should show them: saturation and volume percent are percentages.
_HA_UNITS: Final = MappingProxyType({"%sat": "%", "%vol": "%"})

# Manufacturer by the first word of the profile family (``jumo-tecline`` -> JUMO).
_MANUFACTURERS: Final = MappingProxyType({"jumo": "JUMO", "reiss": "Reiss"})

# Device-block keys and the identity points that fill them, first one known wins.
_IDENTITY_KEYS: Final = MappingProxyType(
    {
        "serial_number": ("serial_number",),
        "sw_version": ("software_version", "firmware_version"),
        "hw_version": ("hardware_version",),
    }
)

# Words (whole ``_``-separated parts of a bit name) that make a status bit a problem.
_PROBLEM_WORDS: Final = (
    "invalid",
    "missing",
    "error",
    "overflow",
    "too_high",
    "too_low",
    "out_of_range",
    "out_of_limits",
    "exceeded",
    "recommended",
    "timeout",
    "fault",
    "failure",
    "alarm",
    "warning",
)

_ACRONYMS: Final = MappingProxyType({"cip": "CIP", "sip": "SIP", "pme": "PME"})

# A fault or failed read clears the plain value topic with an empty payload (see publish.mqtt).
# Home Assistant ignores an empty state for numeric sensors and would keep showing the last
# number; "None" sets the state to unknown instead.
_EMPTY_IS_UNKNOWN: Final = "{{ 'None' if value == '' else value }}"

_NOT_SEGMENT: Final = re.compile(r"[^a-zA-Z0-9_-]")
_WILDCARDS: Final = frozenset("+#")


@dataclass(frozen=True, slots=True, kw_only=True)
class _Entity:
    """One Home Assistant entity: a sensor for a point, or a binary sensor for one bit."""

    component: str  # "sensor" or "binary_sensor"
    point: Point
    flag: str | None = None

    @property
    def key(self) -> str:
        """The entity's name within its device: the point, or the point and the bit."""
        return self.point.name if self.flag is None else f"{self.point.name}_{self.flag}"


def discovery_messages(
    *,
    prefix: str = DEFAULT_PREFIX,
    base_topic: str,
    gateway_id: str,
    device: str,
    profile: Profile,
    points: Iterable[str],
    identity: Mapping[str, object],
    units: Mapping[str, str | None],
    qos: int = 1,
) -> list[Message]:
    """Retained discovery configs for one device's entities, sensors first, in address order.

    ``points`` are the names the gateway polls for the device; ``identity`` the identity
    values decoded so far (missing ones are left out of the device block); ``units`` each
    point's current unit, falling back to the profile's fixed unit.

    Example::

        discovery_messages(base_topic="gateway", gateway_id="gateway-pi", device="tank1",
                           profile=get_profile("jumo-digiline-odo-s10"), points=["oxygen"],
                           identity={"serial_number": "12345678"}, units={"oxygen": "mg/l"})
        # -> [Message(topic="homeassistant/sensor/gateway-pi_tank1/oxygen/config", ...)]
    """
    _check_topic(base_topic, key="mqtt.base_topic")
    node = _node_id(prefix=prefix, gateway_id=gateway_id, device=device)
    common: dict[str, object] = {
        "availability": [
            {"topic": topic, "payload_available": "online", "payload_not_available": "offline"}
            for topic in (f"{base_topic}/status", f"{base_topic}/{device}/availability")
        ],
        "availability_mode": "all",
        "device": _device_block(device=device, node=node, profile=profile, identity=identity),
        "origin": dict(ORIGIN),
        "qos": qos,
    }
    messages = []
    for entity in _entities(profile, points):
        if entity.flag is None:
            config = _sensor_config(entity.point, base_topic, device, units)
        else:
            config = _binary_sensor_config(entity.flag, base_topic, device)
        object_id = f"{device}_{entity.flag or entity.point.name}"
        config |= common | {
            "unique_id": f"{node}_{entity.key}",
            "object_id": object_id,  # Home Assistant before 2025.10
            "default_entity_id": f"{entity.component}.{object_id}",  # 2025.10 and later
        }
        payload = json.dumps(config, sort_keys=True, separators=(",", ":"), ensure_ascii=False)
        messages.append(
            Message(
                topic=_config_topic(prefix, entity, node),
                payload=payload.encode(),
                qos=qos,
                retain=True,
            )
        )
    return messages


# Sensor care's entities (the manual: Sensor care), all read from the retained care document
# ``{base}/{device}/care``, all in the diagnostic category: what the sensor needs, not what
# it measures. Key -> (component, config without the topics).
CARE_TOPIC_SUFFIX: Final = "care"
_CARE_ENTITIES: Final[Mapping[str, tuple[str, Mapping[str, object]]]] = MappingProxyType(
    {
        "care_state": (
            "sensor",
            {
                "name": "Care state",
                "device_class": "enum",
                "options": ["ok", "due_soon", "due", "unknown", "maintenance"],
                "value_template": "{{ value_json.state }}",
            },
        ),
        "calibration_due": (
            "binary_sensor",
            {
                "name": "Calibration due",
                "device_class": "problem",
                "value_template": (
                    "{{ 'ON' if value_json.state in ['due', 'maintenance'] else 'OFF' }}"
                ),
            },
        ),
        "calibration_due_date": (
            "sensor",
            {
                "name": "Calibration due date",
                "device_class": "timestamp",
                "value_template": "{{ value_json.due if value_json.due else 'None' }}",
            },
        ),
        "slope_ratio": (
            "sensor",
            {
                "name": "Slope of nominal",
                "unit_of_measurement": "%",
                "state_class": "measurement",
                "value_template": (
                    "{{ (value_json.slope_ratio * 100) | round(1) "
                    "if value_json.slope_ratio is not none else 'None' }}"
                ),
            },
        ),
    }
)


def care_discovery_messages(
    *,
    prefix: str = DEFAULT_PREFIX,
    base_topic: str,
    gateway_id: str,
    device: str,
    profile: Profile,
    identity: Mapping[str, object],
    slope: bool,
    qos: int = 1,
) -> list[Message]:
    """Retained discovery configs of a device's care entities (``slope``: tecLine/Reiss)."""
    node = _node_id(prefix=prefix, gateway_id=gateway_id, device=device)
    messages = []
    for key, (component, entity) in _CARE_ENTITIES.items():
        if key == "slope_ratio" and not slope:
            continue
        object_id = f"{device}_{key}"
        config = dict(entity) | {
            "state_topic": f"{base_topic}/{device}/{CARE_TOPIC_SUFFIX}",
            "entity_category": "diagnostic",
            "availability": [
                {
                    "topic": f"{base_topic}/status",
                    "payload_available": "online",
                    "payload_not_available": "offline",
                }
            ],
            "device": _device_block(device=device, node=node, profile=profile, identity=identity),
            "origin": dict(ORIGIN),
            "qos": qos,
            "unique_id": f"{node}_{key}",
            "object_id": object_id,
            "default_entity_id": f"{component}.{object_id}",
        }
        payload = json.dumps(config, sort_keys=True, separators=(",", ":"), ensure_ascii=False)
        messages.append(
            Message(
                topic=f"{prefix}/{component}/{node}/{key}/config",
                payload=payload.encode(),
                qos=qos,
                retain=True,
            )
        )
    return messages


def removal_messages(
    *,
    prefix: str = DEFAULT_PREFIX,
    gateway_id: str,
    device: str,
    profile: Profile,
    points: Iterable[str],
    qos: int = 1,
) -> list[Message]:
    """Empty retained payloads on the same config topics: Home Assistant drops the entities."""
    node = _node_id(prefix=prefix, gateway_id=gateway_id, device=device)
    return [
        Message(topic=_config_topic(prefix, entity, node), payload=b"", qos=qos, retain=True)
        for entity in _entities(profile, points)
    ]


def status_topic(prefix: str = DEFAULT_PREFIX) -> str:
    """Where Home Assistant says ``online`` and ``offline``: ``{prefix}/status``."""
    return f"{prefix}/status"


@dataclass(frozen=True, slots=True)
class StatusVerdict:
    """What one message on ``{prefix}/status`` asks of the gateway."""

    delay_s: float | None  # the wait before the configs go again; None: nothing to send
    reason: str  # why, in a few words, for the log


class ReannounceGate:
    """Which of Home Assistant's status messages ask for the discovery again, and when.

    Pure: the random wait is drawn from ``rng``, given, so that a test can seed it; the
    listener that owns the gate does the waiting. At most one re-announce waits at a time:
    every gateway of a plant hears the same ``online``, and a second one while a wait runs
    (Home Assistant restarted twice, or two of them on one broker) is answered by the wait
    already under way, which sends every config anyway.

    Only a live ``online`` counts. A *retained* one is an old birth the broker replays when
    the gateway (re)subscribes, not a restart: answering it would send every config again
    at each reconnect, from every gateway at once after a broker restart, for nothing, since
    the configs are retained and the gateway does not forget them across a reconnect. A
    birth that Home Assistant publishes retained still reaches a gateway already subscribed
    as a live message (the broker clears the flag on delivery to an existing subscription:
    MQTT 3.1.1, 3.3.1.3), so it counts like any other. ``offline`` (Home Assistant's last
    will) asks for nothing: the configs wait on the broker for its return.
    """

    def __init__(self, rng: random.Random) -> None:
        """Draw the waits from ``rng``."""
        self._rng = rng
        self._waiting = False

    @property
    def waiting(self) -> bool:
        """Whether a re-announce is waiting (between :meth:`on_status` and :meth:`done`)."""
        return self._waiting

    def on_status(self, payload: bytes, *, retained: bool, delay_max_s: float) -> StatusVerdict:
        """Judge one status message; a delay (uniform in [0, ``delay_max_s``]) starts a wait.

        Example::

            gate = ReannounceGate(random.Random(1))
            gate.on_status(b"online", retained=False, delay_max_s=5.0).delay_s  # 0.67
            gate.on_status(b"online", retained=False, delay_max_s=5.0).delay_s  # None
        """
        if payload != HA_ONLINE:
            return StatusVerdict(None, f"{_shown(payload)}, not online")
        if retained:
            return StatusVerdict(None, "retained: an old birth replayed at subscribing")
        if self._waiting:
            return StatusVerdict(None, "a re-announce already waits")
        self._waiting = True
        return StatusVerdict(self._rng.uniform(0.0, delay_max_s), "Home Assistant (re)started")

    def done(self) -> None:
        """The wait is over (sent, or cancelled): the next ``online`` starts another."""
        self._waiting = False


def _shown(payload: bytes) -> str:
    """A status payload for the log, never more than a line."""
    return repr(payload[:32].decode(errors="replace"))


def is_problem(flag: str) -> bool:
    """Whether a status bit's name reads like a fault or a warning (``cap_missing``: yes)."""
    padded = f"_{flag}_"
    return any(f"_{word}_" in padded for word in _PROBLEM_WORDS)


def entity_name(name: str) -> str:
    """A point or bit name for people: ``cip_cycles_total`` -> ``CIP cycles total``."""
    words = [_ACRONYMS.get(word, word) for word in name.split("_") if word]
    text = " ".join(words)
    return text[:1].upper() + text[1:]


# --- helpers -------------------------------------------------------------------------------


def _entities(profile: Profile, points: Iterable[str]) -> list[_Entity]:
    """The entities of the polled points: sensors first, then one per named status bit."""
    wanted = {profile.point(name).name for name in points}  # unknown names: ConfigError
    polled = [point for point in profile.points if point.name in wanted]
    sensors = [
        _Entity(component="sensor", point=point)
        for point in polled
        if point.group in _SENSOR_GROUPS and point.dtype in NUMERIC_TYPES and point.repeat is None
    ]
    bits = [
        _Entity(component="binary_sensor", point=point, flag=flag)
        for point in polled
        if point.group is PollGroup.STATUS and point.dtype in BITFIELD_TYPES
        for _, flag in sorted(point.format.bits.items())
    ]
    return sensors + bits


def _sensor_config(
    point: Point, base_topic: str, device: str, units: Mapping[str, str | None]
) -> dict[str, object]:
    config: dict[str, object] = {
        "name": entity_name(point.name),
        "state_topic": f"{base_topic}/{device}/{point.name}",
        "state_class": "measurement",
        "value_template": _EMPTY_IS_UNKNOWN,
    }
    unit = units.get(point.name) or point.unit  # a fixed unit needs no entry in ``units``
    if unit:
        config["unit_of_measurement"] = _HA_UNITS.get(unit, unit)
    if point.unit_from is None and unit and (device_class := _DEVICE_CLASS_BY_UNIT.get(unit)):
        config["device_class"] = device_class
    if category := _SENSOR_GROUPS.get(point.group):
        config["entity_category"] = category
    return config


def _binary_sensor_config(flag: str, base_topic: str, device: str) -> dict[str, object]:
    config: dict[str, object] = {
        "name": entity_name(flag),
        "state_topic": f"{base_topic}/{device}/status/{flag}",
        "payload_on": "true",
        "payload_off": "false",
    }
    if is_problem(flag):
        config["device_class"] = "problem"
    else:  # measuring, new_values: how the sensor works, not what an operator watches
        config["entity_category"] = "diagnostic"
    return config


def _device_block(
    *, device: str, node: str, profile: Profile, identity: Mapping[str, object]
) -> dict[str, object]:
    block: dict[str, object] = {"identifiers": [node], "name": device, "model": profile.title}
    if manufacturer := _MANUFACTURERS.get(profile.family.split("-", 1)[0]):
        block["manufacturer"] = manufacturer
    for key, names in _IDENTITY_KEYS.items():
        for name in names:
            text = "" if identity.get(name) is None else str(identity[name]).strip()
            if text:
                block[key] = text
                break
    return block


def _node_id(*, prefix: str, gateway_id: str, device: str) -> str:
    """``{gateway_id}_{device}``, one valid topic segment; checks the topics it joins."""
    _check_topic(prefix, key="mqtt.discovery.prefix")
    if not device or "/" in device or _WILDCARDS & set(device):
        raise ConfigError(f"{device!r} cannot be one MQTT topic level", key="devices")
    gateway = _NOT_SEGMENT.sub("_", gateway_id)
    if not gateway.strip("_"):
        raise ConfigError(f"{gateway_id!r} gives no usable discovery id", key="mqtt.client_id")
    return _NOT_SEGMENT.sub("_", f"{gateway}_{device}")


def _check_topic(topic: str, *, key: str) -> None:
    if not topic or "" in topic.split("/") or _WILDCARDS & set(topic):
        raise ConfigError(f"{topic!r} is not a topic: no wildcards and no empty levels", key=key)


def _config_topic(prefix: str, entity: _Entity, node: str) -> str:
    return f"{prefix}/{entity.component}/{node}/{entity.key}/config"


__all__ = [
    "CARE_TOPIC_SUFFIX",
    "DEFAULT_PREFIX",
    "HA_ONLINE",
    "ORIGIN",
    "ReannounceGate",
    "StatusVerdict",
    "care_discovery_messages",
    "discovery_messages",
    "entity_name",
    "is_problem",
    "removal_messages",
    "status_topic",
]
