"""The ``GATEWAY_*`` variables: which ones pydantic-settings may apply, problems with the rest."""

from __future__ import annotations

import json
from typing import (
    TYPE_CHECKING,
    Any,
    get_origin,
)

from gateway.config.model import ENV_NESTED_DELIMITER, ENV_PREFIX, GatewayConfig
from gateway.config.problems import Problem

if TYPE_CHECKING:
    from collections.abc import Mapping


def usable_environment(environ: Mapping[str, str]) -> tuple[dict[str, str], list[Problem]]:
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


def deep_merge(base: Mapping[str, Any], override: Mapping[str, Any]) -> dict[str, Any]:
    """``override`` on top of ``base``, mappings merged key by key (as pydantic-settings does)."""
    merged = dict(base)
    for key, value in override.items():
        current = merged.get(key)
        if isinstance(current, dict) and isinstance(value, dict):
            merged[key] = deep_merge(current, value)
        else:
            merged[key] = value
    return merged
