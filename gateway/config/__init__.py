"""The gateway's configuration: a YAML file, ``GATEWAY_*`` overrides, every problem located.

The models live in :mod:`gateway.config.model`; reading a file in
:mod:`gateway.config.loading` (YAML with lines in :mod:`~gateway.config.yaml_lines`, the
environment in :mod:`~gateway.config.environment`, the cross-field checks in
:mod:`~gateway.config.checks`, problems located by :mod:`~gateway.config.locate` as
:mod:`~gateway.config.problems`); the flash-write permission the models hand to the write
guard in :mod:`gateway.config.flash_policy`. Import from here.
"""

from gateway.config.brokers import MqttServer, TlsConfig
from gateway.config.feeds import FeedConfig, FeedSource
from gateway.config.fields import MAX_INTERVAL_S, Seconds, TcpPort
from gateway.config.flash_policy import FlashPolicy
from gateway.config.loading import check_config, load_config, parse_config, review_config
from gateway.config.model import (
    BAUDRATES,
    DEFAULT_FLASH_WRITE_BUDGET,
    ENV_NESTED_DELIMITER,
    ENV_PREFIX,
    MAX_MIN_RESPONSE_TIME_MS,
    MAX_RESPONSE_TIMEOUT_S,
    SERIAL_URL_SCHEMES,
    BusConfig,
    BusName,
    Cadence,
    DeviceConfig,
    DeviceName,
    GatewayConfig,
    LoggingConfig,
    PointSchedule,
    PointSettings,
    PublishMode,
    PublishSettings,
    ResponseTimeout,
    Retries,
)
from gateway.config.mqtt import CommandsConfig, DiscoveryConfig, MqttConfig
from gateway.config.problems import ConfigProblems, Problem
from gateway.config.prometheus import PrometheusConfig
from gateway.config.rs485 import Rs485Config
from gateway.config.sparkplug import SparkplugConfig
from gateway.config.web import WebConfig

__all__ = [
    "BAUDRATES",
    "DEFAULT_FLASH_WRITE_BUDGET",
    "ENV_NESTED_DELIMITER",
    "ENV_PREFIX",
    "MAX_INTERVAL_S",
    "MAX_MIN_RESPONSE_TIME_MS",
    "MAX_RESPONSE_TIMEOUT_S",
    "SERIAL_URL_SCHEMES",
    "BusConfig",
    "BusName",
    "Cadence",
    "CommandsConfig",
    "ConfigProblems",
    "DeviceConfig",
    "DeviceName",
    "DiscoveryConfig",
    "FeedConfig",
    "FeedSource",
    "FlashPolicy",
    "GatewayConfig",
    "LoggingConfig",
    "MqttConfig",
    "MqttServer",
    "PointSchedule",
    "PointSettings",
    "Problem",
    "PrometheusConfig",
    "PublishMode",
    "PublishSettings",
    "ResponseTimeout",
    "Retries",
    "Rs485Config",
    "Seconds",
    "SparkplugConfig",
    "TcpPort",
    "TlsConfig",
    "WebConfig",
    "check_config",
    "load_config",
    "parse_config",
    "review_config",
]
