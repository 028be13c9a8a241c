"""The gateway's configuration: a YAML file, ``GATEWAY_*`` overrides, every problem located.

A config is read in three steps, and each step collects problems rather than stopping at
the first one:

1. YAML, composed node by node so that every mapping key and sequence item keeps its line;
2. validation by the models (:mod:`gateway.config.model`), with ``GATEWAY_*`` environment
   variables layered over the file by pydantic-settings (``GATEWAY_MQTT__PASSWORD`` sets
   ``mqtt.password``; the environment wins over the file);
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

import os
from pathlib import Path  # noqa: TC003 - pydantic resolves annotations at run time
from typing import (
    TYPE_CHECKING,
)

from pydantic import (
    ValidationError,
)
from pydantic_settings import (
    SettingsError,
)

from gateway.config.checks import cross_check
from gateway.config.environment import deep_merge, usable_environment
from gateway.config.locate import Locator, in_file_order, top_level_keys
from gateway.config.model import ENVIRON, EnvironSource, GatewayConfig
from gateway.config.problems import ConfigProblems, Problem
from gateway.config.yaml_lines import parse_yaml
from gateway.errors import ConfigError

if TYPE_CHECKING:
    from collections.abc import Callable, Iterable, Mapping

    from gateway.config.problems import KeyPath

    # What a config means on this machine (its ports' names under /dev, ...): warnings
    # by key path, from a floor that may look at the system.
    Advisor = Callable[[GatewayConfig], Iterable[tuple[KeyPath, str]]]


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


def review_config(
    path: Path, *, advise: Advisor, environ: Mapping[str, str] | None = None
) -> tuple[list[Problem], list[Problem]]:
    """The problems of a config file and, if it has none, the warnings ``advise`` finds.

    Warnings are located like problems (key path and line) but change nothing: the
    config loads and runs as it is. ``advise`` looks at the valid config only.
    """
    problems = check_config(path, environ=environ)
    if problems:
        return problems, []
    text = path.read_text(encoding="utf-8")
    config = parse_config(text, environ=environ)
    env, _ = usable_environment(os.environ if environ is None else environ)
    locate = Locator(parse_yaml(text).lines, env)
    return [], [locate(key, message) for key, message in advise(config)]


def parse_config(text: str, *, environ: Mapping[str, str] | None = None) -> GatewayConfig:
    """Like :func:`load_config`, from the YAML text itself (no file, no I/O)."""
    document = parse_yaml(text)
    problems = list(document.problems)
    if document.data is None and problems:
        raise ConfigProblems(in_file_order(problems))
    data = {} if document.data is None else document.data
    if not isinstance(data, dict):
        message = "the file must be a mapping of the keys " + ", ".join(GatewayConfig.model_fields)
        raise ConfigProblems([Problem("", document.lines.get(()), message)])
    data = top_level_keys(data, document.lines, problems)
    env, env_problems = usable_environment(os.environ if environ is None else environ)
    problems.extend(env_problems)
    try:
        overrides = EnvironSource(GatewayConfig, env)()
    except SettingsError as exc:  # not expected after usable_environment's checks; still located
        problems.append(Problem("", None, f"environment: {exc}"))
        env, overrides = {}, {}
    locate = Locator(document.lines, env)

    config: GatewayConfig | None = None
    token = ENVIRON.set(env)
    try:
        config = GatewayConfig(**data)
    except ValidationError as exc:
        problems.extend(locate.error(error) for error in exc.errors(include_url=False))
    finally:
        ENVIRON.reset(token)

    merged = deep_merge(data, overrides)
    problems.extend(locate(path, message) for path, message in cross_check(merged))
    if problems or config is None:
        raise ConfigProblems(in_file_order(problems))
    return config
