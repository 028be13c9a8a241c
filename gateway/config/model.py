"""The models of the config file: buses, devices and their points, feeds and the sinks.

Each model validates its own fields (``extra="forbid"``, bounds in the annotations); what
needs the whole file (unique names, known buses and profiles, timeouts that fit) is
:mod:`gateway.config.checks`, and reading a file with its lines is
:mod:`gateway.config.loading`. Example::

    config = load_config(Path("config/plant.yaml"))
    for bus in config.buses:
        for device in config.devices_on(bus.name):
            device.interval_for("oxygen")  # PointSchedule.every(1.0)
            device.response_timeout(bus)  # None: computed from the profile's timing
"""

from __future__ import annotations

import re
from contextvars import ContextVar
from dataclasses import dataclass
from enum import StrEnum
from pathlib import Path  # noqa: TC003 - pydantic resolves annotations at run time
from typing import (
    TYPE_CHECKING,
    Annotated,
    ClassVar,
    Final,
    Literal,
)
from urllib.parse import urlsplit

from pydantic import (
    AfterValidator,
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Field,
    SecretStr,
    model_validator,
)
from pydantic_settings import (
    BaseSettings,
    EnvSettingsSource,
    PydanticBaseSettingsSource,
    SettingsConfigDict,
)

from gateway.config.brokers import MqttServer, TlsConfig
from gateway.config.care import CareConfig, CareSettings
from gateway.config.echo import EchoMode, echo_words
from gateway.config.flash_policy import FlashPolicy
from gateway.config.network import MBAP_URL_SCHEME, TcpSettings, tcp_for_network_port
from gateway.config.rs485 import Rs485Config  # noqa: TC001 - pydantic resolves it at run time
from gateway.config.shared_bus import SharedBusConfig
from gateway.config.verification import VerificationConfig
from gateway.errors import ConfigError
from gateway.profiles import Point, PollGroup, Profile, get_profile
from gateway.profiles.serial_number import EMPTY_SERIAL
from gateway.wire.codec import WordOrder  # noqa: TC001 - pydantic resolves it at run time
from gateway.wire.timing import LineFormat, Parity

if TYPE_CHECKING:
    from collections.abc import Mapping


ENV_PREFIX: Final = "GATEWAY_"
ENV_NESTED_DELIMITER: Final = "__"

# Standard serial rates from 1200 to 115200 baud (the families use 2400..115200).
BAUDRATES: Final = (1200, 2400, 4800, 9600, 19200, 38400, 57600, 115200)
MAX_RESPONSE_TIMEOUT_S: Final = 5.0
MAX_MIN_RESPONSE_TIME_MS: Final = 500  # digiLine register 0x0305: 0 to 500 ms (S10 manual 4)
DEFAULT_FLASH_WRITE_BUDGET: Final = 4  # flash writes per point and UTC day
MAX_INTERVAL_S: Final = 86_400.0  # a day; longer is a typo, not a polling plan
# URL handlers of pyserial's serial_for_url (serial/urlhandler/protocol_*.py).
SERIAL_URL_SCHEMES: Final = frozenset(
    {"socket", "rfc2217", "loop", "spy", "alt", "hwgrep", "cp2110"}
)
# Beside them, tcp://host:port: a converter in Modbus TCP mode (gateway.line.mbap).
_URL_SCHEMES: Final = SERIAL_URL_SCHEMES | {MBAP_URL_SCHEME}
_NETWORK_SCHEMES: Final = frozenset({"socket", "rfc2217", MBAP_URL_SCHEME})

_BUS_NAME = re.compile(r"[a-z0-9_-]+")
_DEVICE_NAME = re.compile(r"[a-z0-9_]+")
_WINDOWS_PORT = re.compile(r"COM[0-9]+", re.IGNORECASE)
_MAX_NAME = 64

# --- the models -------------------------------------------------------------------------


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


def _bus_name(value: str) -> str:
    if not _BUS_NAME.fullmatch(value):
        raise ValueError(f"{value!r} is not a bus name: use lowercase letters, digits, '_' and '-'")
    return value


def _device_name(value: str) -> str:
    if not _DEVICE_NAME.fullmatch(value):
        raise ValueError(
            f"{value!r} is not a device name: use lowercase letters, digits and '_' "
            "(it becomes part of MQTT topics and metric labels)"
        )
    return value


def _serial_port(value: str) -> str:
    """A device path (``/dev/ttyUSB0``), a pyserial URL (``socket://h:4001``) or ``tcp://h:502``."""
    if "://" in value:
        parts = urlsplit(value)
        if parts.scheme not in _URL_SCHEMES:
            known = ", ".join(f"{scheme}://" for scheme in sorted(_URL_SCHEMES))
            raise ValueError(f"{value!r}: unknown URL scheme {parts.scheme!r}; known: {known}")
        if parts.scheme in _NETWORK_SCHEMES:
            try:
                port = parts.port
            except ValueError:
                port = None
            if not parts.hostname or port is None:
                example = 502 if parts.scheme == MBAP_URL_SCHEME else 4001
                raise ValueError(
                    f"{value!r}: a {parts.scheme}:// URL needs a host and a port, "
                    f"e.g. {parts.scheme}://10.0.0.5:{example}"
                )
        return value
    if value.startswith("/") or _WINDOWS_PORT.fullmatch(value):
        return value
    raise ValueError(
        f"{value!r} is not a port: give a device path such as /dev/ttyUSB0 "
        "or a URL such as socket://10.0.0.5:4001 or tcp://10.0.0.5:502"
    )


def _standard_baudrate(value: int) -> int:
    if value not in BAUDRATES:
        raise ValueError(
            f"{value} is not a standard baud rate; use one of {', '.join(map(str, BAUDRATES))}"
        )
    return value


def _serial_number(value: object) -> object:
    """Text or a whole number (``devices[].serial_number``); never a float or a boolean.

    YAML reads ``1.10`` as a float and ``yes`` as a boolean: either would be compared as
    something the sensor never sent, so they are refused with the remedy instead.
    """
    quote = 'write it in quotes as the sensor reports it, e.g. serial_number: "S19010593"'
    if isinstance(value, bool):
        raise ValueError(  # noqa: TRY004 - pydantic reports ValueError with the key and line
            f"YAML reads this as the boolean {str(value).lower()} (as it does yes, no, on, "
            f"off), not a serial number: {quote}"
        )
    if isinstance(value, float):
        raise ValueError(  # noqa: TRY004
            f"YAML reads this as the number {value!r} (digits lost), not a serial number: {quote}"
        )
    if not isinstance(value, str | int):
        raise ValueError(  # noqa: TRY004
            f"{value!r} is a {type(value).__name__}, not a serial number: {quote}"
        )
    if isinstance(value, int) and value < 0:
        raise ValueError(f"{value} is negative; a serial number is text or a whole number")
    if isinstance(value, str) and not value.strip():
        raise ValueError(EMPTY_SERIAL)
    return value


def _upper(value: object) -> object:
    return value.upper() if isinstance(value, str) else value


def _feed_topic(value: str) -> str:
    if not value or {"+", "#"} & set(value):
        raise ValueError(f"{value!r} is not a topic to read a value from: no wildcards (+, #)")
    return value


def _mqtt_topic(value: str) -> str:
    if not value or value.startswith("/") or value.endswith("/") or {"+", "#"} & set(value):
        raise ValueError(
            f"{value!r} is not a base topic: no wildcards (+, #) and no leading or trailing '/'"
        )
    return value


BusName = Annotated[str, Field(min_length=1, max_length=_MAX_NAME), AfterValidator(_bus_name)]
DeviceName = Annotated[str, Field(min_length=1, max_length=_MAX_NAME), AfterValidator(_device_name)]
Seconds = Annotated[float, Field(gt=0, le=MAX_INTERVAL_S)]
ResponseTimeout = Annotated[float, Field(gt=0, le=MAX_RESPONSE_TIMEOUT_S)]
Retries = Annotated[int, Field(ge=0, le=10)]
TcpPort = Annotated[int, Field(ge=1, le=65535)]


class BusConfig(_Model):
    """One RS485 line, owned by one task.

    Example::

        BusConfig(name="line1", port="/dev/ttyUSB0", baudrate=9600, parity="E")
    """

    name: BusName
    port: Annotated[str, Field(min_length=1), AfterValidator(_serial_port)]
    baudrate: Annotated[int, AfterValidator(_standard_baudrate)] = 9600
    parity: Annotated[Parity, BeforeValidator(_upper)] = "N"
    stopbits: Annotated[int, Field(ge=1, le=2)] = 1
    # Response timeout of the devices on the line; None: each device's answer time on the
    # wire plus its manual's processing time t1 (digiLine: 25 ms + minimum response time).
    timeout: ResponseTimeout | None = None
    retries: Retries = 2  # retries of a failed request
    reconnect_max_s: Annotated[float, Field(gt=0, le=3600)] = 30.0  # cap of the backoff
    # Whether the adapter hears its own transmission (no automatic direction control):
    # "on" reads every request back before its answer, "off" expects none, "auto" decides
    # from the first reads and logs the setting that fits (gateway.line.transports.echo).
    echo: Annotated[EchoMode, BeforeValidator(echo_words)] = EchoMode.AUTO
    rs485: Rs485Config | None = None  # the kernel's RS485 mode (a UART or HAT switched by RTS)
    # socket:// and tcp:// only: keepalive, user timeout, silence, pauses (config.network).
    tcp: Annotated[TcpSettings | None, AfterValidator(tcp_for_network_port)] = None

    @property
    def line(self) -> LineFormat:
        """The line format, for timing (character time, inter-frame gap)."""
        return LineFormat(baudrate=self.baudrate, parity=self.parity, stopbits=self.stopbits)


class PublishMode(StrEnum):
    """When a value is published to MQTT."""

    EVERY_POLL = "every_poll"  # each value read
    ON_CHANGE = "on_change"  # when it differs from the last published one (or heartbeat)
    DEADBAND = "deadband"  # when it moved by more than ``deadband`` (or heartbeat)


class PublishSettings(_Model):
    """How often values go to MQTT: every poll, on change, or beyond a deadband.

    In the change modes a value is published anyway after ``heartbeat_s`` of silence, so a
    subscriber can tell a steady value from a dead gateway.
    """

    mode: PublishMode = PublishMode.EVERY_POLL
    deadband: Annotated[float, Field(ge=0)] = 0.0  # absolute, in the point's unit
    heartbeat_s: Annotated[float, Field(gt=0, le=86_400)] = 300.0


class PointSettings(_Model):
    """Per-point settings of one device: its own interval, or never polled.

    ``enabled: false`` wins over an ``interval`` given next to it, so that a point can
    be switched off and on again without losing its interval. ``publish`` overrides the
    device's publish settings for this point.
    """

    interval: Seconds | None = None
    enabled: bool = True
    publish: PublishSettings | None = None


class Cadence(StrEnum):
    """How a point is read."""

    PERIODIC = "periodic"  # every interval_s seconds
    ON_CONNECT = "on_connect"  # once at start and after every reconnection (identity)
    NEVER = "never"  # switched off in the config


@dataclass(frozen=True, slots=True)
class PointSchedule:
    """When the bus engine reads a point: periodically, on (re)connection, or never.

    Example::

        PointSchedule.every(5.0)  # Cadence.PERIODIC, interval_s 5.0
        PointSchedule.ON_CONNECT  # identity: at start and after reconnection
        PointSchedule.NEVER  # disabled with ``enabled: false``
    """

    cadence: Cadence
    interval_s: float | None = None  # set exactly when the cadence is periodic

    ON_CONNECT: ClassVar[PointSchedule]
    NEVER: ClassVar[PointSchedule]

    def __post_init__(self) -> None:
        """Keep interval and cadence consistent."""
        if (self.cadence is Cadence.PERIODIC) != (self.interval_s is not None):
            raise ValueError("a periodic schedule needs an interval, and only it has one")

    @classmethod
    def every(cls, interval_s: float) -> PointSchedule:
        """Read every ``interval_s`` seconds."""
        return cls(Cadence.PERIODIC, interval_s)

    @property
    def periodic(self) -> bool:
        """Whether the point is read on a fixed interval."""
        return self.cadence is Cadence.PERIODIC


PointSchedule.ON_CONNECT = PointSchedule(Cadence.ON_CONNECT)
PointSchedule.NEVER = PointSchedule(Cadence.NEVER)


class DeviceConfig(_Model):
    """One sensor on a bus, its profile, rates and per-device overrides.

    Example::

        DeviceConfig(name="tank1_oxygen", bus="line1", address=1,
                     profile="jumo-digiline-odo-s10", points={"temperature": {"interval": 5}})
    """

    name: DeviceName
    bus: Annotated[str, Field(min_length=1)]
    address: Annotated[int, Field(ge=1, le=247)]
    profile: Annotated[str, Field(min_length=1)]
    poll_interval: Seconds = 1.0  # process values and status
    # Where in poll_interval its values fall due, as a fraction of it (0.25: a quarter of an
    # interval after the devices at 0); None: spread by the gateway (the manual: poll phases).
    poll_phase: Annotated[float, Field(ge=0, lt=1)] | None = None
    diagnostics_interval: Seconds = 60.0
    configuration_interval: Seconds = 300.0
    points: dict[str, PointSettings] = {}
    float_order: WordOrder | None = None  # None: as the device reports it (0x0307) or the profile's
    timeout: ResponseTimeout | None = None  # None: the bus timeout
    min_response_time_ms: Annotated[int, Field(ge=0, le=MAX_MIN_RESPONSE_TIME_MS)] = 0
    inter_frame_gap_ms: Annotated[float, Field(ge=0, le=1000)] = 0.0
    retries: Retries | None = None  # None: the bus retries
    # The unit id other masters reach it by on the shared bus; None: its address.
    unit_id: Annotated[int, Field(ge=1, le=247)] | None = None
    offline_after: Annotated[int, Field(ge=1, le=1000)] = 3
    publish: PublishSettings = PublishSettings()
    # Flash-backed points that commands may write, by name; every other flash-backed point
    # is refused (RAM and volatile points need no permission).
    flash_writes: list[str] = []
    flash_write_budget: Annotated[int, Field(ge=0, le=1000)] = DEFAULT_FLASH_WRITE_BUDGET
    # The serial number the sensor must report (the manual: pinning serial numbers); None: any.
    serial_number: Annotated[str | int, BeforeValidator(_serial_number)] | None = None
    # Sensor care: this device's calibration interval and limits (the manual: Sensor care).
    care: CareSettings | None = None

    def get_profile(self) -> Profile:
        """The device's register map (a :class:`ConfigError` for an unknown profile id)."""
        return get_profile(self.profile)

    def interval_for(self, point: Point | str) -> PointSchedule:
        """When to read ``point`` (a :class:`Point` or a point name of the device's profile).

        A per-point setting wins; otherwise the point's poll group decides: process values
        and status every ``poll_interval``, diagnostics every ``diagnostics_interval``,
        configuration every ``configuration_interval``, identity on (re)connection only.
        """
        if isinstance(point, str):
            point = self.get_profile().point(point)
        settings = self.points.get(point.name)
        if settings is not None:
            if not settings.enabled:
                return PointSchedule.NEVER
            if settings.interval is not None:
                return PointSchedule.every(settings.interval)
        match point.group:
            case PollGroup.PROCESS | PollGroup.STATUS:
                return PointSchedule.every(self.poll_interval)
            case PollGroup.DIAGNOSTICS:
                return PointSchedule.every(self.diagnostics_interval)
            case PollGroup.CONFIGURATION:
                return PointSchedule.every(self.configuration_interval)
            case PollGroup.IDENTITY:
                return PointSchedule.ON_CONNECT

    def response_timeout(self, bus: BusConfig) -> float | None:
        """Seconds to wait for an answer, when set (``None``: computed by the bus engine).

        The device's or the bus's timeout plus the device's minimum response time; without
        either, the engine takes the answer's wire time + t1 + minimum response time.
        """
        timeout = self.timeout if self.timeout is not None else bus.timeout
        if timeout is None:
            return None
        return timeout + self.min_response_time_ms / 1000

    def retries_on(self, bus: BusConfig) -> int:
        """Retries of a failed request: the device's override, else the bus's."""
        return self.retries if self.retries is not None else bus.retries

    def flash_policy(self) -> FlashPolicy:
        """Which flash-backed points commands may write, and how often per day."""
        return FlashPolicy(
            allowed=frozenset(self.flash_writes), daily_budget=self.flash_write_budget
        )


class CommandsConfig(_Model):
    """Writes over MQTT: ``{base}/{device}/{point}/set`` and ``{base}/{device}/command/{name}``."""

    enabled: bool = True  # False: the gateway only reads; set and command topics are ignored


class FeedSource(_Model):
    """Where a feed's value comes from: a polled point of any device, or an MQTT topic.

    An MQTT payload is a plain number or JSON: a number, or an object whose ``value``
    (or the configured ``key``) is one.
    """

    device: str | None = None
    point: str | None = None
    topic: Annotated[str, AfterValidator(_feed_topic)] | None = None
    key: Annotated[str, Field(min_length=1)] = "value"

    @model_validator(mode="after")
    def _one_kind(self) -> FeedSource:
        by_point = self.device is not None or self.point is not None
        if by_point and self.topic is not None:
            raise ValueError("give either device and point, or topic, not both")
        if not by_point and self.topic is None:
            raise ValueError("give device and point of a polled value, or an MQTT topic")
        if by_point and (self.device is None or self.point is None):
            raise ValueError("a point source needs both device and point")
        return self

    def describe(self) -> str:
        """The source as text for logs and metrics: ``device/point`` or ``mqtt:topic``."""
        return f"mqtt:{self.topic}" if self.topic is not None else f"{self.device}/{self.point}"


class FeedConfig(_Model):
    """Keep a compensation value of a sensor current from another instrument.

    Written every ``interval`` seconds while the source is fresh, and at once when the
    source moves by more than ``deadband`` since the last write. A source older than
    ``max_age`` is not written (the log and the metrics say so). Feeds only write RAM or
    volatile registers; a flash-backed target is a config error.
    """

    device: str
    point: str
    source: FeedSource
    interval: Seconds = 60.0
    deadband: Annotated[float, Field(ge=0)] | None = None
    max_age: Seconds = 300.0

    @property
    def name(self) -> str:
        """The feed as ``device/point``, its label in logs and metrics."""
        return f"{self.device}/{self.point}"


class DiscoveryConfig(_Model):
    """Home Assistant MQTT discovery (opt-in).

    Example::

        DiscoveryConfig(enabled=True, prefix="homeassistant", announce_delay_max_s=5.0)
    """

    enabled: bool = False
    prefix: Annotated[str, AfterValidator(_mqtt_topic)] = "homeassistant"
    announce_delay_max_s: Annotated[
        float,
        Field(
            ge=0,
            le=300,
            description=(
                "Home Assistant's restart (`online` on `{prefix}/status`) reaches every gateway "
                "of a plant at once; each sends its discovery configs again after a random wait "
                "of up to this many seconds, so that tens of gateways do not answer in the same "
                "instant. 5 s by default: the configs are retained, so Home Assistant has its "
                "entities at its start and the re-announce only repairs what a broker lost; "
                "nothing else waits for it, and 5 s spreads tens of gateways apart. 0: at once."
            ),
        ),
    ] = 5.0


class MqttConfig(_Model):
    """The broker connection, topics, quality of service and the store-and-forward queue."""

    enabled: bool = True
    host: Annotated[str, Field(min_length=1)] = "localhost"
    port: TcpPort = 1883
    # Several brokers (or nodes of a cluster), tried in turn; replaces host, port and tls
    # (config.brokers). Empty: the one of host and port.
    servers: list[MqttServer] = []
    # Back to the first server after this long on another; None: stay where it is.
    return_to_first_s: Annotated[float, Field(ge=10, le=86400)] | None = 600.0
    base_topic: Annotated[str, AfterValidator(_mqtt_topic)] = "gateway"
    client_id: str | None = None  # None: gateway-<host name>
    username: str | None = None
    password: SecretStr | None = None  # meant to come from GATEWAY_MQTT__PASSWORD
    qos: Annotated[int, Field(ge=0, le=1)] = 1  # state, status bits, availability, results
    value_qos: Annotated[int, Field(ge=0, le=1)] = 1  # the plain value topics
    tls: TlsConfig | None = None
    clean_session: bool = True  # False: a persistent session on the broker
    keepalive: Annotated[int, Field(ge=5, le=3600)] = 60
    reconnect_max_s: Annotated[float, Field(gt=0, le=3600)] = 30.0
    queue_max: Annotated[int, Field(ge=100, le=10_000_000)] = 100_000  # messages kept offline
    # When messages are written to the queue on disk: "outage", only while the broker is
    # away (nothing is written while connected: an SD card lasts; a kill loses the messages
    # in flight); "always", each before it is sent (a kill loses nothing handed over, for
    # some 30 GB a day of writes at 5 sensors). The manual: What survives a power cut.
    persist: Literal["outage", "always"] = "outage"
    discovery: DiscoveryConfig = DiscoveryConfig()

    def server_list(self) -> list[MqttServer]:
        """The servers to try, in order: ``servers``, or the one of ``host`` and ``port``."""
        return list(self.servers) or [MqttServer(host=self.host, port=self.port, tls=self.tls)]


def _sparkplug_id(value: str) -> str:
    """A Sparkplug group, edge node or host id: one topic level (Sparkplug 3.0, 4.1.1)."""
    if not value or {"/", "+", "#"} & set(value):
        raise ValueError(f"{value!r} is not a Sparkplug id: one topic level, no '/', '+' or '#'")
    return value


SparkplugId = Annotated[str, Field(min_length=1, max_length=64), AfterValidator(_sparkplug_id)]
Deadband = Annotated[float, Field(ge=0)]


# What a Sparkplug host may get of a device besides the poll groups' points: the care
# report the gateway keeps of it (the manual: Sensor care), its metrics under ``care/``.
CARE_GROUP: Final = "care"
_SPARKPLUG_GROUPS: Final = (*(g.value for g in PollGroup), CARE_GROUP)


def _sparkplug_group(value: object) -> object:
    """A poll group (:class:`PollGroup`) or ``care``; anything else named, with the choices."""
    if value == CARE_GROUP or isinstance(value, PollGroup):
        return value
    if isinstance(value, str) and value in _SPARKPLUG_GROUPS:
        return PollGroup(value)
    choices = ", ".join(_SPARKPLUG_GROUPS)
    raise ValueError(f"{value!r} is not a Sparkplug group: one of {choices}")


SparkplugGroup = Annotated[PollGroup | Literal["care"], BeforeValidator(_sparkplug_group)]
SparkplugGroups = Annotated[list[SparkplugGroup], Field(min_length=1)]


class SparkplugConfig(_Model):
    """Sparkplug B: the gateway as an edge node, beside the plain topics (the manual: Sparkplug B).

    It connects to the broker of ``mqtt:`` (host, port, credentials, TLS, keep-alive) with a
    client of its own, whose last will is the NDEATH; ``mqtt.enabled: false`` leaves it on.
    ``deadband`` applies to every Float metric, ``deadbands`` per device and point (in the
    point's unit); a change smaller than it is not reported by exception.

    ``groups`` are the poll groups whose points are metrics (``device_groups`` per device):
    process values and status by default, what a host expects of a sensor. Diagnostics,
    configuration and identity are polled all the same, but each adds to every DBIRTH (an
    H10 with every group is 312 metrics), so a host gets them only when asked for; so is
    ``care``, the sensor care report of each device (``care/state``, ``care/due``, ...).
    ``birth_wait_s`` bounds how long a device's DBIRTH waits for the unit registers its
    metrics take their unit from (tecLine, Reiss): one birth with its units rather than a
    birth without them and another a second later.
    """

    enabled: bool = False
    group_id: SparkplugId = "water"
    edge_node_id: SparkplugId | None = None  # None: the host name
    primary_host_id: SparkplugId | None = None  # None: publish without waiting for a host
    client_id: str | None = None  # None: spb-<group>-<edge node>
    deadband: Deadband = 0.0
    deadbands: dict[str, dict[str, Deadband]] = {}  # device -> point -> deadband
    groups: SparkplugGroups = [PollGroup.PROCESS, PollGroup.STATUS]
    device_groups: dict[str, SparkplugGroups] = {}
    birth_wait_s: Annotated[float, Field(ge=0, le=600)] = 10.0
    queue_max: Annotated[int, Field(ge=100, le=10_000_000)] = 100_000  # messages kept offline
    # Its own server list (config.brokers); empty: the one of ``mqtt:``.
    servers: list[MqttServer] = []
    # With several servers: how long to wait on one for the primary host's STATE online
    # before moving to the next (Eclipse Tahu's edge client waits 30 s).
    host_wait_s: Annotated[float, Field(ge=1, le=3600)] = 30.0
    # A host's STATE online or a rebirth request reaches every edge node of a plant at
    # once: each waits a random time up to this before its births. 0 (the default, one
    # gateway): at once; a fleet sets a few seconds (the manual: A plant of many cabinets).
    birth_delay_max_s: Annotated[float, Field(ge=0, le=60)] = 0.0

    def server_list(self, mqtt: MqttConfig) -> list[MqttServer]:
        """The servers of the edge node's session, in order (its own, else ``mqtt``'s)."""
        return list(self.servers) or mqtt.server_list()


def _prometheus_group(value: object) -> object:
    """A poll group (:class:`PollGroup`); anything else named, with the choices."""
    if isinstance(value, PollGroup):
        return value
    choices = ", ".join(g.value for g in PollGroup)
    if isinstance(value, str) and value in {g.value for g in PollGroup}:
        return PollGroup(value)
    if value == CARE_GROUP:
        raise ValueError(
            "'care' is not a poll group: the care metrics (gateway_care_state, ...) are "
            f"always exported; list poll groups only: {choices}"
        )
    raise ValueError(f"{value!r} is not a poll group: one of {choices}")


PrometheusGroup = Annotated[PollGroup, BeforeValidator(_prometheus_group)]
PrometheusGroups = Annotated[list[PrometheusGroup], Field(min_length=1)]


class PrometheusConfig(_Model):
    """Where ``/metrics`` and ``/healthz`` are served, and what they carry (the manual: Prometheus).

    ``groups`` are the poll groups whose points are series (``device_groups`` per device):
    process values and status by default. Diagnostics, configuration and identity are
    polled all the same and go to MQTT; as series they are some 170 more per O-DO H10 that
    rarely change, so Prometheus gets them only when asked for. The gateway's own health,
    sensor care and ``gateway_device_info`` are always exported. ``legacy_names: true``
    exports the values whose names changed (base units, no ``_total`` on gauges, no log
    entries as families) under their old names too, for one release. Example::

        prometheus: {port: 9108, groups: [process, status, diagnostics]}
    """

    enabled: bool = True
    port: TcpPort = 9108
    host: Annotated[str, Field(min_length=1)] = "0.0.0.0"  # noqa: S104 - the documented default
    groups: PrometheusGroups = [PollGroup.PROCESS, PollGroup.STATUS]
    device_groups: dict[str, PrometheusGroups] = {}  # device -> its own groups
    legacy_names: bool = False  # also the old names (until the next release)


def _sha256_hex(value: str | None) -> str | None:
    if value is not None and not re.fullmatch(r"[0-9a-fA-F]{64}", value):
        raise ValueError("expected a SHA-256 digest as 64 hexadecimal digits")
    return value.lower() if value is not None else None


_HOST_LABEL = r"(?!-)[a-z0-9-]{1,63}(?<!-)"
_HOST_NAME = re.compile(rf"(?:\*\.)?{_HOST_LABEL}(?:\.{_HOST_LABEL})*\.?")


def _host_name(value: str) -> str:
    """A host name (or ``*.`` and a domain) as the page's ``Host`` header may carry it."""
    name = value.strip().lower()
    if "://" in name or "/" in name:
        raise ValueError(f"{value!r}: a host name only, without scheme or path")
    if name.count(":") == 1 or (name.startswith("[") and "]:" in name):
        raise ValueError(f"{value!r}: a host name only, without a port")
    if name.startswith("[") and name.endswith("]"):
        name = name[1:-1]
    if ":" in name or re.fullmatch(r"[0-9.]+", name):
        return name  # an address: checked as one by the page
    if not _HOST_NAME.fullmatch(name):
        raise ValueError(f"{value!r} is not a host name (letters, digits, '-' and '.')")
    return name.rstrip(".")


class WebConfig(_Model):
    """The commissioning and calibration page in the browser (off unless enabled).

    Reading is open to this machine only (loopback); from elsewhere, and for any write or
    calibration, the page asks the user to sign in: by name, as one of the users of the
    users file (``gateway users add NAME --role operator``; ``users_file``, by default
    ``users.json`` in ``state_dir``), or with the one shared password of a plant without
    accounts, meant to come from the environment (``GATEWAY_WEB__PASSWORD``). Without
    users and a password, the page is read-only. Example::

        web: {enabled: true, port: 8080}  # http://127.0.0.1:8080/
        web: {enabled: true, host: 0.0.0.0, allowed_hosts: [gateway.plant.example]}
        web: {enabled: true, users_file: /etc/rs485-gateway/users.json}
    """

    enabled: bool = False
    host: Annotated[str, Field(min_length=1)] = "127.0.0.1"
    port: TcpPort = 8080
    password: SecretStr | None = None
    # The shared password as its SHA-256, for configs written before the users file: a
    # fast hash, kept only for compatibility (a stolen config gives a guesser billions of
    # tries a second). The gateway keeps it as a scrypt hash in memory; named users in
    # the users file (slow salted hashes, a name on every record) are the way to go.
    password_sha256: Annotated[str | None, AfterValidator(_sha256_hex)] = None
    # The page's named users and their roles (``gateway users``); None: users.json in
    # state_dir. A file that does not exist means no named users.
    users_file: Path | None = None
    session_minutes: Annotated[float, Field(gt=0, le=24 * 60)] = 30.0
    # The names the page answers to in ``Host`` (besides the listen address, and localhost
    # from this machine): a name not listed is a DNS-rebinding attempt, refused with 421.
    allowed_hosts: list[Annotated[str, AfterValidator(_host_name)]] = []
    # A calibration waiting for the operator's "write" ends after this, nothing written.
    confirm_minutes: Annotated[float, Field(gt=0, le=60)] = 10.0


class ClockConfig(_Model):
    """Whether dates may be written into sensors while the host clock is not synchronised.

    ``set-clock`` and every write of a calibration date stamp are refused until the kernel
    holds the host clock synchronised (NTP: systemd-timesyncd, chrony), since a Raspberry
    Pi boots with the time it last saved. ``trust_unsynchronised: true`` is for a plant
    without time sync whose clock is set by hand (the manual: A clock you can trust)::

        clock: {trust_unsynchronised: true}
    """

    trust_unsynchronised: bool = False


class LoggingConfig(_Model):
    """Log level and format."""

    level: Annotated[Literal["DEBUG", "INFO", "WARNING", "ERROR"], BeforeValidator(_upper)] = "INFO"
    format: Literal["text", "json"] = "text"


# The environment mapping a load reads, when a caller gives one (tests, embedding);
# ``None``: os.environ. Set only for the duration of one load by :func:`parse_config`.
ENVIRON: ContextVar[Mapping[str, str] | None] = ContextVar("gateway_config_environ", default=None)


class EnvironSource(EnvSettingsSource):
    """``GATEWAY_*`` variables from an explicit mapping, or from os.environ."""

    def __init__(self, settings_cls: type[BaseSettings], environ: Mapping[str, str] | None) -> None:
        """Read ``environ``'s variables for ``settings_cls`` (``None``: os.environ)."""
        super().__init__(settings_cls)
        if environ is not None:
            # Names are matched case-insensitively, as the stock source does on os.environ.
            self.env_vars = {name.lower(): value for name, value in environ.items()}


class GatewayConfig(BaseSettings):
    """The whole configuration: buses, devices and the sinks.

    Build it with :func:`load_config`, which adds the line numbers and the cross-field
    checks; constructing it directly validates the fields only.
    """

    model_config = SettingsConfigDict(
        env_prefix=ENV_PREFIX,
        env_nested_delimiter=ENV_NESTED_DELIMITER,
        case_sensitive=False,
        extra="forbid",
        frozen=True,
    )

    buses: Annotated[list[BusConfig], Field(min_length=1)]
    devices: list[DeviceConfig] = []
    mqtt: MqttConfig = MqttConfig()
    prometheus: PrometheusConfig = PrometheusConfig()
    web: WebConfig = WebConfig()
    logging: LoggingConfig = LoggingConfig()
    commands: CommandsConfig = CommandsConfig()
    feeds: list[FeedConfig] = []
    shared_bus: SharedBusConfig = SharedBusConfig()
    verification: VerificationConfig = VerificationConfig()
    sparkplug: SparkplugConfig = SparkplugConfig()
    care: CareConfig = CareConfig()
    clock: ClockConfig = ClockConfig()
    # Where the gateway keeps what must survive a restart (the MQTT queue, write counters);
    # None: $STATE_DIRECTORY (systemd), else ./state.
    state_dir: Path | None = None

    @classmethod
    def settings_customise_sources(
        cls,
        settings_cls: type[BaseSettings],
        init_settings: PydanticBaseSettingsSource,
        env_settings: PydanticBaseSettingsSource,  # noqa: ARG003 - replaced below
        dotenv_settings: PydanticBaseSettingsSource,  # noqa: ARG003 - no .env files
        file_secret_settings: PydanticBaseSettingsSource,  # noqa: ARG003 - no secrets dir
    ) -> tuple[PydanticBaseSettingsSource, ...]:
        """The environment first (it wins), then the file's content given as keywords.

        The config file is the only file: no ``.env`` and no secrets directory, so that
        what configures the gateway is in one place plus the environment.
        """
        return EnvironSource(settings_cls, ENVIRON.get()), init_settings

    def bus(self, name: str) -> BusConfig:
        """The bus of that name, or a :class:`ConfigError` listing the buses."""
        for bus in self.buses:
            if bus.name == name:
                return bus
        known = ", ".join(bus.name for bus in self.buses)
        raise ConfigError(f"unknown bus {name!r}; buses: {known}", key="buses")

    def devices_on(self, bus_name: str) -> tuple[DeviceConfig, ...]:
        """The devices on a bus, in config order (a :class:`ConfigError` for unknown buses)."""
        self.bus(bus_name)
        return tuple(device for device in self.devices if device.bus == bus_name)
