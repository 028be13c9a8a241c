"""The gateway's configuration: a YAML file, ``GATEWAY_*`` overrides, every problem located.

A config is read in three steps, and each step collects problems rather than stopping at
the first one:

1. YAML, composed node by node so that every mapping key and sequence item keeps its line;
2. validation by the models below, with ``GATEWAY_*`` environment variables layered over
   the file by pydantic-settings (``GATEWAY_MQTT__PASSWORD`` sets ``mqtt.password``; the
   environment wins over the file);
3. cross-field checks that need the whole config: bus and device names unique, buses and
   profiles known, one address per device on a bus, per-point settings that name points of
   the device's profile, and response timeouts that fit in the device's poll interval.

:func:`load_config` raises :class:`ConfigProblems` listing all of them, each with its key
path and the line of the offending key; :func:`check_config` returns them instead.

Example::

    config = load_config(Path("config/plant.yaml"))
    for bus in config.buses:
        for device in config.devices_on(bus.name):
            device.interval_for("oxygen")  # PointSchedule.every(1.0)
            device.response_timeout(bus)  # None: computed from the profile's timing

Environment variables: ``GATEWAY_`` + key path in capitals with ``__`` between levels
(``GATEWAY_LOGGING__LEVEL=DEBUG``, ``GATEWAY_PROMETHEUS__PORT=9200``). A top-level key
takes JSON (``GATEWAY_MQTT='{"host": "broker"}'``); the lists ``buses`` and ``devices`` can
only be replaced whole that way, not entry by entry.
"""

from __future__ import annotations

import difflib
import json
import os
import re
import types
from contextvars import ContextVar
from dataclasses import dataclass
from enum import StrEnum
from pathlib import Path  # noqa: TC003 - pydantic resolves annotations at run time
from typing import (
    TYPE_CHECKING,
    Annotated,
    Any,
    ClassVar,
    Final,
    Generic,
    Literal,
    TypeAlias,
    TypeVar,
    Union,
    get_args,
    get_origin,
)
from urllib.parse import urlsplit

import yaml
from pydantic import (
    AfterValidator,
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Field,
    SecretStr,
    ValidationError,
    model_validator,
)
from pydantic_settings import (
    BaseSettings,
    EnvSettingsSource,
    PydanticBaseSettingsSource,
    SettingsConfigDict,
    SettingsError,
)

from gateway.config.flash_policy import FlashPolicy
from gateway.errors import ConfigError
from gateway.profiles import Point, PollGroup, Profile, builtin_profiles, get_profile
from gateway.profiles.model import Storage
from gateway.wire.codec import NUMERIC_TYPES, WordOrder
from gateway.wire.timing import LineFormat, Parity

if TYPE_CHECKING:
    from collections.abc import Iterable, Iterator, Mapping, Sequence

    from pydantic_core import ErrorDetails

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
_NETWORK_SCHEMES: Final = frozenset({"socket", "rfc2217"})

_BUS_NAME = re.compile(r"[a-z0-9_-]+")
_DEVICE_NAME = re.compile(r"[a-z0-9_]+")
_WINDOWS_PORT = re.compile(r"COM[0-9]+", re.IGNORECASE)
_MAX_NAME = 64

_Part: TypeAlias = str | int
_KeyPath: TypeAlias = tuple[_Part, ...]
_M = TypeVar("_M", bound=BaseModel)  # a model validating one list entry


# --- problems ---------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Problem:
    """One thing wrong with a config: where (key path, file line) and what.

    Example::

        Problem("devices[1].address", 14, "address 1 is already used on bus line1 by devices[0]")

    ``line`` is ``None`` where no line applies: a value from the environment, or a key
    missing from the file altogether.
    """

    key: str
    line: int | None
    message: str

    def __str__(self) -> str:
        """``devices[1].address (line 14): message``; parts that are not known are left out."""
        where = self.key
        if self.line is not None:
            where = f"{where} (line {self.line})" if where else f"line {self.line}"
        return f"{where}: {self.message}" if where else self.message


class ConfigProblems(ConfigError):  # noqa: N818 - a collection of problems; public name
    """Every problem found in a config, reported at once, one per line of ``str()``."""

    def __init__(self, problems: Sequence[Problem], *, path: Path | None = None) -> None:
        """Keep the problems; ``key`` and ``line`` are the first problem's."""
        self.problems = list(problems)
        self.path = path
        super().__init__("\n".join(str(problem) for problem in self.problems))
        if self.problems:
            self.key = self.problems[0].key
            self.line = self.problems[0].line


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
    """A device path (``/dev/ttyUSB0``, ``COM3``) or a pyserial URL (``socket://host:4001``)."""
    if "://" in value:
        parts = urlsplit(value)
        if parts.scheme not in SERIAL_URL_SCHEMES:
            known = ", ".join(f"{scheme}://" for scheme in sorted(SERIAL_URL_SCHEMES))
            raise ValueError(f"{value!r}: unknown URL scheme {parts.scheme!r}; known: {known}")
        if parts.scheme in _NETWORK_SCHEMES:
            try:
                port = parts.port
            except ValueError:
                port = None
            if not parts.hostname or port is None:
                raise ValueError(
                    f"{value!r}: a {parts.scheme}:// URL needs a host and a port, "
                    f"e.g. {parts.scheme}://10.0.0.5:4001"
                )
        return value
    if value.startswith("/") or _WINDOWS_PORT.fullmatch(value):
        return value
    raise ValueError(
        f"{value!r} is not a port: give a device path such as /dev/ttyUSB0 "
        "or a URL such as socket://10.0.0.5:4001"
    )


def _standard_baudrate(value: int) -> int:
    if value not in BAUDRATES:
        raise ValueError(
            f"{value} is not a standard baud rate; use one of {', '.join(map(str, BAUDRATES))}"
        )
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
    diagnostics_interval: Seconds = 60.0
    configuration_interval: Seconds = 300.0
    points: dict[str, PointSettings] = {}
    float_order: WordOrder | None = None  # None: as the device reports it (0x0307) or the profile's
    timeout: ResponseTimeout | None = None  # None: the bus timeout
    min_response_time_ms: Annotated[int, Field(ge=0, le=MAX_MIN_RESPONSE_TIME_MS)] = 0
    inter_frame_gap_ms: Annotated[float, Field(ge=0, le=1000)] = 0.0
    retries: Retries | None = None  # None: the bus retries
    offline_after: Annotated[int, Field(ge=1, le=1000)] = 3
    publish: PublishSettings = PublishSettings()
    # Flash-backed points that commands may write, by name; every other flash-backed point
    # is refused (RAM and volatile points need no permission).
    flash_writes: list[str] = []
    flash_write_budget: Annotated[int, Field(ge=0, le=1000)] = DEFAULT_FLASH_WRITE_BUDGET

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


class TlsConfig(_Model):
    """TLS to the broker: a CA to trust and, for client authentication, a certificate."""

    ca: Path | None = None  # CA certificate (PEM); None: the system's trust store
    cert: Path | None = None  # client certificate (PEM)
    key: Path | None = None  # its private key (PEM)


class DiscoveryConfig(_Model):
    """Home Assistant MQTT discovery (opt-in)."""

    enabled: bool = False
    prefix: Annotated[str, AfterValidator(_mqtt_topic)] = "homeassistant"


class MqttConfig(_Model):
    """The broker connection, topics, quality of service and the store-and-forward queue."""

    enabled: bool = True
    host: Annotated[str, Field(min_length=1)] = "localhost"
    port: TcpPort = 1883
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
    discovery: DiscoveryConfig = DiscoveryConfig()


class PrometheusConfig(_Model):
    """Where ``/metrics`` and ``/healthz`` are served."""

    enabled: bool = True
    port: TcpPort = 9108
    host: Annotated[str, Field(min_length=1)] = "0.0.0.0"  # noqa: S104 - the documented default


class LoggingConfig(_Model):
    """Log level and format."""

    level: Annotated[Literal["DEBUG", "INFO", "WARNING", "ERROR"], BeforeValidator(_upper)] = "INFO"
    format: Literal["text", "json"] = "text"


# The environment mapping a load reads, when a caller gives one (tests, embedding);
# ``None``: os.environ. Set only for the duration of one load by :func:`parse_config`.
_ENVIRON: ContextVar[Mapping[str, str] | None] = ContextVar("gateway_config_environ", default=None)


class _EnvironSource(EnvSettingsSource):
    """``GATEWAY_*`` variables from an explicit mapping, or from os.environ."""

    def __init__(self, settings_cls: type[BaseSettings], environ: Mapping[str, str] | None) -> None:
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
    logging: LoggingConfig = LoggingConfig()
    commands: CommandsConfig = CommandsConfig()
    feeds: list[FeedConfig] = []
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
        return _EnvironSource(settings_cls, _ENVIRON.get()), init_settings

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


# --- entry points -----------------------------------------------------------------------


def load_config(path: Path, *, environ: Mapping[str, str] | None = None) -> GatewayConfig:
    """Read, override from the environment (default: os.environ), validate and cross-check.

    Raises :class:`ConfigError` naming the path if the file cannot be read, and
    :class:`ConfigProblems` listing every problem otherwise.
    """
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError(f"cannot read config file {path}: {exc.strerror or exc}") from exc
    except UnicodeDecodeError as exc:
        raise ConfigProblems(
            [Problem("", None, f"{path} is not UTF-8 text: {exc.reason}")], path=path
        ) from exc
    try:
        return parse_config(text, environ=environ)
    except ConfigProblems as exc:
        raise ConfigProblems(exc.problems, path=path) from None


def check_config(path: Path, *, environ: Mapping[str, str] | None = None) -> list[Problem]:
    """Every problem of a config file, without raising; empty when the config is good.

    A file that cannot be read is one problem without key or line.
    """
    try:
        load_config(path, environ=environ)
    except ConfigProblems as exc:
        return exc.problems
    except ConfigError as exc:
        return [Problem("", None, str(exc))]
    return []


def parse_config(text: str, *, environ: Mapping[str, str] | None = None) -> GatewayConfig:
    """Like :func:`load_config`, from the YAML text itself (no file, no I/O)."""
    document = _parse_yaml(text)
    problems = list(document.problems)
    if document.data is None and problems:
        raise ConfigProblems(_sorted(problems))
    data = {} if document.data is None else document.data
    if not isinstance(data, dict):
        message = "the file must be a mapping of the keys " + ", ".join(GatewayConfig.model_fields)
        raise ConfigProblems([Problem("", document.lines.get(()), message)])
    data = _top_level_keys(data, document.lines, problems)
    env, env_problems = _environment(os.environ if environ is None else environ)
    problems.extend(env_problems)
    try:
        overrides = _EnvironSource(GatewayConfig, env)()
    except SettingsError as exc:  # not expected after _environment's checks; still located
        problems.append(Problem("", None, f"environment: {exc}"))
        env, overrides = {}, {}
    locate = _Locator(document.lines, env)

    config: GatewayConfig | None = None
    token = _ENVIRON.set(env)
    try:
        config = GatewayConfig(**data)
    except ValidationError as exc:
        problems.extend(locate.error(error) for error in exc.errors(include_url=False))
    finally:
        _ENVIRON.reset(token)

    merged = _deep_merge(data, overrides)
    problems.extend(locate(path, message) for path, message in _cross_check(merged))
    if problems or config is None:
        raise ConfigProblems(_sorted(problems))
    return config


# --- YAML with lines --------------------------------------------------------------------

_MERGE_TAG = "tag:yaml.org,2002:merge"


@dataclass(frozen=True, slots=True)
class _Document:
    data: object  # None for an empty file or one that is not valid YAML
    lines: dict[_KeyPath, int]  # 1-based line of every mapping key and sequence item
    problems: list[Problem]


def _parse_yaml(text: str) -> _Document:
    loader = yaml.SafeLoader(text)
    index = _LineIndex(loader)
    try:
        node = loader.get_single_node()
        if node is None:
            return _Document(None, {}, [])
        index.lines[()] = node.start_mark.line + 1
        index.walk(node)
        data = loader.construct_document(node)
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark or exc.context_mark
        what = exc.problem or "cannot parse"
        if exc.context:
            what += f" ({exc.context})"
        line = mark.line + 1 if mark is not None else None
        return _Document(None, {}, [Problem("", line, f"not valid YAML: {what}")])
    except yaml.YAMLError as exc:
        return _Document(None, {}, [Problem("", None, f"not valid YAML: {exc}")])
    finally:
        loader.dispose()
    return _Document(data, index.lines, index.problems)


class _LineIndex:
    """The 1-based line of every mapping key and sequence item, by key path.

    Works on the composed node tree, before construction, so that duplicate keys (which
    PyYAML would silently collapse) are still visible and reported.
    """

    def __init__(self, loader: yaml.SafeLoader) -> None:
        self._loader = loader
        self.lines: dict[_KeyPath, int] = {}
        self.problems: list[Problem] = []

    def walk(
        self, node: yaml.Node, path: _KeyPath = (), on_path: frozenset[int] = frozenset()
    ) -> None:
        """Index ``node`` and everything below it."""
        if id(node) in on_path:  # a recursive alias
            return
        on_path |= {id(node)}
        if isinstance(node, yaml.SequenceNode):
            for index, item in enumerate(node.value):
                self.lines[(*path, index)] = item.start_mark.line + 1
                self.walk(item, (*path, index), on_path)
        elif isinstance(node, yaml.MappingNode):
            self._mapping(node, path, on_path)

    def _mapping(self, node: yaml.MappingNode, path: _KeyPath, on_path: frozenset[int]) -> None:
        seen: dict[_Part, int] = {}
        merges: list[yaml.Node] = []
        for key_node, value_node in node.value:
            if key_node.tag == _MERGE_TAG:
                merges.append(value_node)
                continue
            key = self._key(key_node)
            if key is None:
                continue
            line = key_node.start_mark.line + 1
            if key in seen:
                self.problems.append(
                    Problem(
                        _format((*path, key)),
                        line,
                        f"duplicate key; it repeats line {seen[key]}, whose value it would "
                        "silently replace",
                    )
                )
            seen[key] = line
            self.lines[(*path, key)] = line
            self.walk(value_node, (*path, key), on_path)
        # ``<<: *anchor`` merges: keys given explicitly win, as in the constructed data.
        for source in _merge_sources(merges):
            merged = _LineIndex(self._loader)
            merged.walk(source, path, on_path)
            for key_path, line in merged.lines.items():
                if key_path[len(path)] not in seen:
                    self.lines.setdefault(key_path, line)

    def _key(self, node: yaml.Node) -> _Part | None:
        if not isinstance(node, yaml.ScalarNode):
            return None
        key = self._loader.construct_object(node)
        return key if isinstance(key, str | int) else None


def _merge_sources(values: Iterable[yaml.Node]) -> Iterator[yaml.Node]:
    for value in values:
        if isinstance(value, yaml.SequenceNode):
            yield from value.value
        else:
            yield value


def _format(path: Iterable[_Part]) -> str:
    """``devices[1].points.temperature`` from ``("devices", 1, "points", "temperature")``."""
    text = ""
    for part in path:
        if isinstance(part, int):
            text += f"[{part}]"
        else:
            text += f".{part}" if text else part
    return text


# --- the environment --------------------------------------------------------------------


def _environment(environ: Mapping[str, str]) -> tuple[dict[str, str], list[Problem]]:
    """The ``GATEWAY_*`` variables pydantic-settings can apply, and problems with the rest.

    pydantic-settings turns ``GATEWAY_DEVICES__0__ADDRESS`` into a mapping that would
    replace the whole list, and stops at the first top-level variable that is not JSON;
    both become located problems here instead.
    """
    usable: dict[str, str] = {}
    problems: list[Problem] = []
    lists = {
        name
        for name, field in GatewayConfig.model_fields.items()
        if get_origin(field.annotation) is list
    }
    for name, value in environ.items():
        if not name.upper().startswith(ENV_PREFIX):
            continue
        parts = name[len(ENV_PREFIX) :].lower().split(ENV_NESTED_DELIMITER)
        top = parts[0]
        if top not in GatewayConfig.model_fields:
            continue  # not a setting (GATEWAY_CONFIG and the like are for the command line)
        if not value:
            # Empty is unset: Compose passes an unset ${MQTT_PASSWORD} on as "", which
            # would otherwise replace the file's mqtt.username with an empty one.
            continue
        if top in lists and len(parts) > 1:
            problems.append(
                Problem(
                    top,
                    None,
                    f"{name}: entries of {top} cannot be set one by one from the "
                    f"environment; give the whole list as JSON in {ENV_PREFIX}{top.upper()}",
                )
            )
            continue
        if len(parts) == 1:
            try:
                json.loads(value)
            except ValueError as exc:
                problems.append(Problem(top, None, f"{name} must be JSON: {exc}"))
                continue
        usable[name] = value
    return usable, problems


def _deep_merge(base: Mapping[str, Any], override: Mapping[str, Any]) -> dict[str, Any]:
    """``override`` on top of ``base``, mappings merged key by key (as pydantic-settings does)."""
    merged = dict(base)
    for key, value in override.items():
        current = merged.get(key)
        if isinstance(current, dict) and isinstance(value, dict):
            merged[key] = _deep_merge(current, value)
        else:
            merged[key] = value
    return merged


# --- locating problems ------------------------------------------------------------------


class _Locator:
    """Turns key paths into :class:`Problem` values with lines or environment names."""

    def __init__(self, lines: Mapping[_KeyPath, int], env: Mapping[str, str]) -> None:
        self._lines = lines
        self._env = {name.upper(): name for name in env}

    def __call__(self, path: _KeyPath, message: str) -> Problem:
        variable = self._variable(path)
        if variable is not None:
            return Problem(_format(path), None, f"{message} (from {variable})")
        return Problem(_format(path), self._line(path), message)

    def error(self, error: ErrorDetails) -> Problem:
        """A pydantic error as a problem at its key path."""
        path: _KeyPath = tuple(part for part in error["loc"] if part != "[key]")
        return self(path, _describe(error, path))

    def _line(self, path: _KeyPath) -> int | None:
        for end in range(len(path), 0, -1):
            line = self._lines.get(path[:end])
            if line is not None:
                return line
        return None

    def _variable(self, path: _KeyPath) -> str | None:
        for end in range(len(path), 0, -1):
            name = ENV_PREFIX + ENV_NESTED_DELIMITER.join(str(p) for p in path[:end]).upper()
            if name in self._env:
                return self._env[name]
        return None


def _describe(error: ErrorDetails, path: _KeyPath) -> str:
    kind = error["type"]
    if kind == "missing":
        return "required, but missing"
    if kind == "extra_forbidden":
        return _unknown_key(path)
    if kind == "value_error":
        return str(error.get("ctx", {}).get("error", error["msg"]))
    message = error["msg"]
    value = error.get("input")
    secret = any(part == "password" for part in path)
    if not secret and isinstance(value, str | int | float):
        message += f", got {value!r}"
    return message


def _unknown_key(path: _KeyPath) -> str:
    key = str(path[-1]) if path else ""
    model = _model_at(path[:-1])
    allowed = list(model.model_fields) if model is not None else []
    if not allowed:
        return "unknown key"
    close = difflib.get_close_matches(key, allowed, n=1)
    hint = f"; did you mean {close[0]}?" if close else ""
    return f"unknown key {key!r}{hint} (allowed: {', '.join(allowed)})"


def _model_at(path: _KeyPath) -> type[BaseModel] | None:
    """The model that validates the mapping at ``path``, if any."""
    current: Any = GatewayConfig
    for part in path:
        current = _unwrap(current)
        origin = get_origin(current)
        if origin is list:
            current = get_args(current)[0]
        elif origin is dict:
            current = get_args(current)[1]
        elif isinstance(current, type) and issubclass(current, BaseModel):
            field = current.model_fields.get(str(part))
            if field is None:
                return None
            current = field.annotation
        else:
            return None
    current = _unwrap(current)
    return current if isinstance(current, type) and issubclass(current, BaseModel) else None


def _unwrap(annotation: Any) -> Any:  # noqa: ANN401 - walks arbitrary type expressions
    """``X`` from ``Annotated[X, ...]`` and ``X | None``."""
    while True:
        origin = get_origin(annotation)
        if origin is Annotated:
            annotation = get_args(annotation)[0]
        elif origin is Union or origin is types.UnionType:
            options = [arg for arg in get_args(annotation) if arg is not type(None)]
            if len(options) != 1:
                return annotation
            annotation = options[0]
        else:
            return annotation


def _top_level_keys(
    data: Mapping[object, Any], lines: Mapping[_KeyPath, int], problems: list[Problem]
) -> dict[str, Any]:
    """The file's top-level mapping as keyword arguments; other keys become problems.

    Keys that are not strings cannot be keywords, and keys with a leading underscore would
    be taken by pydantic-settings as its own options (``_env_file``), so both are refused.
    """
    kept: dict[str, Any] = {}
    for key, value in data.items():
        if isinstance(key, str) and not key.startswith("_"):
            kept[key] = value
        else:
            line = lines.get((key,)) if isinstance(key, str | int) else None
            problems.append(Problem(str(key), line, _unknown_key((str(key),))))
    return kept


def _sorted(problems: Iterable[Problem]) -> list[Problem]:
    """File order; problems from the environment last."""
    return sorted(problems, key=lambda p: (p.line is None, p.line or 0))


# --- cross-field checks -----------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class _Entry(Generic[_M]):
    """One list entry: its index, its raw mapping and its model if it validates alone."""

    index: int
    raw: Mapping[str, Any]
    model: _M | None

    def text(self, key: str) -> str | None:
        value = self.raw.get(key)
        return value if isinstance(value, str) else None


def _entries(raw: object, model: type[_M]) -> list[_Entry[_M]]:
    if not isinstance(raw, list):
        return []
    entries: list[_Entry[_M]] = []
    for index, item in enumerate(raw):
        if not isinstance(item, dict):
            entries.append(_Entry(index, {}, None))
            continue
        try:
            validated: _M | None = model.model_validate(item)
        except ValidationError:
            validated = None  # its field errors are reported by the full validation
        entries.append(_Entry(index, item, validated))
    return entries


def _cross_check(data: Mapping[str, Any]) -> Iterator[tuple[_KeyPath, str]]:
    """Checks across entries, on every entry that can be checked even if others are broken."""
    buses = _entries(data.get("buses"), BusConfig)
    devices = _entries(data.get("devices"), DeviceConfig)
    yield from _unique_names("buses", buses)
    yield from _unique_names("devices", devices)
    bus_names = list(dict.fromkeys(n for entry in buses if (n := entry.text("name")) is not None))
    bus_models: dict[str, BusConfig] = {}
    for entry in buses:
        if entry.model is not None:
            bus_models.setdefault(entry.model.name, entry.model)
    used: dict[tuple[str, int], _Entry[DeviceConfig]] = {}
    for device in devices:
        here: _KeyPath = ("devices", device.index)
        bus_name = device.text("bus")
        if bus_name is not None and bus_name not in bus_names:
            yield (*here, "bus"), _unknown_bus(bus_name, bus_names)
        profile_id = device.text("profile")
        if profile_id is not None:
            yield from _check_profile(here, profile_id, device.raw.get("points"))
            yield from _check_flash_writes(here, profile_id, device.raw.get("flash_writes"))
        model = device.model
        if model is None:
            continue
        first = used.setdefault((model.bus, model.address), device)
        if first is not device:
            yield (
                (*here, "address"),
                (
                    f"address {model.address} is already used on bus {model.bus} by "
                    f"devices[{first.index}] ({first.text('name')})"
                ),
            )
        bus = bus_models.get(model.bus)
        if bus is not None:
            yield from _check_timeout(here, model, bus)
    mqtt = data.get("mqtt")
    mqtt_on = not isinstance(mqtt, dict) or mqtt.get("enabled", True) is not False
    yield from _check_feeds(_entries(data.get("feeds"), FeedConfig), devices, mqtt_on=mqtt_on)


def _check_flash_writes(
    here: _KeyPath, profile_id: str, names: object
) -> Iterator[tuple[_KeyPath, str]]:
    profile = builtin_profiles().get(profile_id)
    if profile is None or not isinstance(names, list):
        return
    for index, name in enumerate(names):
        if not isinstance(name, str):
            continue
        where: _KeyPath = (*here, "flash_writes", index)
        if not profile.has_point(name):
            yield where, f"profile {profile_id} has no point {name!r}"
            continue
        point = profile.point(name)
        if not point.writable:
            yield where, f"{name} is read-only; it cannot be written at all"
        elif point.storage is not Storage.FLASH:
            yield (
                where,
                f"{name} is a {point.storage} register, not flash-backed: it needs no permission",
            )


def _check_feeds(
    feeds: Sequence[_Entry[FeedConfig]], devices: Sequence[_Entry[DeviceConfig]], *, mqtt_on: bool
) -> Iterator[tuple[_KeyPath, str]]:
    """A feed writes a RAM or volatile point of a known device, from a polled source."""
    by_name = {d.model.name: d.model for d in devices if d.model is not None}
    targets: dict[tuple[str, str], int] = {}
    for feed in feeds:
        model = feed.model
        if model is None:
            continue
        here: _KeyPath = ("feeds", feed.index)
        device = by_name.get(model.device)
        if device is None:
            yield (*here, "device"), f"unknown device {model.device!r}; devices: {_names(by_name)}"
        else:
            yield from _check_feed_target(here, model, device)
        first = targets.setdefault((model.device, model.point), feed.index)
        if first != feed.index:
            yield (*here, "point"), f"{model.name} is already fed by feeds[{first}]"
        yield from _check_feed_source(here, model.source, by_name, mqtt_on=mqtt_on)


def _check_feed_source(
    here: _KeyPath, source: FeedSource, by_name: Mapping[str, DeviceConfig], *, mqtt_on: bool
) -> Iterator[tuple[_KeyPath, str]]:
    if source.topic is not None and not mqtt_on:
        yield (*here, "source", "topic"), "an MQTT source needs MQTT (mqtt.enabled is false)"
    if source.device is None or source.point is None:
        return
    origin = by_name.get(source.device)
    if origin is None:
        yield (
            (*here, "source", "device"),
            f"unknown device {source.device!r}; devices: {_names(by_name)}",
        )
        return
    profile = _profile_or_none(origin.profile)
    if profile is None:
        return
    if not profile.has_point(source.point):
        yield (
            (*here, "source", "point"),
            f"profile {origin.profile} has no point {source.point!r}",
        )
    elif not origin.interval_for(source.point).periodic:
        yield (
            (*here, "source", "point"),
            (
                f"{source.device}/{source.point} is not polled periodically, so it would "
                "never feed anything; give it an interval under the device's points"
            ),
        )


def _check_feed_target(
    here: _KeyPath, feed: FeedConfig, device: DeviceConfig
) -> Iterator[tuple[_KeyPath, str]]:
    profile = _profile_or_none(device.profile)
    if profile is None:
        return
    if not profile.has_point(feed.point):
        yield (*here, "point"), f"profile {device.profile} has no point {feed.point!r}"
        return
    point = profile.point(feed.point)
    if not point.writable:
        yield (*here, "point"), f"{feed.point} is read-only"
    elif point.storage is Storage.FLASH:
        free = [
            p.name
            for p in profile.points
            if p.writable and p.storage is not Storage.FLASH and p.dtype in NUMERIC_TYPES
        ]
        hint = f"; RAM or volatile points of {device.profile}: {', '.join(free)}" if free else ""
        yield (
            (*here, "point"),
            (
                f"a feed never writes to flash, and {feed.point} is flash-backed "
                f"(its cells wear out when written cyclically){hint}"
            ),
        )
    elif point.format.dtype not in NUMERIC_TYPES:
        yield (*here, "point"), f"{feed.point} is a {point.format.dtype}, not a number to feed"


def _profile_or_none(profile_id: str) -> Profile | None:
    return builtin_profiles().get(profile_id)


def _names(models: Mapping[str, object]) -> str:
    return ", ".join(models) or "none"


def _unique_names(section: str, entries: Sequence[_Entry[Any]]) -> Iterator[tuple[_KeyPath, str]]:
    first: dict[str, int] = {}
    for entry in entries:
        name = entry.text("name")
        if name is None:
            continue
        if name in first:
            yield (
                (section, entry.index, "name"),
                (f"name {name} is already used by {section}[{first[name]}]"),
            )
        else:
            first[name] = entry.index


def _unknown_bus(name: str, known: Sequence[str]) -> str:
    if not known:
        return f"unknown bus {name!r}; no bus is defined under buses"
    close = difflib.get_close_matches(name, known, n=1)
    hint = f"did you mean {close[0]}? " if close else ""
    return f"unknown bus {name!r}; {hint}buses: {', '.join(known)}"


def _check_profile(
    here: _KeyPath, profile_id: str, points: object
) -> Iterator[tuple[_KeyPath, str]]:
    profiles = builtin_profiles()
    profile = profiles.get(profile_id)
    if profile is None:
        close = difflib.get_close_matches(profile_id, list(profiles), n=2)
        hint = f"did you mean {' or '.join(close)}? " if close else ""
        yield (
            (*here, "profile"),
            (f"unknown profile {profile_id!r}; {hint}known: {', '.join(sorted(profiles))}"),
        )
        return
    if not isinstance(points, dict):
        return
    names = [point.name for point in profile.points]
    for name in points:
        if isinstance(name, str) and not profile.has_point(name):
            close = (
                difflib.get_close_matches(name, names, n=3, cutoff=0.6)
                or [n for n in names if name in n][:3]
            )
            hint = f"; did you mean {', '.join(close)}?" if close else ""
            yield (
                (*here, "points", name),
                (
                    f"profile {profile_id} has no point {name!r}{hint} "
                    f"(gateway profiles show {profile_id} lists them)"
                ),
            )


def _check_timeout(
    here: _KeyPath, device: DeviceConfig, bus: BusConfig
) -> Iterator[tuple[_KeyPath, str]]:
    timeout = device.response_timeout(bus)
    if timeout is None or timeout <= device.poll_interval:
        return
    if device.timeout is not None:
        key, source = "timeout", f"timeout {device.timeout:g} s"
    else:
        key, source = "poll_interval", f"bus {bus.name} timeout {bus.timeout:g} s"
    if device.min_response_time_ms:
        source += f" + min_response_time_ms {device.min_response_time_ms}"
    yield (
        (*here, key),
        (
            f"the response timeout {timeout:g} s ({source}) is longer than poll_interval "
            f"{device.poll_interval:g} s; raise poll_interval or shorten the timeout"
        ),
    )
