"""The models of the config file: buses, devices and their points, and the whole file.

:class:`GatewayConfig` gathers every section; the sections other than buses and devices
have their own modules beside this one (``config/mqtt``, ``feeds``, ``sparkplug``,
``prometheus``, ``web``, ``shared_bus``, ``care``, ``verification``).

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
)
from pydantic_settings import (
    BaseSettings,
    EnvSettingsSource,
    PydanticBaseSettingsSource,
    SettingsConfigDict,
)

from gateway.config.care import CareConfig, CareSettings
from gateway.config.echo import EchoMode, echo_words
from gateway.config.feeds import FeedConfig  # noqa: TC001 - pydantic resolves it at run time
from gateway.config.fields import Seconds  # noqa: TC001 - pydantic resolves it at run time
from gateway.config.flash_policy import FlashPolicy
from gateway.config.mqtt import CommandsConfig, MqttConfig
from gateway.config.network import MBAP_URL_SCHEME, TcpSettings, tcp_for_network_port
from gateway.config.prometheus import PrometheusConfig
from gateway.config.rs485 import Rs485Config  # noqa: TC001 - pydantic resolves it at run time
from gateway.config.shared_bus import SharedBusConfig
from gateway.config.sparkplug import SparkplugConfig
from gateway.config.verification import VerificationConfig
from gateway.config.web import WebConfig
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


BusName = Annotated[str, Field(min_length=1, max_length=_MAX_NAME), AfterValidator(_bus_name)]
DeviceName = Annotated[str, Field(min_length=1, max_length=_MAX_NAME), AfterValidator(_device_name)]
ResponseTimeout = Annotated[float, Field(gt=0, le=MAX_RESPONSE_TIMEOUT_S)]
Retries = Annotated[int, Field(ge=0, le=10)]


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
